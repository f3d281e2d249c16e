#!/usr/bin/env python3
"""Measure the metric loop edges (issue #20) against ground truth on real drives.

For each input log: `annotate` it with the command's defaults (into --scratch, reused when
already there), read the accepted loop closures back, re-read each pair's query, refined match
and a neighbour of the match from the log, and fit `verification.metric_pose` with the
odometry rung (the neighbour's pose from /odom) and the rotation-only rung (rung 1 needs a
depth topic, which the samples lack). The result is compared with the true relative pose from
/ground_truth/pose; the placeholder edge of `export --format g2o` (zero translation) is shown
for comparison (its translation error is the true distance between the two cameras).

Frames: both pose topics are body poses (x forward, y left, z up) of the camera itself
(tools/loggen/make_sample_logs.py: the true camera pose at 1.6 m; the odometry integrates the same
planar motion from the start pose); the camera's optical axes are turned into body axes by
`export.pose_graph.OPTICAL_TO_BODY`, so T_world_camera = T_world_body * (OPTICAL_TO_BODY, 0).

    python -m reproduce.metric_edges                 # the three committed samples
    python -m reproduce.metric_edges LOG ... --scratch /tmp/x --verbose
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from doseqslam_logs.annotations.reader import AnnotatedLog, read_annotations
from doseqslam_logs.annotations.records import LoopClosureRecord
from doseqslam_logs.cli.main import main as cli_main
from doseqslam_logs.export.pose_graph import OPTICAL_TO_BODY
from doseqslam_logs.pipeline.reread import LogFrameReader
from doseqslam_logs.sources.camera_info import read_camera_info
from doseqslam_logs.sources.poses import PoseTrack, read_poses
from doseqslam_logs.verification import (
    DEFAULT_VERIFICATION,
    FrameFeatures,
    Intrinsics,
    Verdict,
    VerificationParameters,
    extract_features,
)
from doseqslam_logs.verification.metric_pose import (
    MetricPose,
    MetricPoseParameters,
    OdometryNeighbour,
    metric_pose,
    relative_pose,
)

F64 = npt.NDArray[np.float64]
ROOT = Path(__file__).resolve().parents[2]
SAMPLES = [
    ROOT / "sample_logs" / "drive_loops.ros2.mcap",
    ROOT / "sample_logs" / "drive_parked.ros2.mcap",
    ROOT / "sample_logs" / "drive_varrate.bag",
]


@dataclass(frozen=True)
class CameraPose:
    """T_world_camera, optical axes: X_world = rotation X_camera + position."""

    rotation: Rotation
    position: F64

    def relative_to(self, other: CameraPose) -> tuple[Rotation, F64]:
        """(R, t) with X_other = R X_self + t (the metric pose's convention, self = query)."""
        return relative_pose((self.rotation, self.position), (other.rotation, other.position))


@dataclass(frozen=True)
class PairResult:
    query: int
    match: int
    neighbours: list[int]
    pose: MetricPose
    translation_error_m: float  # NaN for rotation_only
    rotation_error_deg: float
    placeholder_error_m: float  # |t_true|: the error of a zero-translation edge
    epipolar_rotation_error_deg: float
    # Squared errors in the stated covariance's metric (NEES), translation and rotation
    # blocks; chi-square with 3 degrees of freedom (median 2.37) when the covariance is right.
    translation_nees: float
    rotation_nees: float


def camera_poses(track: PoseTrack) -> list[CameraPose]:
    optical = Rotation.from_matrix(OPTICAL_TO_BODY)
    return [
        CameraPose(Rotation.from_quat(q) * optical, np.asarray(p, np.float64))
        for p, q in zip(track.positions, track.quaternions_xyzw, strict=True)
    ]


def annotated(log: Path, scratch: Path) -> Path:
    out = scratch / f"{log.name.split('.')[0]}.annotated.mcap"
    if not out.exists() and cli_main(["annotate", str(log), "-o", str(out)]) != 0:
        raise RuntimeError(f"annotate {log} failed")
    return out


def verdict_of(record: LoopClosureRecord) -> Verdict:
    q, d = record.rotation_xyzw, record.translation_direction
    return Verdict(
        accepted=True,
        inliers=record.inliers,
        matches_tested=record.tentative_matches,
        model="E",
        reason=record.rejection_reason or "accepted",
        rotation_xyzw=(q[0], q[1], q[2], q[3]) if record.has_relative_pose else None,
        rotation_deg=record.rotation_deg if record.has_relative_pose else None,
        translation_direction=(d[0], d[1], d[2]) if record.has_relative_pose else None,
    )


def choose_neighbours(
    match: int, odometry: list[CameraPose], baselines_m: Sequence[float], reach: int
) -> list[int]:
    """On each side of `match`, the nearest frame whose odometry is at least each of
    `baselines_m` away (within `reach` frames); when there is none at all, the farthest frame
    within reach (a parked camera: the core refuses its baseline)."""

    def distance(i: int) -> float:
        return float(np.linalg.norm(odometry[i].position - odometry[match].position))

    chosen: list[int] = []
    for side in (1, -1):
        frames = [match + side * o for o in range(1, reach + 1)]
        frames = [i for i in frames if 0 <= i < len(odometry)]
        for baseline in baselines_m:
            far = next((i for i in frames if distance(i) >= baseline), None)
            if far is not None and far not in chosen:
                chosen.append(far)
    if chosen:
        return chosen
    around = [i for o in range(1, reach + 1) for i in (match + o, match - o)]
    return [max((i for i in around if 0 <= i < len(odometry)), key=distance)]


def measure_log(
    log: Path,
    scratch: Path,
    params: MetricPoseParameters,
    baselines_m: Sequence[float],
    reach: int,
    feature_changes: Sequence[dict[str, Any]],
    odometry_sigma: tuple[float, float] | None = None,
) -> list[PairResult]:
    """The pairs of one log; each of `feature_changes` (changes to the run's verification
    parameters, e.g. another detector) is tried in turn until one gives a metric pose."""
    annotations = read_annotations(annotated(log, scratch))
    metadata = annotations.metadata
    run = _verification_parameters(annotations)
    variants = [dataclasses.replace(run, **changes) for changes in feature_changes or [{}]]
    info = read_camera_info(log, metadata.image_topic)
    if info is None or annotations.frame_times is None:
        raise RuntimeError(f"{log}: no camera info or no frame times")
    intrinsics = Intrinsics(info.fx, info.fy, info.cx, info.cy)
    times = annotations.detector_times_ns()
    assert times is not None
    odometry = camera_poses(read_poses(log, "/odom").interpolate(times))
    truth = camera_poses(read_poses(log, "/ground_truth/pose").interpolate(times))
    results = []
    with LogFrameReader(log, metadata.image_topic, annotations.frame_times) as frames:
        cache: dict[tuple[int, int], FrameFeatures] = {}

        def features_of(variant: int, indices: Sequence[int]) -> list[FrameFeatures]:
            wanted = [i for i in indices if (variant, i) not in cache]
            for index, gray in frames(wanted):
                cache[variant, index] = extract_features(gray, variants[variant])
            return [cache[variant, i] for i in indices]

        for record in annotations.reported_loop_closures:
            q, m = record.query.index, record.matched.index
            near = choose_neighbours(m, odometry, baselines_m, reach)
            relative = [odometry[m].relative_to(odometry[n]) for n in near]
            verdict = verdict_of(record)
            poses = []
            for variant, verification in enumerate(variants):
                query, match, *others = features_of(variant, [q, m, *near])
                neighbours = [
                    OdometryNeighbour(
                        features,
                        _xyzw(rotation),
                        _xyz(translation),
                        _odometry_covariance(translation, odometry_sigma),
                    )
                    for features, (rotation, translation) in zip(others, relative, strict=True)
                ]
                poses.append(
                    metric_pose(
                        query,
                        match,
                        verdict,
                        intrinsics,
                        verification,
                        params,
                        neighbours=neighbours,
                    )
                )
                if poses[-1] is not None and poses[-1].translation is not None:
                    break
            pose = poses[-1] if poses[-1] is not None and poses[-1].translation else poses[0]
            if pose is None:
                continue
            results.append(_compare(q, m, near, pose, verdict, truth[q].relative_to(truth[m])))
    return results


def _odometry_covariance(translation: F64, sigma_per_m: tuple[float, float] | None) -> F64 | None:
    """Odometry's error over a baseline: (metres per metre, degrees per metre) on every axis,
    growing with the distance; None without a model."""
    if sigma_per_m is None:
        return None
    distance = float(np.linalg.norm(translation))
    metres, degrees = sigma_per_m
    sigmas = [metres * distance] * 3 + [math.radians(degrees) * distance] * 3
    return np.diag(np.square(np.maximum(sigmas, 1e-6)))


def _xyzw(rotation: Rotation) -> tuple[float, float, float, float]:
    q = rotation.as_quat()
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def _xyz(vector: F64) -> tuple[float, float, float]:
    return (float(vector[0]), float(vector[1]), float(vector[2]))


def _verification_parameters(annotations: AnnotatedLog) -> VerificationParameters:
    recorded = annotations.metadata.verification_parameters_json
    if not recorded:
        return DEFAULT_VERIFICATION
    return VerificationParameters.from_dict(json.loads(recorded))


def _compare(
    q: int, m: int, n: list[int], pose: MetricPose, verdict: Verdict, true: tuple[Rotation, F64]
) -> PairResult:
    true_rotation, true_translation = true
    rotation_error = _angle_deg(Rotation.from_quat(pose.rotation_xyzw) * true_rotation.inv())
    epipolar = math.nan
    if verdict.rotation_xyzw is not None:
        epipolar = _angle_deg(Rotation.from_quat(verdict.rotation_xyzw) * true_rotation.inv())
    translation_error, translation_nees, rotation_nees = math.nan, math.nan, math.nan
    if pose.translation is not None:
        error = np.asarray(pose.translation) - true_translation
        translation_error = float(np.linalg.norm(error))
        translation_nees = float(error @ np.linalg.solve(pose.covariance[:3, :3], error))
        # The covariance's rotation: R' = exp(w) R, so w = log(R_estimate R_true^-1).
        turn = (Rotation.from_quat(pose.rotation_xyzw) * true_rotation.inv()).as_rotvec()
        rotation_nees = float(turn @ np.linalg.solve(pose.covariance[3:, 3:], turn))
    return PairResult(
        q,
        m,
        n,
        pose,
        translation_error,
        rotation_error,
        float(np.linalg.norm(true_translation)),
        epipolar,
        translation_nees,
        rotation_nees,
    )


def _angle_deg(rotation: Rotation) -> float:
    return math.degrees(rotation.magnitude())


def _stats(values: Sequence[float]) -> str:
    finite = np.asarray([v for v in values if math.isfinite(v)])
    if finite.size == 0:
        return "-"
    return f"{np.median(finite):.3f} / {np.percentile(finite, 95):.3f}"


def table_rows(name: str, results: list[PairResult]) -> str:
    methods = Counter(r.pose.method for r in results)
    metric = [r for r in results if r.pose.translation is not None]
    return (
        f"| {name} | {len(results)} | {methods['odometry_pnp']} | {methods['rotation_only']} | "
        f"{_stats([r.translation_error_m for r in metric])} | "
        f"{_stats([r.rotation_error_deg for r in metric])} | "
        f"{_stats([r.epipolar_rotation_error_deg for r in results])} | "
        f"{_stats([r.placeholder_error_m for r in results])} |"
    )


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="*", type=Path, default=SAMPLES)
    parser.add_argument("--scratch", type=Path, default=Path("/tmp/metric-pose"))
    parser.add_argument(
        "--baselines", default="1,2", help="neighbour baselines on each side, m, comma-separated"
    )
    parser.add_argument("--reach", type=int, default=8, help="neighbour within +-frames")
    parser.add_argument(
        "--detector",
        help="features for the metric fit (default: the run's); several, comma-separated, are"
        " tried in turn until one gives a metric pose",
    )
    parser.add_argument("--max-features", type=int, help="(default: the run's)")
    parser.add_argument(
        "--max-disagreement",
        type=float,
        default=MetricPoseParameters.max_rotation_disagreement_deg,
        help="deg between the PnP and the epipolar rotation",
    )
    parser.add_argument(
        "--odometry-sigma",
        default="0.03,0.15",
        help="the odometry's error per metre of baseline: metres, degrees ('none': exact)",
    )
    parser.add_argument("--verbose", action="store_true", help="one line per pair")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    args.scratch.mkdir(parents=True, exist_ok=True)
    params = MetricPoseParameters(max_rotation_disagreement_deg=args.max_disagreement)
    sizes = {"max_features": args.max_features} if args.max_features else {}
    detectors = args.detector.split(",") if args.detector else []
    changes = [{"feature_detector": d, **sizes} for d in detectors] or [sizes]
    everything: list[PairResult] = []
    rows = []
    baselines = [float(b) for b in args.baselines.split(",")]
    odometry_sigma = None
    if args.odometry_sigma != "none":
        metres, degrees = (float(v) for v in args.odometry_sigma.split(","))
        odometry_sigma = (metres, degrees)
    for log in args.logs:
        results = measure_log(
            log, args.scratch, params, baselines, args.reach, changes, odometry_sigma
        )
        everything += results
        rows.append(table_rows(log.name, results))
        if args.verbose:
            for r in results:
                print(
                    f"{log.name} q{r.query} m{r.match} n{r.neighbours} {r.pose.method}"
                    f" inliers {r.pose.inliers} rms {r.pose.rms_px:.2f} px"
                    f" t_err {r.translation_error_m:.3f} m r_err {r.rotation_error_deg:.2f} deg"
                    f" |t_true| {r.placeholder_error_m:.2f} m {r.pose.reason}",
                    file=sys.stderr,
                )
    print(
        "| drive | pairs | odometry_pnp | rotation_only | translation error, m (median / p95)"
        " | rotation error, deg (median / p95) | epipolar rotation error, deg (all pairs)"
        " | placeholder translation error, m |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        print(row)
    print(table_rows("all", everything))
    reasons = Counter(
        reason.split(" (")[0] for r in everything for reason in r.pose.reason.split("; ") if reason
    )
    for reason, count in reasons.most_common():
        print(f"fallback: {reason}: {count}")
    metric = [r for r in everything if r.pose.translation is not None]
    if metric:
        print(
            "covariance check (median NEES, 2.37 when right): translation "
            f"{np.median([r.translation_nees for r in metric]):.1f}, rotation "
            f"{np.median([r.rotation_nees for r in metric]):.1f}"
        )
    print(
        f"{len(everything)} pairs, {time.perf_counter() - started:.1f} s in all"
        " (with annotate unless its output was in --scratch already)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
