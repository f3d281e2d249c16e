"""Geometric verification parameters: one frozen, validated, hashable object."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal, get_args

from ..detector.fingerprint import canonical_json, fingerprint
from ..detector.params import Parameters, reject_non_finite
from ..errors import ParameterError

VerificationDetector = Literal["sift", "orb", "akaze", "brisk"]
RobustMethod = Literal["ransac", "magsac"]

_CHOICES: dict[str, tuple[str, ...]] = {
    "feature_detector": get_args(VerificationDetector),
    "method": get_args(RobustMethod),
}

# Fewer than 8 correspondences always fit a fundamental matrix: such a count proves nothing.
MIN_ACCEPTABLE_INLIERS = 8


@dataclass(frozen=True)
class VerificationParameters:
    """How each loop-closure pair is checked geometrically.

    Defaults were chosen on the tuning sets (the RTAB-Map samples and our sample logs) by a
    sweep of these parameters, never on the held-out Lip6 Outdoor: ORB + MAGSAC was the
    fastest and, with min_inliers = 30, the only setting family that kept 0 false positives
    under every nearby change of max_features, ratio and threshold; refine_radius = 25 frames
    (25 s at 1 Hz) is where recall stops growing. Frames are shrunk to 320 px: on a 640x480
    log that costs a quarter of the features and pair checks, and the few frames that come out
    poor at 320 px (under `detail_below` features) get a second look at twice the side, so
    larger frames keep the pairs the shrinking would lose; smaller frames are enlarged to 320
    px (`segmentation.feature_image`). Determinism needs no seed: OpenCV's RANSAC and USAC
    seed their own generators (tested).

    `ransac_threshold_px` is in pixels of the feature image (the frame scaled so that its
    longer side is `image_max_side`); it is scaled to the original frame's pixels.
    """

    feature_detector: VerificationDetector = "orb"
    max_features: int = 1000  # strongest features kept per frame
    image_max_side: int = 320  # frames are shrunk (small ones enlarged) to this for features
    # A frame with fewer features than this at image_max_side is detected again at twice that
    # side (never past its own size): dim, plain frames are where verification fails at
    # 320 px, and a finer look finds what the shrinking lost. 0: never.
    detail_below: int = 150
    # ORB's FAST corner threshold (grey levels; OpenCV's default). Lower finds corners on plain
    # and dim surfaces too, from which ORB still keeps the strongest max_features, as ORB-SLAM
    # falls back to 7 where 20 finds none: 10 verifies more revisits on the tuning sets and the
    # generated matrix, for more CPU a frame pair (small frames fill their feature budget).
    fast_threshold: int = 20
    ratio: float = 0.8  # Lowe ratio test on the two nearest descriptors
    method: RobustMethod = "magsac"  # cv2.USAC_MAGSAC, or cv2.FM_RANSAC / cv2.RANSAC
    ransac_threshold_px: float = 1.0  # epipolar distance (feature-image px) of an inlier
    confidence: float = 0.999
    max_iterations: int = 2000
    min_inliers: int = 30  # accepted when the robust fit's inliers reach this
    # ... or this many when a frame of the pair was enlarged (under 160 px: `feature_image`):
    # a thumbnail has fewer features to agree on. Chosen on thumbnails of the tuning sets,
    # daylight and dark: the first false pair came at 10 inliers, and 20 keeps twice that margin.
    small_frame_min_inliers: int = 20
    # A pair found on a second guess (a next-best trajectory of the detector, or the previous
    # sequence's place continued) needs this many times the inliers of a first guess: each
    # further place tried for one query is one more chance to accept a look-alike. 1: the
    # same bar.
    second_guess_factor: float = 2.0
    refine_radius: int = 25  # frames: the match may move to the best frame within +-r
    # Above 1 / query_interval_s frames per second, one candidate in s = that many frames is
    # checked, windows are searched coarse to fine and accepted offsets tracked
    # (verification.stage); at 2 Hz or slower every candidate is (0: always).
    query_interval_s: float = 0.5
    # With intrinsics (essential matrix) only, both chosen on our sample logs (a pair seen from
    # the same place with another heading, or from a few metres off, is not a revisit): a pair
    # whose relative rotation exceeds
    # max_rotation_deg is rejected (180: no limit; a pair with a second guess's inliers that a
    # homography explains is measured by it, geometry.HOMOGRAPHY_SHARE: seen from nearly one
    # spot, the essential matrix's rotation is off), and with `bracket` a refined match is kept
    # only where the query's position lies between two verified frames of the match's
    # trajectory (geometry.bracketed_match); the refined match is then the nearer of those two.
    max_rotation_deg: float = 10.0
    # With planar_share > 0, a pair whose essential fit turns under the limit but whose
    # inliers a homography explains at that share is read as the wider of the plane's two
    # poses (geometry._planar_rotation): points on one plane fit two poses, and the fit may
    # read a turn past the limit as a sideways step and a small turn. It also rejects true
    # pairs whose other reading is wide (a match a metre off a plane): 0, off, by default.
    planar_share: float = 0.0
    bracket: bool = True
    # The motion rule (verification.motion): a pair is reported only if the camera left the
    # match's place and came back; else it is rejected "stationary". With a pose topic, left
    # means at least leave_distance_m from the match's position at some frame between; without
    # one, at least a third of leave_samples frames between them see neither end's place.
    motion_rule: bool = True
    leave_distance_m: float = 2.0
    leave_samples: int = 6
    # With a pose topic, the images' turn must agree with the odometry's (verification.motion):
    # a pair whose odometry turned more than the essential fit's rotation by over
    # heading_drift_deg + heading_drift_deg_per_m x the path between is rejected "odometry
    # disagrees" (a look-alike seen facing another way). 30 deg is VINS-Mono's bound on a
    # loop's yaw drift; 0.45 deg/m three times the odometry's yaw error per metre that the
    # metric stage assumes, so a long drive's drift is allowed for. 180: off.
    heading_drift_deg: float = 30.0
    heading_drift_deg_per_m: float = 0.45
    # With a pose topic, where the match's visit has frames over relocate_spacing_m apart (a
    # low frame rate), the query camera is placed on the visit's path by PnP with the
    # odometry's baseline (verification.position), and the loop moves to the visit's frame
    # nearest it when that frame is relocate_margin_m nearer than the bracketed one and passes
    # the check: between frames a metre apart the bracketing's sign is noisy.
    relocate_spacing_m: float = 0.5
    relocate_margin_m: float = 0.5
    # With a pose topic, a pair turned more than max_rotation_deg, up to
    # confirmed_rotation_deg, is accepted when that PnP places the query within
    # confirm_distance_m of the refined match, and rejected for its rotation as without a
    # pose topic otherwise: at larger turns a few more look-alikes metres along the route pass
    # the fit, and the odometry's metric baseline tells them apart. 15 deg keeps a margin under
    # the ground truth's 20 (the fit's rotation is off by degrees at 30-50 inliers).
    confirmed_rotation_deg: float = 15.0
    confirm_distance_m: float = 1.5
    # With a pose topic, a pair whose fit passed but that is not bracketed (every verified
    # frame on one side of the query: a revisit of the visit's first frames, a window or walk
    # that stops short of the place) is accepted at the visit's frame that PnP places the
    # query nearest, when within confirm_distance_m, not at an end of the frames searched
    # that the visit goes on past, its own check passes and PnP from it places the query
    # within confirm_distance_m too (`Verifier._placed_unbracketed`).
    place_unbracketed: bool = True
    # One feature extraction a frame: where the detector's segmentation is ORB on the same
    # feature image (`shares_features`: the verified defaults), it and the place index take
    # the features of these that ORB would keep for their budget (on each pyramid level the
    # strongest of its quota) instead of extracting their own: a frame's features are
    # extracted once, for the same false pairs and slightly more true ones. False: the
    # detector extracts its own.
    shared_features: bool = True

    def __post_init__(self) -> None:
        reject_non_finite(self)
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ParameterError(
                    f"{name} must be one of {', '.join(allowed)}, not {getattr(self, name)!r}"
                )
        for name in ("max_features", "image_max_side", "max_iterations"):
            if getattr(self, name) <= 0:
                raise ParameterError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 < self.ratio <= 1:
            raise ParameterError(f"ratio must be in (0, 1], got {self.ratio}")
        if not self.ransac_threshold_px > 0:
            raise ParameterError(
                f"ransac_threshold_px must be positive, got {self.ransac_threshold_px}"
            )
        if not 0 < self.confidence < 1:
            raise ParameterError(f"confidence must be in (0, 1), got {self.confidence}")
        for name in ("min_inliers", "small_frame_min_inliers"):
            if getattr(self, name) < MIN_ACCEPTABLE_INLIERS:
                raise ParameterError(
                    f"{name} must be >= {MIN_ACCEPTABLE_INLIERS}, got {getattr(self, name)}"
                )
        if not 0 <= self.planar_share <= 1:
            raise ParameterError(
                f"planar_share must be in [0, 1] (0: off), got {self.planar_share}"
            )
        if not self.second_guess_factor >= 1:
            raise ParameterError(
                f"second_guess_factor must be >= 1, got {self.second_guess_factor}"
            )
        if not 1 <= self.fast_threshold <= 254:
            raise ParameterError(f"fast_threshold must be in 1..254, got {self.fast_threshold}")
        if self.detail_below < 0:
            raise ParameterError(f"detail_below must be >= 0, got {self.detail_below}")
        if self.refine_radius < 0:
            raise ParameterError(f"refine_radius must be >= 0, got {self.refine_radius}")
        if not 0 < self.max_rotation_deg <= 180:
            raise ParameterError(
                f"max_rotation_deg must be in (0, 180], got {self.max_rotation_deg}"
            )
        if not self.leave_distance_m > 0:
            raise ParameterError(f"leave_distance_m must be positive, got {self.leave_distance_m}")
        if not 0 <= self.heading_drift_deg <= 180:
            raise ParameterError(
                f"heading_drift_deg must be in [0, 180], got {self.heading_drift_deg}"
            )
        if not self.heading_drift_deg_per_m >= 0:
            raise ParameterError(
                f"heading_drift_deg_per_m must be >= 0, got {self.heading_drift_deg_per_m}"
            )
        if not 0 < self.confirmed_rotation_deg <= 180:
            raise ParameterError(
                f"confirmed_rotation_deg must be in (0, 180], got {self.confirmed_rotation_deg}"
            )
        for name in ("relocate_spacing_m", "relocate_margin_m", "confirm_distance_m"):
            if not getattr(self, name) >= 0:
                raise ParameterError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.leave_samples < 1:
            raise ParameterError(f"leave_samples must be >= 1, got {self.leave_samples}")
        if not self.query_interval_s >= 0:
            raise ParameterError(f"query_interval_s must be >= 0, got {self.query_interval_s}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> VerificationParameters:
        """Build from plain values (ints are accepted for float fields).

        Raises:
            ParameterError: an unknown name, a value of the wrong type, or an invalid value.
        """
        known: dict[str, Any] = {f.name: f.default for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ParameterError(f"unknown verification parameter(s): {', '.join(unknown)}")
        converted: dict[str, Any] = {}
        for name, value in values.items():
            default = known[name]
            # bool is an int subclass: True must not pass for a count, nor 1 for a switch.
            if isinstance(default, bool):
                ok = isinstance(value, bool)
            else:
                ok = not isinstance(value, bool) and isinstance(value, _accepted_types(default))
            if not ok:
                raise ParameterError(
                    f"verification parameter {name} must be {type(default).__name__}, got {value!r}"
                )
            converted[name] = float(value) if isinstance(default, float) else value
        return cls(**converted)

    def replace(self, **changes: Any) -> VerificationParameters:
        """A copy with some values changed (validated like `from_dict`).

        Raises:
            ParameterError: as `from_dict`.
        """
        return self.from_dict({**self.to_dict(), **changes})

    def canonical_json(self) -> str:
        """Sorted keys, floats by their shortest repr: the same text on every machine."""
        return canonical_json(self.to_dict())

    @property
    def hash(self) -> str:
        """A stable 16-hex-digit fingerprint of every parameter."""
        return fingerprint(self.to_dict())


def _accepted_types(default: object) -> tuple[type, ...]:
    return (int, float) if isinstance(default, float) else (type(default),)


DEFAULT_VERIFICATION = VerificationParameters()

# The detector's th when verification is on (unless given): the check supplies the precision,
# so the detector only needs to propose; chosen on the tuning sets.
VERIFIED_THRESHOLD = 0.99
# The detector's alternatives when verification is on (unless given): a candidate whose match
# fails its check is tried again at the same query's match on the sequence's next-best
# trajectory starts, best first. 3 is where the tuning sets stop gaining true pairs.
VERIFIED_ALTERNATIVES = 3
# The segmentation when verification is on (unless feature_detector or feature_image_max_side
# is given): ORB on frames shrunk to 320 px. Verified, it finds the same loop closures as the
# paper-like SIFT at 240 px on the tuning sets for half the CPU; without the check SIFT is
# kept, as its raw decisions are better.
VERIFIED_SEGMENTATION: Mapping[str, Any] = {
    "feature_detector": "orb",
    "feature_image_max_side": 320,
}
# The place search when verification is on (unless given): the indexed one (detector/
# place_search.py). At 1-2 Hz it finds the same verified pairs as the full search; on a route
# driven lap after lap the full search rejects a revisit whose other visits score as well
# (gamma tends to 1), where the index scores each visit's window on its own and finds far
# more of them. Without verification the paper's full search stays.
VERIFIED_PLACE_SEARCH = "index"
# With the indexed search and verification on (unless given): at most one frame per this many
# seconds joins the place index (`Parameters.place_index_interval_s`). At 2 Hz or slower every
# frame still does; at 10 Hz one in three: neighbouring frames are near copies, so indexing
# one in three finds the places as well for a fraction of the index's CPU and postings. Not
# swept.
VERIFIED_INDEX_INTERVAL_S = 0.25


# With verification on (unless given): the segmentation's ORB sees a frame smaller than its
# working size enlarged to it, as verification does: on a small frame ORB finds too few
# features to segment by.
VERIFIED_ENLARGE = True


def shares_features(detector: Parameters, verification: VerificationParameters) -> bool:
    """Whether the detector takes the verification's features (`shared_features`): both ORB,
    detected on the same image (the frame shrunk or enlarged to one side), with at least the
    detector's budget."""
    return (
        verification.shared_features
        and verification.feature_detector == "orb"
        and detector.feature_detector == "orb"
        and detector.feature_image_max_side == verification.image_max_side
        and detector.feature_image_enlarge
        and verification.max_features >= detector.max_features
    )


def verified_defaults(given: Callable[[str], bool]) -> dict[str, Any]:
    """The detector parameters that verification changes, as changes for Parameters.replace:
    th = VERIFIED_THRESHOLD, alternatives = VERIFIED_ALTERNATIVES, VERIFIED_SEGMENTATION,
    place_search = VERIFIED_PLACE_SEARCH and place_index_interval_s =
    VERIFIED_INDEX_INTERVAL_S,
    each left out where `given(name)` says the user set it (the segmentation as a whole, when
    either of its parameters is given)."""
    defaults: dict[str, Any] = {}
    if not given("threshold"):
        defaults["threshold"] = VERIFIED_THRESHOLD
    if not given("alternatives"):
        defaults["alternatives"] = VERIFIED_ALTERNATIVES
    if not any(given(name) for name in VERIFIED_SEGMENTATION):
        defaults.update(VERIFIED_SEGMENTATION)
    if not given("place_search"):
        defaults["place_search"] = VERIFIED_PLACE_SEARCH
    if not given("place_index_interval_s"):
        defaults["place_index_interval_s"] = VERIFIED_INDEX_INTERVAL_S
    if not given("feature_image_enlarge"):
        defaults["feature_image_enlarge"] = VERIFIED_ENLARGE
    return defaults


def verified_detector_parameters(**changes: Any) -> Parameters:
    """The detector's defaults as `annotate` and `evaluate` run them with verification on
    (`verified_defaults`), with `changes` applied.

    Raises:
        ParameterError: for an unknown or invalid parameter.
    """
    return Parameters().replace(**verified_defaults(changes.__contains__), **changes)


def command_detector_parameters(verification: VerificationParameters | None) -> Parameters:
    """The detector parameters the commands run when none are given: the verified defaults with
    verification on, the paper's (`Parameters()`) with it off (`--no-verify`)."""
    return verified_detector_parameters() if verification is not None else Parameters()
