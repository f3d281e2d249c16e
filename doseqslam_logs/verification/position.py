"""Where the query camera stands along the match's visit, from the odometry.

The essential fit gives the direction of the query camera seen from the match, not its
distance, and the bracketing (`geometry.bracketed_match`) reads where along the visit the
query lies from that direction's sign, which forward motion and distant points make noisy.
A pose topic gives what the images lack, a metric baseline: the match's keypoints
triangulated against its neighbours of the visit (the odometry's relative pose as the
baseline) and the query's keypoints resected against them (`metric_pose.odometry_pnp`,
without its baseline refinement: it is a position that is wanted here, not a covariance)
put the query camera in metres on the visit's path.

The verification stage uses it three ways (`Verifier._placed_by_odometry`): where the
visit's frames lie a metre or so apart (a low frame rate), the pair moves to the visit's
frame nearest the query, as the bracketing's pick between two such frames can be the wrong
one; a pair turned past max_rotation_deg is kept only where the query is placed near its
match; a pair that is not bracketed is accepted where the query is placed. At a high frame
rate the visit's frames are a few decimetres apart, closer than this estimate's error along
the path, and the bracketing's pick stays.

Pure computation: features, poses and parameters in, frame indices out.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from .geometry import FrameFeatures, Intrinsics, Verdict
from .metric_pose import MetricPose, MetricPoseParameters, OdometryNeighbour, odometry_pnp
from .motion import CameraPath
from .params import VerificationParameters

# The neighbours of the match the query is resected against: on each side of the visit, the
# nearest frame at least each of these from it, as the metric stage picks them (its
# NEIGHBOUR_BASELINES_M): the frame 2 m away gives 3-D points to match features that the one
# at 1 m sees under too little parallax or not at all, so more pairs are placed.
BASELINES_M: Final = (1.0, 2.0)
_PNP = MetricPoseParameters(refine_baselines=False)


def spacing_m(path: CameraPath, frame: int) -> float | None:
    """The mean distance between `frame` and its neighbours of the visit (metres), None
    where the poses do not cover them."""
    steps = [
        float(np.linalg.norm(path.positions[other] - path.positions[frame]))
        for other in (frame - 1, frame + 1)
        if path.covers(min(frame, other), max(frame, other))
    ]
    return sum(steps) / len(steps) if steps else None


def neighbours_of(path: CameraPath, match: int, frames: range) -> list[int]:
    """On each side of `match` within `frames`, the nearest frame at least each of
    BASELINES_M from it along a stretch the poses cover (once, if one frame is both)."""
    chosen: list[int] = []
    for side in (-1, 1):
        frame, baselines = match + side, list(BASELINES_M)
        while baselines and frame in frames and path.covers(min(frame, match), max(frame, match)):
            distance = np.linalg.norm(path.positions[frame] - path.positions[match])
            if distance >= baselines[0]:
                chosen.append(frame)
                baselines = [b for b in baselines if b > distance]
            frame += side
    return chosen


def neighbour(
    path: CameraPath, match: int, other: int, features: FrameFeatures
) -> OdometryNeighbour:
    """Frame `other` of the visit with its pose relative to the match's: X_other = R X_match
    + t (the path must have orientations). No covariance: the baseline is taken as exact,
    as it is over the metre or two between them."""
    assert path.orientations is not None
    orientations, positions = path.orientations, path.positions

    def pose(frame: int) -> tuple[Rotation, npt.NDArray[np.float64]]:
        return Rotation.from_quat(orientations[frame]), positions[frame]

    return OdometryNeighbour.between(features, pose(match), pose(other))


def query_position(
    query: FrameFeatures,
    match: FrameFeatures,
    neighbours: Sequence[OdometryNeighbour],
    verdict: Verdict,
    intrinsics: Intrinsics,
    params: VerificationParameters,
) -> npt.NDArray[np.float64] | None:
    """The query camera's centre in the match camera's frame (metres), None when the PnP
    does not pass `metric_pose`'s checks (too few points or inliers, a large residual, a
    rotation far from the essential fit's)."""
    pose = odometry_pnp(query, match, neighbours, verdict, intrinsics, params, _PNP)
    if not isinstance(pose, MetricPose) or pose.translation is None:
        return None
    return np.asarray(pose.translation, np.float64)


def nearest_frame(
    path: CameraPath, match: int, position: npt.NDArray[np.float64], frames: range
) -> tuple[int, float, float]:
    """(the frame of `frames` with a pose nearest the point `position` of the match camera's
    frame, its distance, the match's distance) in metres."""
    assert path.orientations is not None
    world = path.positions[match] + Rotation.from_quat(path.orientations[match]).apply(position)
    candidates = [f for f in frames if path.covers(f, f)]
    distances = np.linalg.norm(path.positions[candidates] - world, axis=1)
    best = int(np.argmin(distances))
    return candidates[best], float(distances[best]), float(np.linalg.norm(position))
