"""The odometry self-calibration (export/odometry_calibration.py): SE(3) algebra, the chain
covariances, and the yaw-rate bias found from loop edges on a synthetic drive with a known
bias; its effect on a real drifting drive is tested in tests/test_optimize.py."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from doseqslam_logs.export.odometry_calibration import (
    MIN_LOOP_EDGES,
    adjoint,
    calibrate_odometry,
    calibrated_graph,
    chain_covariances,
)
from doseqslam_logs.export.pose_graph import Edge, PoseGraph
from doseqslam_logs.sources.poses import PoseTrack

F = np.float64


def _exp(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First-order enough for small xi: (R, t) of Exp(xi), xi = (translation, rotation)."""
    return Rotation.from_rotvec(xi[3:]).as_matrix(), xi[:3]


def _compose(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple:
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def _inverse(a: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    return a[0].T, -a[0].T @ a[1]


def _log(a: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    return np.concatenate([a[1], Rotation.from_matrix(a[0]).as_rotvec()])


poses = st.tuples(
    st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    st.lists(st.floats(-20.0, 20.0), min_size=3, max_size=3),
)


@given(poses, st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6))
@settings(max_examples=50, deadline=None)
def test_the_adjoint_moves_a_perturbation_across_a_pose(pose: tuple, direction: list) -> None:
    """T Exp(xi) T^-1 = Exp(Ad(T) xi), to first order in xi."""
    rotation, translation = Rotation.from_rotvec(pose[0]).as_matrix(), np.asarray(pose[1], F)
    xi = 1e-6 * np.asarray(direction, F)
    moved = _compose(_compose((rotation, translation), _exp(xi)), _inverse((rotation, translation)))
    np.testing.assert_allclose(_log(moved), adjoint(rotation, translation) @ xi, atol=1e-10)


def _track(rotations: list[np.ndarray], positions: np.ndarray, times_s: np.ndarray) -> PoseTrack:
    quaternions = np.asarray([Rotation.from_matrix(r).as_quat() for r in rotations], F)
    return PoseTrack(
        "/odom", np.round(times_s * 1e9).astype(np.int64), positions, quaternions, None
    )


def _edge(
    kind: str, a: int, b: int, relative: tuple, information: np.ndarray, model: str = ""
) -> Edge:
    quaternion = np.asarray(Rotation.from_matrix(relative[0]).as_quat(), F)
    return Edge(kind, a, b, np.asarray(relative[1], F), quaternion, information, model)  # type: ignore[arg-type]


def _graph(
    odometry: list[tuple], loops: list[Edge], times_s: np.ndarray, sigmas: np.ndarray
) -> PoseGraph:
    """Vertices integrated from the odometry's relative poses, starting at the origin."""
    pose = (np.eye(3), np.zeros(3))
    rotations, positions = [pose[0]], [pose[1]]
    information = np.diag(1.0 / sigmas**2)
    edges = []
    for k, relative in enumerate(odometry):
        pose = _compose(pose, relative)
        rotations.append(pose[0])
        positions.append(pose[1])
        edges.append(_edge("odometry", k, k + 1, relative, information))
    track = _track(rotations, np.asarray(positions, F), times_s)
    return PoseGraph(np.arange(len(rotations), dtype=np.int64), track, edges, loops, 0, 0, 0)


@given(st.integers(0, 2**32 - 1), st.integers(2, 12))
@settings(max_examples=30, deadline=None)
def test_chain_covariances_are_the_covariances_propagated_along_the_chain(
    seed: int, count: int
) -> None:
    """Prefix sums give what propagating edge by edge gives (right perturbations, at the
    chain's far end); from the far end back, the same covariance carried across the chain."""
    rng = np.random.default_rng(seed)
    odometry = [
        (Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(), rng.normal(0, 2.0, 3))
        for _ in range(count)
    ]
    sigmas = np.abs(rng.normal(0.1, 0.05, 6)) + 0.01
    graph = _graph(odometry, [], np.arange(count + 1, dtype=F), sigmas)
    a, c = sorted(rng.choice(count + 1, 2, replace=False))
    forward = _edge("loop", int(a), int(c), (np.eye(3), np.zeros(3)), np.eye(6))
    backward = _edge("loop", int(c), int(a), (np.eye(3), np.zeros(3)), np.eye(6))
    found = chain_covariances(graph, [forward, backward])

    expected = np.zeros((6, 6))
    chain = (np.eye(3), np.zeros(3))
    for relative in odometry[a:c]:  # Cov(T Z) at the end: Ad(Z^-1) Cov(T) Ad(Z^-1)^T + Cov(Z)
        inverse = _inverse(relative)
        moved = adjoint(*inverse)
        expected = moved @ expected @ moved.T + np.diag(sigmas**2)
        chain = _compose(chain, relative)
    np.testing.assert_allclose(found[0], expected, rtol=1e-8, atol=1e-12)
    carried = adjoint(*chain)  # T^-1 perturbed at its end: -Ad(T) xi
    np.testing.assert_allclose(found[1], carried @ expected @ carried.T, rtol=1e-8, atol=1e-10)


# -- a synthetic drive with a known yaw-rate bias ------------------------------------------------

RADIUS_M, SPEED_MPS, RATE_HZ = 10.0, 1.0, 2.0
LOOP_SIGMAS = np.array([0.05, 0.05, 0.05, *np.radians([0.5, 0.5, 0.5])])
# The odometry's white noise per frame, on top of the bias; stated as it is unless said.
ODOMETRY_SIGMAS = np.array([0.005, 0.005, 0.005, 0.0005, 0.0005, 0.0005])


def _measured(
    true_steps: list[tuple], rng: np.random.Generator, heading_error: Callable[[float], float]
) -> tuple[list[tuple], list[tuple]]:
    """The odometry of `true_steps`: each moving step's heading off by heading_error(its true
    turn about z) plus white noise (ODOMETRY_SIGMAS); a still step reports nothing. And the
    true poses the steps integrate to, from the origin."""
    odometry = []
    for relative in true_steps:
        moving = bool(relative[1].any())
        angle = Rotation.from_matrix(relative[0]).as_rotvec()[2]
        noise = rng.normal(0, ODOMETRY_SIGMAS) * moving
        turn = Rotation.from_rotvec([0, 0, heading_error(angle) * moving]).as_matrix()
        turn = turn @ Rotation.from_rotvec(noise[3:]).as_matrix()
        odometry.append((turn @ relative[0], relative[1] + noise[:3]))
    truth = [(np.eye(3), np.zeros(3))]
    for relative in true_steps:
        truth.append(_compose(truth[-1], relative))
    return odometry, truth


def _circle_drive(
    bias_rad_s: float, parked_s: float, wrong: int, stated: float = 1.0, seed: int = 0
) -> tuple:
    """Two laps of a circle at 2 Hz, parked `parked_s` seconds between them (odometry
    reporting no motion), the odometry's heading off by `bias_rad_s` while it moves; loop
    edges from each second-lap vertex to the first-lap vertex one frame after the same place,
    exact, plus `wrong` loop edges 2 m and 20 degrees off; the odometry's covariance stated
    `stated` times its noise's. Returns (graph, true positions)."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE_HZ
    lap = round(2 * math.pi * RADIUS_M / SPEED_MPS * RATE_HZ)
    parked = round(parked_s * RATE_HZ)
    step = (Rotation.from_rotvec([0, 0, SPEED_MPS * dt / RADIUS_M]).as_matrix(),
            np.array([SPEED_MPS * dt, 0.0, 0.0]))  # fmt: skip
    still = (np.eye(3), np.zeros(3))
    true_steps = [step] * lap + [still] * parked + [step] * lap
    odometry, truth = _measured(true_steps, rng, lambda turn: bias_rad_s * dt)
    information = np.diag(1.0 / LOOP_SIGMAS**2)
    loops = []
    for k in range(lap + parked + 5, 2 * lap + parked - 5, 4):
        match = k - lap - parked + 1
        relative = _compose(_inverse(truth[k]), truth[match])
        loops.append(_edge("loop", k, match, relative, information, "odometry_pnp"))
    for k in range(wrong):
        edge = loops[3 * k]
        off = (Rotation.from_rotvec([0, 0, math.radians(20)]).as_matrix(), np.array([2.0, 0, 0]))
        loops[3 * k] = _edge("loop", edge.from_id, edge.to_id, off, information, "odometry_pnp")
    times = np.arange(len(true_steps) + 1) * dt
    graph = _graph(odometry, loops, times, ODOMETRY_SIGMAS * math.sqrt(stated))
    return graph, np.array([t[1] for t in truth])


BIAS = math.radians(0.08)  # deg/s as a wheel odometry's


@pytest.mark.parametrize("parked_s", [0.0, 30.0])
def test_the_yaw_rate_bias_is_found_from_the_loop_edges(parked_s: float) -> None:
    """The bias only acts while the odometry moves: a parked half minute between the laps
    does not dilute it (counted in, the estimate would be 0.08 * 63 / 93 deg/s)."""
    graph, truth = _circle_drive(BIAS, parked_s, wrong=0)
    calibration = calibrate_odometry(graph)
    assert calibration.metric_loop_edges == len(graph.loop_edges)
    assert calibration.yaw_rate_bias == pytest.approx(BIAS, rel=0.15)  # measured: 1 %, 8 %
    corrected = calibrated_graph(graph, calibration)
    drift = np.linalg.norm(graph.poses.positions[-1] - truth[-1])
    left = np.linalg.norm(corrected.poses.positions[-1] - truth[-1])
    assert drift > 1.0 and left < drift / 2.5  # integrated again; the rest is white noise


def test_wrong_loop_edges_fewer_than_half_leave_the_calibration_alone() -> None:
    clean = calibrate_odometry(_circle_drive(BIAS, 0.0, wrong=0)[0])
    graph = _circle_drive(BIAS, 0.0, wrong=5)[0]
    assert len(graph.loop_edges) >= 25
    found = calibrate_odometry(graph)
    assert found.yaw_rate_bias == pytest.approx(clean.yaw_rate_bias, rel=0.05)
    assert 0.2 < found.covariance_scale / clean.covariance_scale < 5


def test_without_enough_metric_loop_edges_nothing_is_calibrated() -> None:
    graph, _ = _circle_drive(BIAS, 0.0, wrong=0)
    few = graph.loop_edges[: MIN_LOOP_EDGES - 1]
    placeholders = [_edge("loop", e.from_id, e.to_id, (np.eye(3), np.zeros(3)), e.information,
                          "placeholder") for e in graph.loop_edges]  # fmt: skip
    for loops in (few, placeholders):
        small = PoseGraph(graph.vertex_ids, graph.poses, graph.odometry_edges, loops, 0, 0, 0)
        calibration = calibrate_odometry(small)
        assert not calibration.applied
        assert calibration.summary().startswith("odometry as stated (")
        assert calibrated_graph(small, calibration) is small


def test_the_covariance_scale_follows_the_odometry_s_real_noise() -> None:
    """The same drive with its covariance stated 100 times too large or 100 times too small:
    the scale undoes it (the discrepancies, not the statement, decide)."""
    honest = calibrate_odometry(_circle_drive(BIAS, 0.0, wrong=0)[0]).covariance_scale
    for stated in (100.0, 0.01):
        found = calibrate_odometry(_circle_drive(BIAS, 0.0, wrong=0, stated=stated)[0])
        assert found.covariance_scale * stated == pytest.approx(honest, rel=0.02)


def _out_and_back_drive(yaw_scale: float, bias_rad_s: float, seed: int = 1) -> PoseGraph:
    """40 m out, a U-turn, 40 m back at 2 Hz; the odometry's turns off by `yaw_scale` of each
    and its heading by `bias_rad_s` while it moves; loop edges from each back-leg vertex to the
    out-leg vertex at the same place (facing the other way: the calibration only needs poses)."""
    rng = np.random.default_rng(seed)
    dt, leg = 1.0 / RATE_HZ, 80
    straight = (np.eye(3), np.array([SPEED_MPS * dt, 0.0, 0.0]))
    u_turn = (Rotation.from_rotvec([0, 0, math.pi / 10]).as_matrix(), np.array([0.5, 0.0, 0.0]))
    true_steps = [straight] * leg + [u_turn] * 10 + [straight] * leg
    odometry, truth = _measured(true_steps, rng, lambda turn: yaw_scale * turn + bias_rad_s * dt)
    positions = np.array([t[1] for t in truth])
    information = np.diag(1.0 / LOOP_SIGMAS**2)
    loops = []
    for k in range(leg + 14, 2 * leg + 10, 3):
        match = int(np.argmin(np.linalg.norm(positions[:leg] - positions[k], axis=1)))
        relative = _compose(_inverse(truth[k]), truth[match])
        loops.append(_edge("loop", k, match, relative, information, "odometry_pnp"))
    times = np.arange(len(true_steps) + 1) * dt
    return _graph(odometry, loops, times, ODOMETRY_SIGMAS)


def test_a_yaw_scale_is_fitted_when_the_turns_explain_what_time_does_not() -> None:
    """Out and back: every loop edge spans the same U-turn but a different time, so a 2 %
    yaw scale shows as a constant heading offset that no yaw-rate bias explains. On the
    circle, where the turns keep pace with time, the scale is not fitted (it would only fit
    noise there: docs/export.md)."""
    calibration = calibrate_odometry(_out_and_back_drive(0.02, BIAS))
    assert calibration.yaw_scale == pytest.approx(0.02, rel=0.2)
    assert calibration.yaw_rate_bias == pytest.approx(BIAS, rel=0.2)
    assert re.search(
        r"yaw-rate bias \+0\.0\d{3} deg/s, yaw scale \+\d\.\d\d %", calibration.summary()
    )
    without = calibrate_odometry(_out_and_back_drive(0.0, BIAS))
    assert without.yaw_scale == 0.0  # not significant: left out
    assert calibrate_odometry(_circle_drive(BIAS, 0.0, wrong=0)[0]).yaw_scale == 0.0
