"""Geometric verification of a loop-closure pair: local features, ratio test, robust epipolar fit.

Pure computation: gray frames in, verdicts out. Features are extracted once per frame
(`extract_features`, cacheable), then any pair is checked with `verify_pair`: descriptors are
matched with Lowe's ratio test (one match per feature of the match frame), and a fundamental
matrix (or, with intrinsics, an essential matrix) is fitted robustly; the pair is accepted when
the inliers reach `min_inliers`. With intrinsics the relative pose (rotation, direction of
translation) comes from the essential matrix by cv2.recoverPose (the rotation of a pair seen
from nearly one spot from a homography: HOMOGRAPHY_SHARE).

Determinism: OpenCV 5.0's RANSAC (FM_RANSAC, RANSAC) and USAC (USAC_MAGSAC) seed their own
random generators on every call (measured: the global cv::RNG state changes nothing), and the
features are put in a canonical order, so the same two frames give the same verdict on every
run. The thread's cv::RNG is still re-seeded before each fit (`_FIT_SEED`), so that a build
drawing from it would stay deterministic; callers relying on cv::theRNG() should know that.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ..detector.segmentation import feature_image
from .hamming import two_nearest
from .params import VerificationParameters

GrayImage = npt.NDArray[np.uint8]
Points = npt.NDArray[np.float32]
Model = Literal["F", "E"]

# Minimal sample sizes: 7-point fundamental matrix (8 for FM_RANSAC's check), 5-point essential.
_MIN_POINTS: dict[Model, int] = {"F": 8, "E": 5}
_FACTORIES = {
    "sift": "SIFT_create",
    "orb": "ORB_create",
    "akaze": "AKAZE_create",
    "brisk": "BRISK_create",
}
_FIT_SEED = 0
_DESCRIPTOR_BYTES = {"sift": 128, "orb": 32, "akaze": 61, "brisk": 64}
# How much finer a feature-poor frame is looked at again (`extract_features`).
DETAIL_FACTOR = 2
# The reason of a refined match rejected by `bracketed_match`.
NOT_BRACKETED = "not bracketed"
# A pair whose essential fit turns past max_rotation_deg, with the inliers of a second guess
# (second_guess_factor x min_inliers: a rotation measured again is one more chance to pass a
# look-alike, and 90 % of a few dozen points may lie on one plane by chance), is measured
# again by a homography fitted to that fit's inliers: where it explains at least this share
# of them, the scene is far for the baseline (a revisit from nearly the same spot), the
# essential matrix's decomposition is ill-conditioned there (its rotation off by 5-15 degrees
# on generated drives), and the rotation nearest K^-1 H K is the pair's
# (`_homography_rotation`).
HOMOGRAPHY_SHARE = 0.9
# The homography's inlier distance, in multiples of the essential fit's: a point's transfer
# error is measured in one image, the epipolar distance only across the epipolar line.
HOMOGRAPHY_THRESHOLD_FACTOR = 2.0
# Inlier correspondences an accepted verdict keeps at most, for drawing: enough to show where
# the two images agree, and a bounded cost per reported pair whatever its inliers.
MAX_INLIER_POINTS = 200


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of the original (unshrunk) frame, in pixels; no distortion."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in values) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics need finite values and fx, fy > 0, got {values}")

    @classmethod
    def assumed(cls, width: int, height: int) -> Intrinsics:
        """A pinhole guess for a camera whose K is unusable: focal length the larger image
        side (a 53-degree field of view across it), principal point at the centre. The
        essential fit's rotation limit and bracketing tolerate a focal length well off the
        true one, where the fundamental matrix passes look-alikes."""
        focal = float(max(width, height, 1))
        return cls(focal, focal, width / 2, height / 2)

    def matrix(self) -> npt.NDArray[np.float64]:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float64)


@dataclass(frozen=True, eq=False, slots=True)
class FrameFeatures:
    """One frame's local features, compact enough to cache for every frame of a log.

    `keypoints` is N x 2 float32 (x, y) in pixels of the original frame; `descriptors` is
    N x D uint8: ORB 32, BRISK 64, AKAZE 61 bytes, SIFT 128 (OpenCV's SIFT values are integers
    in 0..255, so uint8 is lossless). Per frame that is N * (8 + D) bytes (`nbytes`) plus about
    400 bytes of Python objects: at most 40 kB with the default 1000 ORB features, 136 kB for
    1000 SIFT features. Features are sorted by detector response (strongest first), ties by
    position: a canonical order.
    """

    keypoints: Points
    descriptors: npt.NDArray[np.uint8]
    detector: str
    # Feature-image pixels per original pixel (the smaller axis): < 1 for a shrunk frame, > 1
    # for a small one enlarged (`feature_image`), 1 for a frame detected at its own size.
    scale: float
    # ORB only: each feature's pyramid level (KeyPoint.octave), so that the segmentation can
    # take the features ORB would keep with a smaller budget (segmentation.OrbFeatures).
    levels: npt.NDArray[np.uint8] | None = None

    @property
    def count(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the two arrays."""
        return int(self.keypoints.nbytes + self.descriptors.nbytes)


@dataclass(frozen=True, eq=False, slots=True)
class InlierPoints:
    """Where an accepted pair's images agree: the robust fit's inliers (the first
    MAX_INLIER_POINTS in ratio-test order), row i of `query` matching row i of `match`, each
    N x 2 float32 (x, y) in its own frame's original pixels (pixel centres at integers, as
    `FrameFeatures.keypoints`), whatever size the features were detected at."""

    query: Points
    match: Points

    @property
    def count(self) -> int:
        return int(self.query.shape[0])


@dataclass(frozen=True)
class Verdict:
    """The outcome of checking one (query, match) pair.

    `inliers` counts the correspondences consistent with the fitted model (0 when no model was
    fitted; for "E" the RANSAC inliers, before recoverPose's chirality check); `matches_tested`
    the ratio-test matches given to the robust fit (0 when a frame had too few features).

    The pose fields are set only when intrinsics were given and the fit reached min_inliers
    (a pair rejected afterwards, by max_rotation_deg or bracketing, keeps them):
    `rotation_xyzw` is the unit quaternion (x, y, z, w) of R and `translation_direction` the
    unit vector t, with X_match = R X_query + t for a 3-D point X in each camera's frame
    (cv2.recoverPose with the query as the first view); `rotation_deg` is the angle of R.

    `inlier_points` is set on an accepted verdict only (the visualization draws them): a
    rejected pair keeps none, so checking it costs nothing more.
    """

    accepted: bool
    inliers: int
    matches_tested: int
    model: Model
    # "accepted", "too few features", "too few matches", "no model", "too few inliers",
    # "rotation over N deg", NOT_BRACKETED
    reason: str
    rotation_xyzw: tuple[float, float, float, float] | None = None
    rotation_deg: float | None = None
    translation_direction: tuple[float, float, float] | None = None
    inlier_points: InlierPoints | None = field(default=None, compare=False, repr=False)

    def without_points(self) -> Verdict:
        """This verdict without its inlier points (a rejected pair keeps none)."""
        if self.inlier_points is None:
            return self
        return dataclasses.replace(self, inlier_points=None)


def extract_features(gray: GrayImage, params: VerificationParameters) -> FrameFeatures:
    """Detect and describe the strongest `params.max_features` features of a gray frame,
    shrunk to `params.image_max_side` (a smaller frame enlarged to it: `feature_image`); a
    frame with fewer than `params.detail_below` there and larger than that side is detected
    again at DETAIL_FACTOR times that side (enlarged to it if need be), and the finer look is
    kept when it finds more.

    A flat or empty frame gives zero features (not an error).

    Raises:
        ValueError: `gray` is not a 2-D uint8 array.
    """
    if not isinstance(gray, np.ndarray) or gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError("extract_features needs a 2-D uint8 gray image")
    if gray.size == 0:
        return _empty_features(params, 1.0)
    features = _detect(gray, params.image_max_side, params)
    if features.count < params.detail_below and max(gray.shape) > params.image_max_side:
        finer = _detect(gray, DETAIL_FACTOR * params.image_max_side, params)
        if finer.count > features.count:
            return finer
    return features


def _detect(gray: GrayImage, max_side: int, params: VerificationParameters) -> FrameFeatures:
    """The strongest features of `gray` shrunk to `max_side` (enlarged to it when smaller:
    a frame of 160x120 gave 9 true pairs on a generated 5-minute drive, 239 enlarged), in
    original pixels."""
    small = feature_image(gray, max_side, enlarge_below=max_side)
    # Per axis: each side is rounded separately, so the two ratios differ by < 1 px.
    scale_xy = np.array([small.shape[1] / gray.shape[1], small.shape[0] / gray.shape[0]])
    scale = float(scale_xy.min())
    keypoints, descriptors = _make_extractor(params).detectAndCompute(small, None)
    if descriptors is None or len(keypoints) == 0:
        return _empty_features(params, scale)
    xy = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    response = np.array([k.response for k in keypoints], dtype=np.float64)
    # Strongest first; position breaks ties so the order never depends on detector internals.
    order = np.lexsort((xy[:, 1], xy[:, 0], -response))[: params.max_features]
    # Pixel centres: x_original = (x_small + 0.5) / scale - 0.5 (cv2.resize's convention).
    original = (xy[order] + 0.5) / scale_xy - 0.5
    levels = None
    if params.feature_detector == "orb":
        levels = np.array([k.octave for k in keypoints], dtype=np.uint8)[order]
    return FrameFeatures(
        keypoints=np.ascontiguousarray(original, dtype=np.float32),
        descriptors=np.ascontiguousarray(descriptors[order], dtype=np.uint8),
        detector=params.feature_detector,
        scale=scale,
        levels=levels,
    )


def verify_pair(
    query: FrameFeatures,
    match: FrameFeatures,
    params: VerificationParameters,
    intrinsics: Intrinsics | None = None,
) -> Verdict:
    """Check that two frames see the same place: ratio-test matches, then a robust F or E fit,
    accepted at `params.min_inliers` inliers (`small_frame_min_inliers` when a frame of the
    pair was enlarged: its `scale` exceeds 1).

    Degenerate inputs (too few features or matches, a fit that fails) give a rejected verdict.

    Raises:
        ValueError: the two frames' features come from different detectors (or descriptor
            widths).
    """
    if (
        query.detector != match.detector
        or query.descriptors.shape[1:] != match.descriptors.shape[1:]
    ):
        raise ValueError(f"cannot match {query.detector} features against {match.detector}")
    needed_inliers = pair_min_inliers(query, match, params)
    if needed_inliers != params.min_inliers:  # a replace validates: not on every pair
        params = dataclasses.replace(params, min_inliers=needed_inliers)
    model: Model = "F" if intrinsics is None else "E"
    needed = max(_MIN_POINTS[model], params.min_inliers)
    if min(query.count, match.count) < needed:
        return Verdict(False, 0, 0, model, "too few features")
    q_index, m_index = _ratio_matches(query, match, params.ratio)
    tested = int(q_index.size)
    if tested < needed:  # cannot reach min_inliers: skip the robust fit
        return Verdict(False, 0, tested, model, "too few matches")
    p_query, p_match = query.keypoints[q_index], match.keypoints[m_index]
    # The threshold is in feature-image pixels; keypoints are in original pixels.
    threshold = params.ransac_threshold_px / min(query.scale, match.scale)
    if intrinsics is None:
        mask = _fundamental_inliers(p_query, p_match, threshold, params)
        verdict = _verdict(_count(mask), tested, model, params)
        return _with_points(verdict, p_query, p_match, mask)
    return _essential_verdict(p_query, p_match, threshold, tested, params, intrinsics)


def pair_min_inliers(
    query: FrameFeatures, match: FrameFeatures, params: VerificationParameters
) -> int:
    """The inliers a pair needs: `small_frame_min_inliers` when a frame of it was enlarged (its
    `scale` exceeds 1: a thumbnail has fewer features to agree on), else `min_inliers`."""
    if max(query.scale, match.scale) > 1:
        return params.small_frame_min_inliers
    return params.min_inliers


def refine_match(
    query: FrameFeatures,
    candidates: Sequence[tuple[int, FrameFeatures]],
    params: VerificationParameters,
    intrinsics: Intrinsics | None = None,
    *,
    original: int | None = None,
) -> tuple[int, Verdict]:
    """Verify `query` against each (frame index, features) and keep the frame with most inliers.

    Ties go to `original` (the detector's match) when it is among the candidates, then to the
    lower frame index (`best_verdict`). The caller chooses the frames, e.g. the detector's
    match +- `params.refine_radius`, clipped to the sequence's database.

    Raises:
        ValueError: `candidates` is empty, or features come from different detectors.
    """
    verdicts = [(i, verify_pair(query, features, params, intrinsics)) for i, features in candidates]
    return best_verdict(verdicts, original)


def best_verdict(
    verdicts: Sequence[tuple[int, Verdict]], original: int | None = None
) -> tuple[int, Verdict]:
    """The accepted (frame index, verdict) with the most inliers, else the rejected one with the
    most; ties: `original`, then the lower index.

    Inliers rank the frames whether or not they reach `min_inliers`, so the choice of frame
    does not depend on the acceptance threshold; accepted frames come first because a fit with
    many inliers can still be rejected (its rotation over `max_rotation_deg`).

    Raises:
        ValueError: `verdicts` is empty.
    """
    if not verdicts:
        raise ValueError("refine_match needs at least one candidate frame")
    return min(
        verdicts,
        key=lambda item: (not item[1].accepted, -item[1].inliers, item[0] != original, item[0]),
    )


def match_camera_direction(verdict: Verdict) -> npt.NDArray[np.float64] | None:
    """Unit direction of the match camera's centre in the query camera's frame (-R^T t):
    z > 0 when the match frame was taken ahead of the query along its optical axis. None
    without a relative pose."""
    if verdict.rotation_xyzw is None or verdict.translation_direction is None:
        return None
    # R^T v = v - 2w (u x v) + 2 u x (u x v) for the unit quaternion (u, w), in floats: a
    # bracketing reads this for every frame of its run, and scipy's Rotation objects cost
    # far more than the arithmetic on one vector.
    x, y, z, w = verdict.rotation_xyzw
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    vx, vy, vz = (-c for c in verdict.translation_direction)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx  # u x v
    ccx, ccy, ccz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx  # u x (u x v)
    return np.array(
        [vx - 2 * w * cx + 2 * ccx, vy - 2 * w * cy + 2 * ccy, vz - 2 * w * cz + 2 * ccz]
    )


def bracketed_match(
    verdicts: Sequence[tuple[int, Verdict]],
    refined: int,
    verdict: Verdict,
    max_gap: int | None = None,
) -> tuple[int, Verdict]:
    """The frame nearest the query among the verified frames around `refined`, or `refined`
    rejected (NOT_BRACKETED) when the query's position does not lie between two of them.

    `verdicts` are the checked frames of one window; the run is the frames next to `refined`
    (in frame order) whose fit reached min_inliers with a relative pose, those then rejected
    for their rotation included: a crossing at such a frame rejects the pair with that
    frame's verdict, instead of a frame further on whose rotation happens to pass. Along a
    trajectory driven the same way as the query, the match camera is behind the query
    (z < 0, `match_camera_direction`) before the nearest point and ahead after it: a sign
    change between neighbours of the run brackets the query, and the one of the two with
    the smaller |z| is the nearer. Signs are noisy where the cameras are closest, so the
    change kept is the one that best splits the whole run into "behind" then "ahead"
    (`_crossing`), and none is kept when every split leaves too many frames on the wrong
    side. With `max_gap`, the run also ends where two checked frames are more than that many
    frames apart: what lies between was not looked at. Without a change, every verified frame
    is on one side: the views overlap, but the
    camera was not where the query was (e.g. the same facades seen from several metres
    further on). Accepted verdicts without a pose (fundamental matrix) are returned
    unchanged. Assumes a forward-looking camera.

    Raises:
        ValueError: `refined` is not one of the frames of `verdicts`.
    """
    run = _run(verdicts, refined, max_gap)
    if not _has_pose(verdict):
        return refined, verdict
    found = _crossing_in(run)
    if found is None:
        return refined, dataclasses.replace(verdict, accepted=False, reason=NOT_BRACKETED)
    in_run = dict(run)
    before, after = (found.before, in_run[found.before]), (found.after, in_run[found.after])
    nearer, other = (
        (before, after) if abs(_ahead(before[1])) < abs(_ahead(after[1])) else (after, before)
    )
    if not other[1].accepted and nearer[1].accepted:
        # The place lies between a frame turned past max_rotation_deg and one that is not: the
        # heading changes fast there, and the one estimate under the limit is not to be
        # trusted alone (on small frames a pair turned far past the limit can be estimated
        # under it).
        return nearer[0], dataclasses.replace(nearer[1], accepted=False, reason=other[1].reason)
    # The nearer frame, with its own verdict: rejected when the camera there is turned past
    # max_rotation_deg (the place is there, but not seen from the query's heading).
    return nearer


@dataclass(frozen=True)
class Crossing:
    """Where `bracketed_match` places the query along the run of frames around the refined
    match: between frames `before` and `after`, with the run's frames that agree with it on
    each side (`behind`: before the crossing, the match camera behind the query; `ahead`:
    after it, ahead)."""

    before: int
    after: int
    behind: tuple[int, ...]
    ahead: tuple[int, ...]
    run: int  # frames in the run, those on the wrong side of the crossing included

    @property
    def wrong(self) -> int:
        """The run's frames on the wrong side of the crossing."""
        return self.run - len(self.behind) - len(self.ahead)


def crossing(
    verdicts: Sequence[tuple[int, Verdict]], refined: int, max_gap: int | None = None
) -> Crossing | None:
    """The crossing `bracketed_match` finds among `verdicts` around `refined` (None: no
    crossing).

    Raises:
        ValueError: `refined` is not one of the frames of `verdicts`.
    """
    return _crossing_in(_run(verdicts, refined, max_gap))


def _crossing_in(run: list[tuple[int, Verdict]]) -> Crossing | None:
    """The crossing of a run (`_run`), None where `_crossing` finds none."""
    sides = [_side(v) for _, v in run]
    i = _crossing(sides, [v.inliers for _, v in run])
    if i is None:
        return None
    frames = [frame for frame, _ in run]
    behind = tuple(frames[k] for k in range(i + 1) if sides[k] < 0)
    ahead = tuple(frames[k] for k in range(i + 1, len(run)) if sides[k] > 0)
    return Crossing(frames[i], frames[i + 1], behind, ahead, len(run))


def _run(
    verdicts: Sequence[tuple[int, Verdict]], refined: int, max_gap: int | None
) -> list[tuple[int, Verdict]]:
    """The frames next to `refined` (in frame order, itself included) whose fit has a
    relative pose (`_fitted`), up to a gap of more than `max_gap` frames."""
    ordered = sorted(verdicts, key=lambda item: item[0])
    frames = [frame for frame, _ in ordered]
    if refined not in frames:
        raise ValueError(f"frame {refined} is not among the checked frames")
    at = frames.index(refined)
    first, last = at, at

    def joins(i: int, j: int) -> bool:
        near = max_gap is None or abs(frames[j] - frames[i]) <= max_gap
        return near and _fitted(ordered[j][1])

    while first > 0 and joins(first, first - 1):
        first -= 1
    while last + 1 < len(ordered) and joins(last, last + 1):
        last += 1
    return ordered[first : last + 1]


def _crossing(sides: list[int], inliers: list[int]) -> int | None:
    """The sign change i (sides[i] < 0 < sides[i + 1]) that best splits the run into frames
    behind (-1) then ahead (+1): the most frames on their split's side, then the most
    inliers of the pair, among the changes with more frames on their side than not on each
    side; None when no such change leaves at most (n - 1) // 4 of the n frames on the wrong
    side.

    The direction of t is least certain where the cameras are closest and the scene is far:
    there one frame's sign can flip, and so can the near-zero signs of the true crossing. A
    lone flip amid one side ("- + - -", "+ + - +") splits no run well, so it brackets no false
    pair, and a crossing stays the best split with a flip beside it or inside it. Smoothing the
    flips away first (median-of-three) would not do: it also erases a true crossing whose
    signs are near zero, and a later change is taken instead.
    """
    n = len(sides)
    behind_before = [0] * (n + 1)  # frames behind among the first k
    for k, side in enumerate(sides):
        behind_before[k + 1] = behind_before[k] + (side < 0)
    ahead_total = n - behind_before[n]
    best: tuple[int, int, int] | None = None  # (agreeing frames, pair inliers, -i)
    for i in range(n - 1):
        if not sides[i] < 0 < sides[i + 1]:
            continue
        ahead_after = ahead_total - ((i + 1) - behind_before[i + 1])
        # Each side mostly on its side: a flip beside the run's end ("+ - + + +") leaves the
        # short side half wrong, a sign change that splits nothing.
        if 2 * behind_before[i + 1] <= i + 1 or 2 * ahead_after <= n - i - 1:
            continue
        score = (behind_before[i + 1] + ahead_after, inliers[i] + inliers[i + 1], -i)
        best = score if best is None or score > best else best
    if best is None or n - best[0] > (n - 1) // 4:
        return None
    return -best[2]


def turned_past(verdict: Verdict, limit_deg: float) -> bool:
    """Whether the verdict's relative pose turns past `limit_deg` (False without a pose)."""
    return verdict.rotation_deg is not None and verdict.rotation_deg > limit_deg


def turned_too_far(limit_deg: float) -> str:
    """The reason of a pair rejected for a rotation over `limit_deg`."""
    return f"rotation over {limit_deg:g} deg"


def side_of_query(verdict: Verdict) -> int:
    """Where the query's place lies along the match's trajectory, from one verified frame: +1
    at later frames (the match camera is behind the query, z < 0: `bracketed_match`'s sign
    rule), -1 at earlier ones, 0 for a verdict that did not pass with a relative pose. Assumes
    a forward-looking camera driven the same way, as `bracketed_match` does."""
    return -_side(verdict) if _has_pose(verdict) else 0


def crossing_side(verdict: Verdict) -> int:
    """The side of a crossing a frame lies on, as a run counts it (`bracketed_match`): -1
    before it (the match camera behind the query, z < 0), +1 after it, 0 without a relative
    pose. A fit turned past the limit has one and counts."""
    return _side(verdict) if _fitted(verdict) else 0


def _side(verdict: Verdict) -> int:
    """A run's sign of a frame: -1 where the match camera is behind the query (z < 0), else
    +1 (z = 0 too, and a frame without a direction, whose z reads 0)."""
    return 1 if _ahead(verdict) >= 0 else -1


def _has_pose(verdict: Verdict) -> bool:
    return verdict.accepted and verdict.translation_direction is not None


def _fitted(verdict: Verdict) -> bool:
    """The fit reached min_inliers with a relative pose, whether or not its rotation was
    then over max_rotation_deg: its side of the query counts in a run."""
    return verdict.translation_direction is not None


def _ahead(verdict: Verdict) -> float:
    direction = match_camera_direction(verdict)
    return 0.0 if direction is None else float(direction[2])


# -- features -----------------------------------------------------------------------------


def _make_extractor(params: VerificationParameters) -> Any:
    """A fresh OpenCV feature object (cheap to create; not shared, so callers may use threads)."""
    name, budget = params.feature_detector, params.max_features
    # cv2's type stubs lack the factories; AKAZE/BRISK live in cv2.xfeatures2d in OpenCV 5.
    factory: Any = getattr(cv2, _FACTORIES[name], None) or getattr(
        cv2.xfeatures2d, _FACTORIES[name]
    )
    if name == "orb":
        return factory(nfeatures=budget, fastThreshold=params.fast_threshold)
    if name == "sift":
        return factory(nfeatures=budget)
    return factory()  # no feature budget: extract_features keeps the strongest


def _empty_features(params: VerificationParameters, scale: float) -> FrameFeatures:
    return FrameFeatures(
        keypoints=np.empty((0, 2), np.float32),
        descriptors=np.empty((0, _DESCRIPTOR_BYTES[params.feature_detector]), np.uint8),
        detector=params.feature_detector,
        scale=scale,
    )


def ratio_matches(
    query: FrameFeatures, match: FrameFeatures, ratio: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(query indices, match indices) of the ratio-test matches `verify_pair` fits: at most one
    per match-frame feature (for the metric pose, which needs the correspondences)."""
    return _ratio_matches(query, match, ratio)


def _ratio_matches(
    query: FrameFeatures, match: FrameFeatures, ratio: float
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Indices of ratio-test matches, at most one per match-frame feature (the closest).

    Many-to-one matches (repeated texture, e.g. a corridor's doors) would each count as an
    inlier of the same point; keeping one per feature stops them inflating the count. The two
    nearest neighbours come as arrays (brute force, like BFMatcher's knnMatch, whose matches
    it reproduces: tested), so no Python object is made per feature and the GIL stays free
    for the other verification thread: binary descriptors' from `hamming.two_nearest`, SIFT's
    from `cv2.batchDistance`.
    """
    a: npt.NDArray[Any] = query.descriptors
    b: npt.NDArray[Any] = match.descriptors
    if len(a) == 0 or len(b) < 2:  # no second neighbour: no match passes the ratio test
        return np.empty(0, np.int64), np.empty(0, np.int64)
    if query.detector == "sift":  # float L2 is faster than OpenCV's uint8 L2 path
        a, b = a.astype(np.float32), b.astype(np.float32)
        distance, nearest = cv2.batchDistance(a, b, cv2.CV_32F, normType=cv2.NORM_L2, K=2)
    else:  # binary descriptors: Hamming distances
        distance, nearest = two_nearest(a, b)
    passed = distance[:, 0] < ratio * distance[:, 1]
    q_index = np.flatnonzero(passed)
    m_index = nearest[q_index, 0].astype(np.int64)
    # One query per match feature: the closest; ties go to the first query (knnMatch order).
    order = np.lexsort((q_index, distance[q_index, 0], m_index))
    m_sorted, q_sorted = m_index[order], q_index[order]
    first = np.ones(m_sorted.size, bool)
    first[1:] = m_sorted[1:] != m_sorted[:-1]
    return q_sorted[first].astype(np.int64), m_sorted[first]


# -- robust fits --------------------------------------------------------------------------


def _fundamental_inliers(
    p_query: Points, p_match: Points, threshold: float, params: VerificationParameters
) -> npt.NDArray[Any] | None:
    """The inlier mask of a robust fundamental-matrix fit (None when OpenCV finds no model)."""
    method = cv2.FM_RANSAC if params.method == "ransac" else cv2.USAC_MAGSAC
    cv2.setRNGSeed(_FIT_SEED)
    try:
        fundamental, mask = cv2.findFundamentalMat(
            p_query, p_match, method, threshold, params.confidence, params.max_iterations
        )
    except cv2.error:  # degenerate configurations (e.g. all points equal) raise in some paths
        return None
    if fundamental is None or mask is None or fundamental.shape != (3, 3):
        return None
    return mask


def _count(mask: npt.NDArray[Any] | None) -> int:
    return 0 if mask is None else int(np.count_nonzero(mask))


def _with_points(
    verdict: Verdict, p_query: Points, p_match: Points, mask: npt.NDArray[Any] | None
) -> Verdict:
    """An accepted verdict with its inliers' points (MAX_INLIER_POINTS at most); a rejected
    one as it is."""
    if not verdict.accepted or mask is None:
        return verdict
    kept = np.flatnonzero(mask.ravel())[:MAX_INLIER_POINTS]
    points = InlierPoints(
        np.ascontiguousarray(p_query[kept], np.float32),
        np.ascontiguousarray(p_match[kept], np.float32),
    )
    return dataclasses.replace(verdict, inlier_points=points)


def _essential_verdict(
    p_query: Points,
    p_match: Points,
    threshold: float,
    tested: int,
    params: VerificationParameters,
    intrinsics: Intrinsics,
) -> Verdict:
    """Robust essential-matrix fit, then the relative pose of the accepted pairs."""
    method = cv2.RANSAC if params.method == "ransac" else cv2.USAC_MAGSAC
    k = intrinsics.matrix()
    cv2.setRNGSeed(_FIT_SEED)
    try:
        essential, mask = cv2.findEssentialMat(
            p_query, p_match, k, method, params.confidence, threshold, params.max_iterations
        )
    except cv2.error:
        return Verdict(False, 0, tested, "E", "no model")
    if essential is None or mask is None or essential.shape[0] < 3:
        return Verdict(False, 0, tested, "E", "no model")
    verdict = _verdict(int(np.count_nonzero(mask)), tested, "E", params)
    if not verdict.accepted:
        return verdict
    posed = _with_pose(verdict, np.asarray(essential[:3], np.float64), p_query, p_match, k, mask)
    looked_again = verdict.inliers >= params.second_guess_factor * params.min_inliers
    if looked_again and turned_past(posed, params.max_rotation_deg):
        posed = _homography_rotation(posed, p_query, p_match, k, mask, threshold, params)
    elif not turned_past(posed, params.max_rotation_deg):
        posed = _planar_rotation(posed, p_query, p_match, k, mask, threshold, params)
    if turned_past(posed, params.max_rotation_deg):
        reason = turned_too_far(params.max_rotation_deg)
        return dataclasses.replace(posed, accepted=False, reason=reason)
    return _with_points(posed, p_query, p_match, mask)


def _homography_rotation(
    verdict: Verdict,
    p_query: Points,
    p_match: Points,
    k: npt.NDArray[np.float64],
    mask: npt.NDArray[Any],
    threshold: float,
    params: VerificationParameters,
) -> Verdict:
    """`verdict` with the rotation of a homography fitted to its essential fit's inliers,
    where that homography explains HOMOGRAPHY_SHARE of them (as ORB-SLAM's initialization
    picks H or F by which explains the matches): with the scene far for the baseline, the
    matches constrain the rotation and hardly the translation, and the rotation nearest
    K^-1 H K (its orthogonal polar factor) is that rotation; the translation's direction is
    then the one that best fits it (`_direction_given`). Unchanged otherwise."""
    fitted = _inlier_homography(p_query, p_match, mask, threshold, params, HOMOGRAPHY_SHARE)
    if fitted is None:
        return verdict
    homography, q_inliers, m_inliers = fitted
    u, _, vt = np.linalg.svd(np.linalg.inv(k) @ homography @ k)
    nearest = u @ vt
    if np.linalg.det(nearest) < 0:  # H is defined up to scale, its sign included
        nearest = -nearest
    return _posed_by(verdict, Rotation.from_matrix(nearest), q_inliers, m_inliers, k)


def _planar_rotation(
    verdict: Verdict,
    p_query: Points,
    p_match: Points,
    k: npt.NDArray[np.float64],
    mask: npt.NDArray[Any],
    threshold: float,
    params: VerificationParameters,
) -> Verdict:
    """`verdict` with the wider rotation of a plane's two readings, where a homography explains
    `params.planar_share` of the essential fit's inliers (0: off) and that reading turns past
    max_rotation_deg. Points on one plane (a facade filling the view) fit two poses equally,
    the plane's two decompositions (Faugeras and Lustman, 1988); the essential fit picks one or
    lands between them, and a sideways step is then read as a smaller turn: 6 degrees for a
    pair turned 21, whose plane reads 14 or 23. Under the limit only if both readings are."""
    if params.planar_share <= 0:
        return verdict
    fitted = _inlier_homography(p_query, p_match, mask, threshold, params, params.planar_share)
    if fitted is None:
        return verdict
    homography, q_inliers, m_inliers = fitted
    _, rotations, _, _ = cv2.decomposeHomographyMat(homography, k)
    # OpenCV's analytic decomposition gives NaN where two of H's singular values coincide.
    finite = [np.asarray(r, np.float64) for r in rotations if np.all(np.isfinite(r))]
    readings = [Rotation.from_matrix(r) for r in finite]
    if not readings:
        return verdict
    widest = max(readings, key=lambda r: float(np.linalg.norm(r.as_rotvec())))
    if math.degrees(float(np.linalg.norm(widest.as_rotvec()))) <= params.max_rotation_deg:
        return verdict
    return _posed_by(verdict, widest, q_inliers, m_inliers, k)


def _inlier_homography(
    p_query: Points,
    p_match: Points,
    mask: npt.NDArray[Any],
    threshold: float,
    params: VerificationParameters,
    share: float,
) -> tuple[npt.NDArray[np.float64], Points, Points] | None:
    """(H, the fit's inlier points of each frame) where a homography fitted to the essential
    fit's inliers explains `share` of them (at HOMOGRAPHY_THRESHOLD_FACTOR x its threshold);
    None otherwise."""
    inliers = mask.ravel().astype(bool)
    q_inliers, m_inliers = p_query[inliers], p_match[inliers]
    cv2.setRNGSeed(_FIT_SEED)
    try:
        homography, kept = cv2.findHomography(
            q_inliers,
            m_inliers,
            cv2.USAC_MAGSAC,
            HOMOGRAPHY_THRESHOLD_FACTOR * threshold,
            maxIters=params.max_iterations,
            confidence=params.confidence,
        )
    except cv2.error:
        return None
    if homography is None or kept is None or _count(kept) < share * _count(mask):
        return None
    return np.asarray(homography, np.float64), q_inliers, m_inliers


def _posed_by(
    verdict: Verdict,
    rotation: Rotation,
    q_inliers: Points,
    m_inliers: Points,
    k: npt.NDArray[np.float64],
) -> Verdict:
    """`verdict` with `rotation` (as the scalar-non-negative quaternion `_with_pose` gives)
    and the translation direction that best fits it (`_direction_given`)."""
    x, y, z, w = (float(v) for v in rotation.as_quat())
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    angle = math.degrees(float(np.linalg.norm(rotation.as_rotvec())))
    direction = _direction_given(rotation.as_matrix(), q_inliers, m_inliers, k)
    return dataclasses.replace(
        verdict,
        rotation_xyzw=(x, y, z, w),
        rotation_deg=angle,
        translation_direction=(float(direction[0]), float(direction[1]), float(direction[2])),
    )


def _direction_given(
    rotation: npt.NDArray[np.float64], p_query: Points, p_match: Points, k: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """The unit t that best fits the epipolar constraint m^T [t]x R q = 0 of the points with R
    given (q, m: their normalized rays): t is orthogonal to each R q x m, so it is the last
    right singular vector of those rows; of t and -t, the one that puts more points in front
    of both cameras (X_match = R X_query + t, as `Verdict`'s pose). The recorded pose stays
    one pose: the homography's rotation with the essential fit's direction would not be."""
    k_inv = np.linalg.inv(k)
    q = np.column_stack([p_query, np.ones(len(p_query))]) @ k_inv.T
    m = np.column_stack([p_match, np.ones(len(p_match))]) @ k_inv.T
    turned = q @ rotation.T
    normals = np.cross(turned, m)
    # Only V: the full U of n rows is n x n, most of the cost and never read.
    direction: npt.NDArray[np.float64] = np.linalg.svd(normals, full_matrices=False)[2][-1]
    # Depths along the rays: lambda_m m = lambda_q R q + t, crossed with m and with R q.
    squared = np.einsum("ij,ij->i", normals, normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        query_depth = np.einsum("ij,ij->i", np.cross(m, direction), normals) / squared
        match_depth = np.einsum("ij,ij->i", np.cross(turned, direction), normals) / squared
    ahead = int(np.count_nonzero((query_depth > 0) & (match_depth > 0)))
    behind = int(np.count_nonzero((query_depth < 0) & (match_depth < 0)))
    return direction if ahead >= behind else -direction


def _with_pose(
    verdict: Verdict,
    essential: npt.NDArray[np.float64],
    p_query: Points,
    p_match: Points,
    k: npt.NDArray[np.float64],
    mask: npt.NDArray[Any],
) -> Verdict:
    """Add R and the direction of t (chirality check over the RANSAC inliers)."""
    inliers = mask.ravel() != 0
    try:
        # Given the inliers alone: recoverPose counts the points in front of both cameras
        # among the masked ones only, so the pose is the same, and the outliers it would
        # triangulate for nothing are most of its cost.
        _, rotation, translation, _ = cv2.recoverPose(
            essential, p_query[inliers], p_match[inliers], k
        )
    except cv2.error:
        return verdict
    rvec, _ = cv2.Rodrigues(rotation)
    angle = float(np.linalg.norm(rvec))
    axis = rvec.ravel() / angle if angle > 0 else np.zeros(3)
    xyz = axis * math.sin(angle / 2)
    direction = translation.ravel() / max(float(np.linalg.norm(translation)), 1e-12)
    return Verdict(
        accepted=verdict.accepted,
        inliers=verdict.inliers,
        matches_tested=verdict.matches_tested,
        model="E",
        reason=verdict.reason,
        rotation_xyzw=(float(xyz[0]), float(xyz[1]), float(xyz[2]), math.cos(angle / 2)),
        rotation_deg=math.degrees(angle),
        translation_direction=(float(direction[0]), float(direction[1]), float(direction[2])),
    )


def _verdict(inliers: int, tested: int, model: Model, params: VerificationParameters) -> Verdict:
    if inliers == 0:
        return Verdict(False, 0, tested, model, "no model")
    accepted = inliers >= params.min_inliers
    return Verdict(accepted, inliers, tested, model, "accepted" if accepted else "too few inliers")
