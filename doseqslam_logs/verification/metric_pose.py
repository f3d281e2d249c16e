"""Metric relative pose of a verified loop pair: a ladder of fits, best first.

Pure computation: features, a depth image or neighbouring frames with their odometry, and the
pair's `Verdict` in; a `MetricPose` out. The rungs, each used when the caller has what it needs:

1. ``depth_pnp``: the match frame's aligned depth image gives 3-D points at its keypoints;
   PnP-RANSAC of the query's keypoints against them, then Levenberg-Marquardt refinement.
2. ``odometry_pnp``: the match frame's keypoints are triangulated against neighbouring frames
   of the match, with the odometry's relative pose between them as the baseline (this is
   where the metric scale comes from), first refined by the two frames' epipolar geometry
   with the odometry as its prior (`_refined_baseline`: a wheel odometry's tenths of a degree
   over a metre bend the structure of a forward motion); then the same PnP of the query.
3. ``rotation_only``: the rotation alone, the translation unknown and left as None, never a
   zero. The rotation is the consensus of the verdict's essential fit, the metric features'
   essential fit and homography, and (with odometry) fits through frames near the query and
   the match chained with their odometry.

A metric rung is refused, with a reason, when it has too few PnP inliers (default 25, as
VINS-Mono), a large residual, a rotation that disagrees with the epipolar fit, or (rung 2) a
degenerate baseline. `metric_pose` returns the best rung that passed and the reasons of the
better rungs that were tried and failed.

Frames: as `Verdict`, camera optical frames (x right, y down, z forward) and
X_match = R X_query + t for a 3-D point X in each camera's frame, so (R, t) is the query
camera's pose in the match camera's frame. The covariance is over (t_x, t_y, t_z, rot x, rot y,
rot z), ROS's order: the translation perturbed additively and the rotation as R' = exp(w) R,
a rotation vector w about the match camera's axes (ROS's "fixed axes" of the parent frame).

Covariance of a metric fit: sigma^2 (J^T J)^-1, J the Jacobian of the PnP inliers' reprojection
residuals (pixels) with respect to those six parameters, and sigma^2 the a-posteriori variance
of a pixel coordinate, sum(r^2) / (2n - 6), floored at `MetricPoseParameters.min_pixel_sigma_px`
(the residuals of RANSAC inliers are truncated at its threshold, so the estimate can come out
too small on few points). Rung 2's triangulated points are noisy too: there J also holds the
points as parameters, seen in the query, the match and their neighbour, and the covariance is
the pose's block of the inverse (Schur complement), since the points' depth errors move the
pose. A neighbour's odometry error (`OdometryNeighbour.covariance`, when the caller knows it)
adds G cov G^T, G how the estimate follows a wrong baseline; with the refinement, cov is the
refined baseline's posterior covariance. Not in it: the depth image's noise (rung 1). The
model assumes Gaussian pixel noise, which SIFT keypoints fit and ORB's grid-bound keypoints do
not: with ORB features the stated sigmas come out too small.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .geometry import FrameFeatures, Intrinsics, Verdict, ratio_matches, verify_pair
from .params import VerificationParameters

F64 = npt.NDArray[np.float64]
DepthImage = npt.NDArray[np.float32]
Method = Literal["depth_pnp", "odometry_pnp", "rotation_only"]

# Camera optical axes (x right, y down, z forward) in body axes (x forward, y left, z up): a
# camera looking along its body's x axis, the convention of the pose graph and of turning
# odometry body poses into camera poses (no tf is read).
OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

_FIT_SEED = 0
_JACOBIAN_STEP = 1e-6  # metres and radians: central differences of the reprojection
_DIRECTION_SEEDS = 40  # rung 3: matches whose pairs propose a translation direction
_SUPPORT_BLOCK = 128  # rung 3: directions scored at once


@dataclass(frozen=True)
class MetricPoseParameters:
    """Checks of the metric rungs; pixel values are in feature-image pixels (as
    `VerificationParameters.ransac_threshold_px`), scaled to the original frame's pixels."""

    min_inliers: int = 25  # PnP inliers needed (VINS-Mono's loop-closure PnP uses 25)
    reprojection_threshold_px: float = 2.0  # PnP-RANSAC inlier threshold
    max_rms_px: float = 1.5  # refined RMS reprojection residual of the inliers
    max_rotation_disagreement_deg: float = 5.0  # against the essential fit's rotation
    ransac_iterations: int = 1000
    confidence: float = 0.999
    min_baseline_m: float = 0.2  # rung 2: odometry distance between match and neighbour
    min_parallax_deg: float = 1.0  # rung 2: angle between the two rays of a triangulated point
    min_pixel_sigma_px: float = 0.3  # floor of the covariance's pixel sigma (original pixels)
    # Rung 3's rotation is the consensus of several estimates of it (`_rotation_consensus`):
    # the verification's essential fit, the metric features' essential fit and homography, and
    # the essential fits of the query against the match's neighbours and of the query's
    # neighbours against the match, chained through their refined odometry; those within
    # `rotation_agreement_deg` of the medoid are averaged: on few matches each estimator alone
    # is off by degrees now and then, and they are seldom off the same way. False: the
    # verdict's rotation alone.
    rotation_consensus: bool = True
    rotation_agreement_deg: float = 2.0
    # Floor of a rotation-only pose's rotation sigma, on every axis: an essential fit's own
    # sigma states tenths of a degree for errors of degrees, heavy tailed. 12 degrees: the
    # floor with the lowest trajectory error after `optimize` on the calibration drives.
    rotation_only_min_sigma_deg: float = 12.0
    # Rung 2's covariance times this: calibrated so that the median NEES (squared error in the
    # stated covariance's metric, 6 degrees of freedom) of the odometry_pnp edges on the
    # calibration drives is chi-square's. The tail stays heavier than chi-square's.
    odometry_covariance_scale: float = 1.33
    # A PnP pose that disagrees with the epipolar fit is still kept when it explains strictly
    # more of the pair's matches (Sampson distance within the verification's threshold): the
    # essential fit of a short baseline trades rotation for translation, and in most
    # disagreements on our samples it was the wrong one. False: always refuse.
    keep_better_supported: bool = True
    # Rung 2: refine each neighbour's odometry pose by the epipolar geometry of its matches
    # with the match frame, the odometry (with its covariance) as the prior (`_refined_baseline`).
    refine_baselines: bool = True

    def __post_init__(self) -> None:
        positive = (
            self.min_inliers,
            self.reprojection_threshold_px,
            self.max_rms_px,
            self.max_rotation_disagreement_deg,
            self.ransac_iterations,
            self.min_baseline_m,
            self.min_pixel_sigma_px,
            self.rotation_only_min_sigma_deg,
            self.odometry_covariance_scale,
            self.rotation_agreement_deg,
        )
        if not all(math.isfinite(v) and v > 0 for v in positive) or self.min_inliers < 6:
            raise ValueError(f"metric pose parameters must be positive (min_inliers >= 6): {self}")
        if not 0 < self.confidence < 1 or not self.min_parallax_deg >= 0:
            raise ValueError(f"confidence must be in (0, 1), min_parallax_deg >= 0: {self}")


@dataclass(frozen=True, eq=False)
class MetricPose:
    """The relative pose of a loop pair: X_match = R X_query + t, camera optical frames.

    `translation` is in metres, None for ``rotation_only`` (the scale is unknown: the
    covariance's translation variances are then infinite). `covariance` is 6x6 over
    (t_x, t_y, t_z, rot x, rot y, rot z) as the module says. `inliers` and `rms_px` describe
    the fit the pose came from: the PnP inliers and the RMS of their residuals' x and y
    components (original pixels), or for ``rotation_only`` the ratio matches within the
    verification's threshold of the verdict's essential matrix and the RMS of their Sampson
    distances. `reason` says why better rungs that were tried failed ("" when none failed).
    """

    method: Method
    rotation_xyzw: tuple[float, float, float, float]
    translation: tuple[float, float, float] | None
    covariance: F64
    inliers: int
    rms_px: float
    reason: str = ""

    @property
    def rotation_deg(self) -> float:
        return math.degrees(Rotation.from_quat(self.rotation_xyzw).magnitude())

    def match_in_query(self) -> MetricPose:
        """The inverse: the match camera's pose in the query camera's frame
        (X_query = R' X_match + t', R' = R^T, t' = -R^T t), which is what a pose-graph edge
        from the query to the match measures (still in optical axes). Its covariance has the
        same convention, about the query camera's axes now: R perturbed as exp(w) R and t as
        t + dt give w' = -R^T w and dt' = -R^T dt - R^T [t]x w. Without a translation only the
        rotation block is mapped (the translation stays unknown)."""
        rotation = Rotation.from_quat(self.rotation_xyzw).as_matrix()
        rotation_t = rotation.T
        jacobian = np.zeros((6, 6))
        jacobian[3:, 3:] = -rotation_t
        covariance = np.full((6, 6), 0.0)
        translation = None
        if self.translation is None:
            covariance[:3, :3] = np.diag([math.inf] * 3)
            block = self.covariance[3:, 3:]
            covariance[3:, 3:] = jacobian[3:, 3:] @ block @ jacobian[3:, 3:].T
        else:
            t = np.asarray(self.translation, np.float64)
            jacobian[:3, :3] = -rotation_t
            jacobian[:3, 3:] = -rotation_t @ _skew(t)
            covariance = jacobian @ self.covariance @ jacobian.T
            inverse_t = -rotation_t @ t
            translation = (float(inverse_t[0]), float(inverse_t[1]), float(inverse_t[2]))
        return dataclasses.replace(
            self,
            rotation_xyzw=_quaternion(rotation_t),
            translation=translation,
            covariance=(covariance + covariance.T) / 2,
        )


@dataclass(frozen=True, eq=False)
class OdometryNeighbour:
    """A frame near the match and where the odometry puts it: X_neighbour = R X_match + t,
    camera optical frames, t in metres (the caller turns the odometry's body poses into this).

    `covariance`, when known, is that of (t, R) in the module's convention (6x6: t additive,
    R perturbed as exp(w) R): the odometry's error over the baseline then widens the metric
    pose's covariance. None: the baseline is taken as exact.
    """

    features: FrameFeatures
    rotation_xyzw: tuple[float, float, float, float]
    translation: tuple[float, float, float]
    covariance: F64 | None = None

    @classmethod
    def between(
        cls,
        features: FrameFeatures,
        match: tuple[Rotation, F64],
        neighbour: tuple[Rotation, F64],
        covariance: Callable[[F64], F64] | None = None,
    ) -> OdometryNeighbour:
        """The neighbour whose camera pose (R, p: X_world = R X + p) is `neighbour`, relative
        to the match camera's `match`; `covariance(t)`, when given, is the odometry's over
        the baseline t."""
        rotation, translation = relative_pose(match, neighbour)
        q = rotation.as_quat()
        return cls(
            features,
            (float(q[0]), float(q[1]), float(q[2]), float(q[3])),
            (float(translation[0]), float(translation[1]), float(translation[2])),
            None if covariance is None else covariance(translation),
        )


def relative_pose(
    match: tuple[Rotation, F64], neighbour: tuple[Rotation, F64]
) -> tuple[Rotation, F64]:
    """(R, t) with X_neighbour = R X_match + t, from the two camera poses (R_i, p_i) with
    X_world = R_i X_i + p_i."""
    (at, at_position), (to, to_position) = match, neighbour
    inverse = to.inv()
    translation = inverse.apply(at_position - to_position)
    return inverse * at, np.asarray(translation, np.float64)


def metric_pose(
    query: FrameFeatures,
    match: FrameFeatures,
    verdict: Verdict,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters | None = None,
    *,
    depth: DepthImage | None = None,
    neighbours: Sequence[OdometryNeighbour] = (),
    query_neighbours: Callable[[], Sequence[OdometryNeighbour]] | None = None,
) -> MetricPose | None:
    """The best rung for a verified pair: depth PnP when `depth` (the match frame's, float32
    metres, NaN or <= 0 invalid, the frame's size) is given, else or on failure odometry PnP
    when `neighbours` are, else or on failure the rotation only. `verification` gives the
    ratio test (as the pair was verified). `query_neighbours`, called only when the rotation
    only is left, gives frames near the query with their odometry (X_neighbour = R X_query +
    t), for that rotation's consensus. None when every rung tried failed and the verdict has
    no rotation.
    """
    params = params or MetricPoseParameters()
    reasons: list[str] = []
    if depth is not None:
        outcome = depth_pnp(query, match, depth, verdict, intrinsics, verification, params)
        if isinstance(outcome, MetricPose):
            return outcome
        reasons.append(f"depth_pnp: {outcome}")
    if neighbours:
        outcome = odometry_pnp(query, match, neighbours, verdict, intrinsics, verification, params)
        if isinstance(outcome, MetricPose):
            return _with_reasons(outcome, reasons)
        reasons.append(f"odometry_pnp: {outcome}")
    near_query = () if query_neighbours is None else query_neighbours()
    fallback = rotation_only(
        query,
        match,
        verdict,
        intrinsics,
        verification,
        params,
        neighbours=neighbours,
        query_neighbours=near_query,
    )
    return None if fallback is None else _with_reasons(fallback, reasons)


def _with_reasons(pose: MetricPose, reasons: list[str]) -> MetricPose:
    return dataclasses.replace(pose, reason="; ".join(reasons)) if reasons else pose


# -- rung 1: depth ------------------------------------------------------------------------


def depth_pnp(
    query: FrameFeatures,
    match: FrameFeatures,
    depth: DepthImage,
    verdict: Verdict,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
) -> MetricPose | str:
    """Rung 1: the match's keypoints back-projected with `depth` (nearest pixel), PnP of the
    query's. A MetricPose, or why not."""
    if depth.ndim != 2:
        raise ValueError(f"depth must be a 2-D image, got shape {depth.shape}")
    q_index, m_index = ratio_matches(query, match, verification.ratio)
    pixels = match.keypoints[m_index].astype(np.float64)
    z = _depth_at(depth, pixels)
    valid = np.isfinite(z) & (z > 0)
    if np.count_nonzero(valid) < params.min_inliers:
        return f"too few matches with depth ({np.count_nonzero(valid)} < {params.min_inliers})"
    points = _back_project(pixels[valid], z[valid], intrinsics)
    image = query.keypoints[q_index[valid]].astype(np.float64)
    scale = min(query.scale, match.scale)
    pair = _pair_rays(query, match, q_index, m_index, intrinsics, verification)
    return _pnp(points, image, verdict, intrinsics, params, scale, pair, "depth_pnp")


def _depth_at(depth: DepthImage, pixels: F64) -> F64:
    """Depth at each (x, y) pixel centre, nearest pixel; NaN outside the image."""
    height, width = depth.shape
    column = np.rint(pixels[:, 0]).astype(np.int64)
    row = np.rint(pixels[:, 1]).astype(np.int64)
    inside = (column >= 0) & (column < width) & (row >= 0) & (row < height)
    z = np.full(len(pixels), np.nan)
    z[inside] = depth[row[inside], column[inside]]
    return z


def _back_project(pixels: F64, z: F64, intrinsics: Intrinsics) -> F64:
    x = (pixels[:, 0] - intrinsics.cx) / intrinsics.fx * z
    y = (pixels[:, 1] - intrinsics.cy) / intrinsics.fy * z
    return np.column_stack([x, y, z])


# -- rung 2: odometry baseline ------------------------------------------------------------


def odometry_pnp(
    query: FrameFeatures,
    match: FrameFeatures,
    neighbours: Sequence[OdometryNeighbour],
    verdict: Verdict,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
) -> MetricPose | str:
    """Rung 2: the match's keypoints triangulated against each neighbour's (the odometry's
    relative pose as the baseline), PnP of the query's. A MetricPose, or why not.

    Each match feature keeps the point of the neighbour that sees it under the widest
    parallax: neighbours on both sides of the match (or at two distances) give 3-D points to
    more of its features than one does.
    """
    if not neighbours:
        raise ValueError("odometry_pnp needs at least one neighbour")
    longest = max(float(np.linalg.norm(n.translation)) for n in neighbours)
    usable = [n for n in neighbours if np.linalg.norm(n.translation) >= params.min_baseline_m]
    if not usable:
        return f"degenerate baseline ({longest:.2f} m < {params.min_baseline_m:g} m)"
    scale = min([query.scale, match.scale] + [n.features.scale for n in usable])
    if params.refine_baselines:
        usable = [_refined_baseline(match, n, intrinsics, verification, params) for n in usable]
    triangulated = [_triangulate(match, n, intrinsics, verification, params, scale) for n in usable]
    # -1: no point from that neighbour (a point's parallax is >= 0).
    angles = np.nan_to_num(np.stack([t.parallax_deg for t in triangulated]), nan=-1.0)
    best, every = np.argmax(angles, axis=0), np.arange(match.count)
    parallax = angles[best, every]
    points_by_feature = np.stack([t.points for t in triangulated])[best, every]
    good = parallax >= 0
    wide = good & (parallax >= params.min_parallax_deg)
    if np.count_nonzero(wide) < params.min_inliers:
        if np.count_nonzero(good) >= params.min_inliers:
            return (
                f"parallax too small ({np.count_nonzero(wide)} of {np.count_nonzero(good)} "
                f"points over {params.min_parallax_deg:g} deg)"
            )
        return f"too few triangulated points ({np.count_nonzero(good)} < {params.min_inliers})"
    q_index, m_index = ratio_matches(query, match, verification.ratio)
    keep = wide[m_index]
    if np.count_nonzero(keep) < params.min_inliers:
        return (
            f"too few query matches on triangulated points "
            f"({np.count_nonzero(keep)} < {params.min_inliers})"
        )
    points = points_by_feature[m_index[keep]]
    image = query.keypoints[q_index[keep]].astype(np.float64)
    pair = _pair_rays(query, match, q_index, m_index, intrinsics, verification)
    which = best[m_index[keep]]
    views = _PointViews(
        np.stack([Rotation.from_quat(n.rotation_xyzw).as_matrix() for n in usable])[which],
        np.asarray([n.translation for n in usable], np.float64)[which],
        which,
        tuple(n.covariance for n in usable),
    )
    return _pnp(points, image, verdict, intrinsics, params, scale, pair, "odometry_pnp", views)


def _refined_baseline(
    match: FrameFeatures,
    neighbour: OdometryNeighbour,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
) -> OdometryNeighbour:
    """The neighbour's pose refined by the two frames' epipolar geometry, the odometry as a
    prior: the odometry sets the scale, the matches the direction and the rotation, which a
    wheel odometry gets wrong by tenths of a degree over a metre or two, enough to bend the
    triangulated structure of a forward motion (small parallax) and so the PnP pose. The
    covariance is the posterior one, so the metric pose's covariance carries what is left of
    the baseline's error. Unchanged without an odometry covariance (no prior to weigh the
    matches against) or with too few matches near the odometry's epipolar geometry."""
    if neighbour.covariance is None:
        return neighbour
    m_index, n_index = ratio_matches(match, neighbour.features, verification.ratio)
    pair = _pair_rays(match, neighbour.features, m_index, n_index, intrinsics, verification)
    rotation = Rotation.from_quat(neighbour.rotation_xyzw).as_matrix()
    translation = np.asarray(neighbour.translation, np.float64)
    prior = np.linalg.cholesky(_symmetric_inverse(neighbour.covariance)).T  # whitens a delta
    delta, sigma = np.zeros(6), pair.threshold_px / 2
    jacobian = np.zeros((0, 6))
    # Twice: from the matches near the odometry's geometry (its error moves them by a few
    # pixels), then from those within the threshold of the first refinement's, with the pixel
    # sigma of the first refinement's residuals.
    for reach in (3.0, 1.0):
        turned, moved = _moved(rotation, translation, delta)
        near = np.abs(pair.distances_px(turned, moved)) <= reach * pair.threshold_px
        if np.count_nonzero(near) < params.min_inliers:
            return neighbour
        fit = _baseline_fit(pair, near, rotation, translation, prior, sigma, delta)
        delta, jacobian, sigma = fit
        sigma = max(sigma, params.min_pixel_sigma_px)
    turned, moved = _moved(rotation, translation, delta)
    return OdometryNeighbour(
        neighbour.features,
        _quaternion(turned),
        (float(moved[0]), float(moved[1]), float(moved[2])),
        _symmetric_inverse(jacobian.T @ jacobian),
    )


def _moved(rotation: F64, translation: F64, delta: F64) -> tuple[F64, F64]:
    """(exp(w) R, t + dt) for delta = (dt, w)."""
    turn = np.asarray(cv2.Rodrigues(np.ascontiguousarray(delta[3:]))[0], np.float64)
    return turn @ rotation, translation + delta[:3]


def _baseline_fit(
    pair: _PairRays,
    chosen: npt.NDArray[np.bool_],
    rotation: F64,
    translation: F64,
    prior: F64,
    sigma_px: float,
    start: F64,
) -> tuple[F64, F64, float]:
    """The (dt, w), from `start`, that minimizes the chosen matches' Sampson distances (pixel
    sigma `sigma_px`) plus the prior's whitened delta; the whitened Jacobian there (its J^T J is the
    posterior information) and the RMS of the distances."""
    rays_a, rays_b = pair.rays_query[chosen], pair.rays_match[chosen]

    def whitened(delta: F64) -> F64:
        turned, moved = _moved(rotation, translation, delta)
        distances = _sampson(rays_a, rays_b, turned, moved) * (pair.focal / sigma_px)
        return np.concatenate([distances, prior @ delta])

    fit = least_squares(whitened, start, method="lm")
    distances = fit.fun[:-6] * sigma_px
    rms = float(np.sqrt(distances @ distances / max(distances.size - 5, 1)))
    return np.asarray(fit.x, np.float64), np.asarray(fit.jac, np.float64), rms


@dataclass(frozen=True, eq=False)
class _PointViews:
    """Which neighbour saw each of rung 2's 3-D points (besides the match and the query), its
    pose (X_neighbour = R X_match + t), and per neighbour the covariance of that pose (None:
    exact)."""

    neighbour_rotation: F64  # (n, 3, 3)
    neighbour_translation: F64  # (n, 3)
    neighbour_of: npt.NDArray[np.intp]  # (n,): index into `covariance`
    covariance: tuple[F64 | None, ...]

    def subset(self, chosen: npt.NDArray[np.intp]) -> _PointViews:
        return _PointViews(
            self.neighbour_rotation[chosen],
            self.neighbour_translation[chosen],
            self.neighbour_of[chosen],
            self.covariance,
        )


@dataclass(frozen=True, eq=False)
class _Triangulated:
    """Per match feature: its 3-D point (match camera frame) and the angle between its two
    rays, NaN where no good point (not matched, behind a camera, reprojected too far)."""

    points: F64  # (match.count, 3)
    parallax_deg: F64  # (match.count,)


def _triangulate(
    match: FrameFeatures,
    neighbour: OdometryNeighbour,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
    scale: float,
) -> _Triangulated:
    """The match's features triangulated against one neighbour's: good points are in front of
    both cameras and reprojected within the PnP threshold in both views."""
    m_index, n_index = ratio_matches(match, neighbour.features, verification.ratio)
    by_feature = np.zeros((match.count, 3))
    parallax = np.full(match.count, np.nan)
    if m_index.size == 0:
        return _Triangulated(by_feature, parallax)
    k = intrinsics.matrix()
    rotation = Rotation.from_quat(neighbour.rotation_xyzw).as_matrix()
    translation = np.asarray(neighbour.translation, np.float64)
    p_match = match.keypoints[m_index].astype(np.float64)
    p_neighbour = neighbour.features.keypoints[n_index].astype(np.float64)
    projection_m = k @ np.hstack([np.eye(3), np.zeros((3, 1))])
    projection_n = k @ np.hstack([rotation, translation[:, None]])
    homogeneous = cv2.triangulatePoints(projection_m, projection_n, p_match.T, p_neighbour.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = (homogeneous[:3] / homogeneous[3]).T
    in_neighbour = points @ rotation.T + translation
    threshold = params.reprojection_threshold_px / scale
    error_m = np.linalg.norm(_project(points, k) - p_match, axis=1)
    error_n = np.linalg.norm(_project(in_neighbour, k) - p_neighbour, axis=1)
    good = (
        np.isfinite(points).all(axis=1)
        & (points[:, 2] > 0)
        & (in_neighbour[:, 2] > 0)
        & (error_m <= threshold)
        & (error_n <= threshold)
    )
    centre_n = -rotation.T @ translation  # the neighbour camera's centre in the match frame
    by_feature[m_index[good]] = points[good]
    parallax[m_index[good]] = _ray_angle_deg(points[good], points[good] - centre_n)
    return _Triangulated(by_feature, parallax)


def _ray_angle_deg(a: F64, b: F64) -> F64:
    cosine = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    angle: F64 = np.degrees(np.arccos(np.clip(np.nan_to_num(cosine, nan=1.0), -1.0, 1.0)))
    return angle


# -- PnP and its checks -------------------------------------------------------------------


def _pnp(
    points: F64,
    image: F64,
    verdict: Verdict,
    intrinsics: Intrinsics,
    params: MetricPoseParameters,
    scale: float,
    pair: _PairRays,
    method: Method,
    views: _PointViews | None = None,
) -> MetricPose | str:
    """PnP of `image` (query pixels) against `points` (match camera frame), the checks, the
    covariance."""
    k = intrinsics.matrix()
    fit = _fit_pnp(points, image, k, params.reprojection_threshold_px / scale, params)
    if isinstance(fit, str):
        return fit
    rotation, translation, chosen = fit
    residuals = _residuals(points[chosen], image[chosen], rotation, translation, k)
    rms = float(np.sqrt(np.mean(np.square(residuals))))
    if rms > params.max_rms_px / scale:
        return f"residual too large ({rms:.2f} px > {params.max_rms_px / scale:.2f} px)"
    refusal = _disagreement(rotation, translation, verdict, pair, params)
    if refusal:
        return refusal
    variance = max(
        float(residuals @ residuals) / max(residuals.size - 6, 1), params.min_pixel_sigma_px**2
    )
    if views is None:
        covariance = _pnp_covariance(points[chosen], image[chosen], rotation, translation, k)
        covariance *= variance
    else:
        covariance = _marginal_covariance(
            points[chosen], rotation, translation, k, views.subset(chosen), variance
        )
        covariance *= params.odometry_covariance_scale
    return MetricPose(
        method=method,
        rotation_xyzw=_quaternion(rotation),
        translation=(float(translation[0]), float(translation[1]), float(translation[2])),
        covariance=covariance,
        inliers=int(chosen.size),
        rms_px=rms,
    )


def _fit_pnp(
    points: F64, image: F64, k: F64, threshold: float, params: MetricPoseParameters
) -> tuple[F64, F64, npt.NDArray[np.intp]] | str:
    """PnP-RANSAC, then Levenberg-Marquardt on the inliers: (R, t) in the module's convention
    and the inliers' indices, or why not."""
    cv2.setRNGSeed(_FIT_SEED)
    try:
        found, rvec, tvec, inliers = cv2.solvePnPRansac(
            points,
            image,
            k,
            None,
            iterationsCount=params.ransac_iterations,
            reprojectionError=threshold,
            confidence=params.confidence,
        )
    except cv2.error:
        found, inliers = False, None
    count = 0 if inliers is None else len(inliers)
    if not found or count < params.min_inliers:
        return f"too few PnP inliers ({count} < {params.min_inliers})"
    chosen = np.asarray(inliers).ravel()
    rvec, tvec = cv2.solvePnPRefineLM(points[chosen], image[chosen], k, None, rvec, tvec)
    # RANSAC judged the inliers by a minimal-sample model: judge them again by the refined one.
    projected = cv2.projectPoints(points, rvec, tvec, k, None)[0].reshape(-1, 2)
    again = np.flatnonzero(np.linalg.norm(projected - image, axis=1) <= threshold)
    if again.size >= params.min_inliers and not np.array_equal(again, chosen):
        chosen = again
        rvec, tvec = cv2.solvePnPRefineLM(points[chosen], image[chosen], k, None, rvec, tvec)
    # PnP gives the match frame in the query camera: X_query = R_pnp X_match + t_pnp.
    r_pnp = cv2.Rodrigues(rvec)[0]
    return r_pnp.T, -r_pnp.T @ tvec.ravel(), chosen


def _project(points: F64, k: F64) -> F64:
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = points @ k.T
        pixels: F64 = uv[:, :2] / uv[:, 2:3]
    return pixels


def _residuals(points: F64, image: F64, rotation: F64, translation: F64, k: F64) -> F64:
    """Reprojection residuals (2n,) of match-frame points in the query camera, for the pose
    X_match = R X_query + t."""
    in_query = (points - translation) @ rotation  # R^T (X - t), row-wise
    return (_project(in_query, k) - image).ravel()


def _pnp_covariance(points: F64, image: F64, rotation: F64, translation: F64, k: F64) -> F64:
    """(J^T J)^-1 over (t, w) with R' = exp(w) R (the module's convention), the 3-D points
    taken as exact; times sigma^2 it is the covariance."""

    def residuals_at(delta: F64) -> F64:
        perturbed = Rotation.from_rotvec(delta[3:]).as_matrix() @ rotation
        return _residuals(points, image, perturbed, translation + delta[:3], k)

    jacobian = _numeric_jacobian(residuals_at, 6)
    return _symmetric_inverse(jacobian.T @ jacobian)


def _marginal_covariance(
    points: F64, rotation: F64, translation: F64, k: F64, views: _PointViews, variance: float
) -> F64:
    """Rung 2's covariance, in two parts.

    Pixels: the pose's block of (J^T J)^-1 with the triangulated points as free parameters too,
    seen in the query, the match and their neighbour (Schur complement over the points), times
    the pixel variance: a point's depth error moves the pose, which the PnP-only covariance
    ignores. Baselines: the estimate follows a wrong neighbour pose b (the points move, the PnP
    follows them), by G = dpose/db from the two least-squares optima (implicit function
    theorem); each neighbour with a covariance adds G cov G^T.
    """
    in_query = (points - translation) @ rotation  # R^T (X - t)
    j_query = _projection_jacobian(in_query, k) @ rotation.T  # d r_query / d X: (n, 2, 3)
    j_pose = np.concatenate([-j_query, j_query @ _skew_rows(points - translation)], axis=2)
    rotated = np.einsum("nij,nj->ni", views.neighbour_rotation, points)
    j_seen = _projection_jacobian(rotated + views.neighbour_translation, k)
    j_neighbour = j_seen @ views.neighbour_rotation
    j_match = _projection_jacobian(points, k)
    pose_pose = np.einsum("nai,naj->ij", j_pose, j_pose)
    pose_point = np.einsum("nai,naj->nij", j_pose, j_query)
    two_views = np.einsum("nai,naj->nij", j_match, j_match)
    two_views += np.einsum("nai,naj->nij", j_neighbour, j_neighbour)
    point = two_views + np.einsum("nai,naj->nij", j_query, j_query)
    schur = pose_pose - np.einsum("nij,njk,nlk->il", pose_point, np.linalg.inv(point), pose_point)
    covariance = _symmetric_inverse(schur) * variance
    # d r_neighbour / d (t, w) of its pose: the projection of [I, -[R X]x]; then dX / db.
    j_baseline = j_seen @ np.concatenate(
        [np.broadcast_to(np.eye(3), (len(points), 3, 3)), -_skew_rows(rotated)], axis=2
    )
    moved = -np.linalg.inv(two_views) @ (j_neighbour.transpose(0, 2, 1) @ j_baseline)
    follow = _symmetric_inverse(pose_pose)
    for j, baseline_covariance in enumerate(views.covariance):
        mine = views.neighbour_of == j
        if baseline_covariance is None or not mine.any():
            continue
        g = -follow @ np.einsum("nij,njk->ik", pose_point[mine], moved[mine])
        covariance += g @ baseline_covariance @ g.T
    return np.asarray((covariance + covariance.T) / 2, np.float64)


def _projection_jacobian(points: F64, k: F64) -> F64:
    """d pixel / d point of the pinhole projection, per point: (n, 2, 3)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    jacobian = np.zeros((len(points), 2, 3))
    jacobian[:, 0, 0] = k[0, 0] / z
    jacobian[:, 0, 2] = -k[0, 0] * x / z**2
    jacobian[:, 1, 1] = k[1, 1] / z
    jacobian[:, 1, 2] = -k[1, 1] * y / z**2
    return jacobian


def _skew_rows(vectors: F64) -> F64:
    """[v]x for each row v: (n, 3, 3)."""
    skew = np.zeros((len(vectors), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -vectors[:, 2], vectors[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = vectors[:, 2], -vectors[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -vectors[:, 1], vectors[:, 0]
    return skew


def _numeric_jacobian(function: Callable[[F64], F64], size: int) -> F64:
    """Central differences of a function of a `size` vector at zero."""
    columns = []
    for i in range(size):
        step = np.zeros(size)
        step[i] = _JACOBIAN_STEP
        columns.append((function(step) - function(-step)) / (2 * _JACOBIAN_STEP))
    return np.column_stack(columns)


def _symmetric_inverse(matrix: F64) -> F64:
    inverse = np.linalg.pinv(matrix)
    return np.asarray((inverse + inverse.T) / 2, np.float64)


def _disagreement(
    rotation: F64, translation: F64, verdict: Verdict, pair: _PairRays, params: MetricPoseParameters
) -> str:
    """Why the PnP pose is refused against the epipolar fit ("" when it is not)."""
    if verdict.rotation_xyzw is None or verdict.translation_direction is None:
        return ""
    epipolar = Rotation.from_quat(verdict.rotation_xyzw)
    apart = math.degrees((Rotation.from_matrix(rotation) * epipolar.inv()).magnitude())
    if apart <= params.max_rotation_disagreement_deg:
        return ""
    text = (
        f"disagrees with the epipolar fit (rotation {apart:.1f} deg apart > "
        f"{params.max_rotation_disagreement_deg:g} deg"
    )
    if not params.keep_better_supported:
        return text + ")"
    theirs = pair.support(epipolar.as_matrix(), np.asarray(verdict.translation_direction))
    ours = pair.support(rotation, translation)
    if ours > theirs:
        return ""
    return text + f", which explains {theirs} of the {pair.count} matches to the PnP pose's {ours})"


def _quaternion(rotation: F64) -> tuple[float, float, float, float]:
    q = Rotation.from_matrix(rotation).as_quat()
    q = -q if q[3] < 0 else q
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


# -- rung 3: rotation only ----------------------------------------------------------------


def rotation_only(
    query: FrameFeatures,
    match: FrameFeatures,
    verdict: Verdict,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
    *,
    neighbours: Sequence[OdometryNeighbour] = (),
    query_neighbours: Sequence[OdometryNeighbour] = (),
) -> MetricPose | None:
    """Rung 3: the rotation only; None when the verdict has none.

    The rotation is the consensus of several estimates (`_rotation_consensus`; with
    `params.rotation_consensus` off, the verdict's), the translation direction the one that
    explains the most matches for it. Its covariance: the translation variances infinite
    (unknown scale), the rotation block sigma^2 (J^T J)^-1 of the Sampson distances of the ratio
    matches within the verification's threshold of E = [t]x R, over the rotation and the two
    angles of t's direction (the 3x3 rotation marginal); sigma floored as for PnP, and every
    direction's sigma at least `params.rotation_only_min_sigma_deg`.
    """
    if verdict.rotation_xyzw is None or verdict.translation_direction is None:
        return None
    rotation = Rotation.from_quat(verdict.rotation_xyzw).as_matrix()
    direction = np.asarray(verdict.translation_direction, np.float64)
    q_index, m_index = ratio_matches(query, match, verification.ratio)
    pair = _pair_rays(query, match, q_index, m_index, intrinsics, verification)
    if params.rotation_consensus:
        candidates = [rotation]
        candidates += _pair_rotations(query, match, q_index, m_index, pair, intrinsics, params)
        candidates += _chained_rotations(
            query, match, intrinsics, verification, params, neighbours, query_neighbours
        )
        rotation = _rotation_consensus(candidates, params.rotation_agreement_deg)
        direction = _direction_for(pair, rotation, direction)
    rays_q, rays_m, focal = pair.rays_query, pair.rays_match, pair.focal
    distances = pair.distances_px(rotation, direction)
    inlier = np.abs(distances) <= pair.threshold_px
    covariance = np.full((6, 6), 0.0)
    covariance[:3, :3] = np.diag([math.inf] * 3)
    count = int(np.count_nonzero(inlier))
    rms = float(np.sqrt(np.mean(np.square(distances[inlier])))) if count else math.nan
    if count > 5:
        fitted = _rotation_covariance(
            rays_q[inlier], rays_m[inlier], rotation, direction, focal, params.min_pixel_sigma_px
        )
        covariance[3:, 3:] = _floored(fitted, math.radians(params.rotation_only_min_sigma_deg))
    else:
        covariance[3:, 3:] = np.diag([math.inf] * 3)
    return MetricPose("rotation_only", _quaternion(rotation), None, covariance, count, rms)


def _pair_rotations(
    query: FrameFeatures,
    match: FrameFeatures,
    q_index: npt.NDArray[np.int64],
    m_index: npt.NDArray[np.int64],
    pair: _PairRays,
    intrinsics: Intrinsics,
    params: MetricPoseParameters,
) -> list[F64]:
    """The pair's rotation from its (metric) features: an essential fit (RANSAC) and the
    rotation of a homography (K^-1 H K, nearest rotation), which a short baseline before a
    distant scene explains nearly as well. Either left out when its fit fails."""
    p_query = query.keypoints[q_index].astype(np.float64)
    p_match = match.keypoints[m_index].astype(np.float64)
    if len(p_query) < 8:
        return []
    k = intrinsics.matrix()
    found = []
    cv2.setRNGSeed(_FIT_SEED)
    try:
        essential, mask = cv2.findEssentialMat(
            p_query, p_match, k, cv2.RANSAC, params.confidence, pair.threshold_px, 2000
        )
        if essential is not None and mask is not None and essential.shape[0] >= 3:
            _, turn, _, _ = cv2.recoverPose(essential[:3], p_query, p_match, k, mask=mask)
            found.append(np.asarray(turn, np.float64))
        cv2.setRNGSeed(_FIT_SEED)
        homography, _ = cv2.findHomography(
            p_query, p_match, cv2.RANSAC, pair.threshold_px, maxIters=2000, confidence=0.999
        )
    except cv2.error:
        return found
    # Always a candidate: gating it by its support as ORB-SLAM's initialisation does (H when
    # it explains 0.8 or 1.0 times the essential fit's matches) made the consensus worse on
    # the calibration drives; a biased one is outvoted or averaged with the essential fits.
    if homography is not None:
        found.append(_nearest_rotation(np.linalg.inv(k) @ homography @ k))
    return found


def _chained_rotations(
    query: FrameFeatures,
    match: FrameFeatures,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
    neighbours: Sequence[OdometryNeighbour],
    query_neighbours: Sequence[OdometryNeighbour],
) -> list[F64]:
    """The pair's rotation through frames near it: the query's essential fit against each
    neighbour of the match, and each neighbour of the query's against the match (the
    verification's check, on these features), chained with the neighbour's odometry rotation
    refined by its images (`_refined_baseline`). A wider baseline than the pair's own, and
    other matches: an estimate whose errors are not the pair's."""
    found = []
    for neighbour in neighbours:  # X_n = R_n X_match + t
        verdict = verify_pair(query, neighbour.features, verification, intrinsics)
        if verdict.rotation_xyzw is not None:
            baseline = _baseline_rotation(match, neighbour, intrinsics, verification, params)
            found.append(baseline.T @ Rotation.from_quat(verdict.rotation_xyzw).as_matrix())
    for neighbour in query_neighbours:  # X_n = R_n X_query + t
        verdict = verify_pair(neighbour.features, match, verification, intrinsics)
        if verdict.rotation_xyzw is not None:
            baseline = _baseline_rotation(query, neighbour, intrinsics, verification, params)
            found.append(Rotation.from_quat(verdict.rotation_xyzw).as_matrix() @ baseline)
    return found


def _baseline_rotation(
    frame: FrameFeatures,
    neighbour: OdometryNeighbour,
    intrinsics: Intrinsics,
    verification: VerificationParameters,
    params: MetricPoseParameters,
) -> F64:
    if params.refine_baselines:
        neighbour = _refined_baseline(frame, neighbour, intrinsics, verification, params)
    return np.asarray(Rotation.from_quat(neighbour.rotation_xyzw).as_matrix(), np.float64)


def _rotation_consensus(candidates: Sequence[F64], agreement_deg: float) -> F64:
    """The mean (chordal) of the candidates within `agreement_deg` of their medoid (the one
    with the least summed angle to the others; the first on a tie)."""
    stacked = Rotation.from_matrix(np.stack(candidates))
    apart = np.array([(stacked * one.inv()).magnitude() for one in stacked])
    medoid = int(np.argmin(apart.sum(axis=1)))
    near = np.flatnonzero(apart[medoid] <= math.radians(agreement_deg))
    return np.asarray(stacked[near].mean().as_matrix(), np.float64)


def _nearest_rotation(matrix: F64) -> F64:
    u, _, vt = np.linalg.svd(matrix)
    rotation: F64 = u @ vt
    return rotation if np.linalg.det(rotation) > 0 else -rotation


def _direction_for(pair: _PairRays, rotation: F64, fallback: F64) -> F64:
    """The translation direction that explains the most matches for a fixed rotation: t is
    orthogonal to each match's (R x_q) x x_m, so two matches give one candidate (their cross
    product); the best supported, then the least-squares direction of the matches it explains.
    `fallback` (the verdict's) when too few matches."""
    normals = np.cross(pair.rays_query @ rotation.T, pair.rays_match)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    first, second = np.triu_indices(min(len(normals), _DIRECTION_SEEDS), 1)
    candidates = np.cross(normals[first], normals[second])
    lengths = np.linalg.norm(candidates, axis=1)
    candidates = candidates[lengths > 1e-9] / lengths[lengths > 1e-9, None]
    if len(candidates) == 0:
        return fallback
    best: F64 = candidates[int(np.argmax(pair.supports(rotation, candidates)))]
    explained = np.abs(pair.distances_px(rotation, best)) <= pair.threshold_px
    if np.count_nonzero(explained) >= 2:
        best = np.asarray(np.linalg.svd(normals[explained], full_matrices=False)[2][-1], np.float64)
    return best if float(best @ fallback) >= 0 else -best


@dataclass(frozen=True, eq=False)
class _PairRays:
    """The pair's ratio matches as normalized rays, to check an epipolar geometry against."""

    rays_query: F64
    rays_match: F64
    focal: float  # pixels per normalized unit, for Sampson distances in pixels
    threshold_px: float  # the verification's, in original pixels

    @property
    def count(self) -> int:
        return int(self.rays_query.shape[0])

    def distances_px(self, rotation: F64, translation: F64) -> F64:
        """Signed Sampson distances (pixels) to E = [t]x R."""
        norm = max(float(np.linalg.norm(translation)), 1e-12)
        distances: F64 = _sampson(self.rays_query, self.rays_match, rotation, translation / norm)
        return distances * self.focal

    def support(self, rotation: F64, translation: F64) -> int:
        """How many matches lie within the threshold of E = [t]x R."""
        distances = self.distances_px(rotation, translation)
        return int(np.count_nonzero(np.abs(distances) <= self.threshold_px))

    def supports(self, rotation: F64, directions: F64) -> npt.NDArray[np.intp]:
        """`support` of each unit row of `directions` with the same rotation, at once (in
        blocks: a (block, matches, 3) array each)."""
        turned = self.rays_query @ rotation.T  # R x_q
        counts = []
        for start in range(0, len(directions), _SUPPORT_BLOCK):
            t = directions[start : start + _SUPPORT_BLOCK, None, :]
            line = np.cross(t, turned[None])  # E x_q = t x R x_q
            back = np.cross(t, self.rays_match[None]) @ rotation  # -(E^T x_m), as rows
            numerator = np.sum(self.rays_match[None] * line, axis=2)
            denominator = np.sqrt(np.sum(line[..., :2] ** 2 + back[..., :2] ** 2, axis=2))
            distances = numerator / np.maximum(denominator, 1e-12) * self.focal
            counts.append(np.count_nonzero(np.abs(distances) <= self.threshold_px, axis=1))
        return np.concatenate(counts) if counts else np.zeros(0, np.intp)


def _pair_rays(
    query: FrameFeatures,
    match: FrameFeatures,
    q_index: npt.NDArray[np.int64],
    m_index: npt.NDArray[np.int64],
    intrinsics: Intrinsics,
    verification: VerificationParameters,
) -> _PairRays:
    k_inv = np.asarray(np.linalg.inv(intrinsics.matrix()), np.float64)
    return _PairRays(
        _rays(query.keypoints[q_index], k_inv),
        _rays(match.keypoints[m_index], k_inv),
        (intrinsics.fx + intrinsics.fy) / 2,
        verification.ransac_threshold_px / min(query.scale, match.scale),
    )


def _rays(pixels: npt.NDArray[np.float32], k_inv: F64) -> F64:
    homogeneous = np.column_stack([pixels.astype(np.float64), np.ones(len(pixels))])
    rays: F64 = homogeneous @ k_inv.T
    return rays


def _sampson(rays_q: F64, rays_m: F64, rotation: F64, direction: F64) -> F64:
    """Signed Sampson distance (normalized units) of each correspondence to E = [t]x R."""
    essential = _skew(direction) @ rotation
    e_q = rays_q @ essential.T  # E x_q: the epipolar line in the match image
    e_t_m = rays_m @ essential  # E^T x_m
    numerator = np.sum(rays_m * e_q, axis=1)
    denominator = np.sqrt(e_q[:, 0] ** 2 + e_q[:, 1] ** 2 + e_t_m[:, 0] ** 2 + e_t_m[:, 1] ** 2)
    distances: F64 = numerator / np.maximum(denominator, 1e-12)
    return distances


def _skew(v: F64) -> F64:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]], np.float64)


def _floored(covariance: F64, min_sigma: float) -> F64:
    """`covariance` with its eigenvalues raised to at least min_sigma^2 (same axes)."""
    values, vectors = np.linalg.eigh((covariance + covariance.T) / 2)
    floored: F64 = (vectors * np.maximum(values, min_sigma**2)) @ vectors.T
    return floored


def _rotation_covariance(
    rays_q: F64, rays_m: F64, rotation: F64, direction: F64, focal: float, min_sigma: float
) -> F64:
    """Rotation block of sigma^2 (J^T J)^-1 over (w, two tangent angles of t's direction)."""
    tangent = np.linalg.svd(direction[None, :])[2][1:]  # two unit vectors orthogonal to t

    def distances_at(delta: F64) -> F64:
        perturbed = Rotation.from_rotvec(delta[:3]).as_matrix() @ rotation
        moved = direction + tangent.T @ delta[3:]
        return _sampson(rays_q, rays_m, perturbed, moved / np.linalg.norm(moved)) * focal

    jacobian = _numeric_jacobian(distances_at, 5)
    distances = distances_at(np.zeros(5))
    variance = float(distances @ distances) / max(distances.size - 5, 1)
    return _symmetric_inverse(jacobian.T @ jacobian)[:3, :3] * max(variance, min_sigma**2)
