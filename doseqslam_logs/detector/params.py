"""Every detector parameter in one frozen object that loads from and dumps to TOML."""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal, get_args

import tomli_w

from ..errors import ParameterError
from .fingerprint import canonical_json, fingerprint

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

Method = Literal["doseqslam", "seqslam"]
Association = Literal["greedy", "trajectory"]
FeatureDetector = Literal["auto", "surf", "orb", "sift", "akaze", "brisk", "klt"]
Precision = Literal["uint8", "float32"]
PlaceSearch = Literal["full", "index"]

_CHOICES: dict[str, tuple[str, ...]] = {
    "method": get_args(Method),
    "association": get_args(Association),
    "feature_detector": get_args(FeatureDetector),
    "difference_precision": get_args(Precision),
    "place_search": get_args(PlaceSearch),
}

# Fields added after outputs recorded parameter hashes: `to_dict` leaves each out while it holds
# its default, so every earlier parameter set keeps its dict, TOML, canonical JSON and hash
# byte for byte (they are written into output files), and `from_dict` accepts them either way.
# A field added from now on belongs here with its default.
LATER_FIELDS = (
    "place_search",
    "place_count",
    "place_queries",
    "place_margin",
    "place_index_interval_s",
    "feature_image_enlarge",
)


def reject_non_finite(params: Any) -> None:
    """ParameterError for a NaN or infinite float field of a parameters dataclass: no
    comparison the checks make is meaningful for them (NaN passes every `<`)."""
    for field in fields(params):
        value = getattr(params, field.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ParameterError(f"{field.name} must be a finite number, got {value}")


@dataclass(frozen=True)
class Parameters:
    """Detector parameters; defaults are the paper's Table II where it has one.

    Names follow the paper: `kappa_s` is its time constant kappa (seconds of timestamp),
    `enhancement_window` its epsilon, `threshold` its th (theta for SeqSLAM).
    """

    method: Method = "doseqslam"
    # Preprocessing (paper Table II: 64 x 32 pixels, chi = 2048, N = 8).
    image_width: int = 64
    image_height: int = 32
    patch_size: int = 8
    # Frame vectors for the SAD rows: uint8-quantized (fast, 4x smaller) or float32.
    difference_precision: Precision = "uint8"
    # Contrast enhancement window epsilon (samples j-5 .. j+5).
    enhancement_window: int = 10
    # Time constant kappa: database frames are at least this many seconds older than the query.
    kappa_s: float = 40.0
    # Trajectory velocities 0.7 .. 1.3 in steps of 0.1 (the paper's "step 1" read as 0.1).
    velocity_min: float = 0.7
    velocity_max: float = 1.3
    velocity_step: float = 0.1
    # Decision: loop closure when f < threshold.
    threshold: float = 0.75
    # Image-to-image association inside an accepted sequence.
    association: Association = "trajectory"
    # Segmentation (paper III-B): a sequence ends when at most one common feature survives.
    feature_detector: FeatureDetector = "auto"
    max_features: int = 500
    feature_image_max_side: int = 240  # frames are shrunk to this before feature detection
    match_ratio: float = 0.8  # Lowe ratio test for descriptor matching
    min_features: int = 10  # a frame with fewer features joins the current sequence
    max_sequence_length: int = 300  # frames; 0 turns the cap off
    # Next-best trajectory starts recorded per sequence (each at least alternative_separation
    # frames from the ones before), for the verification stage to try when the detector's own
    # match fails its check. 0 is the paper; with verification on, the CLI raises it to
    # VERIFIED_ALTERNATIVES (verification.params). DOSeqSLAM only.
    alternatives: int = 0
    alternative_separation: int = 10
    # SeqSLAM baseline: fixed sequence length ds.
    seqslam_length: int = 10
    # Where a sequence is searched: "full" is the paper (every older frame, gamma = best /
    # second best); "index" asks a bag-of-words place index (detector/place_search.py) for
    # `place_count` places, voted by `place_queries` frames of the sequence, and scores
    # trajectories only in windows of +-`place_margin` frames around them, with gamma = best /
    # median of the windows' non-matching scores (repeated visits do not count against it).
    # DOSeqSLAM only. Left out of `to_dict` at their defaults (LATER_FIELDS).
    place_search: PlaceSearch = "full"
    place_count: int = 4
    place_queries: int = 5
    place_margin: int = 10
    # Frames join the place index at most one per this many seconds of timestamp (keyframes;
    # 0: every frame). At 10 Hz, neighbouring frames are near copies: indexing each costs the
    # nearest-word search of its descriptors and postings that grow with the log, and adds no
    # place the sequence's windows (+-place_margin) would not find. With verification on, the
    # CLI raises it to VERIFIED_INDEX_INTERVAL_S (verification.params).
    place_index_interval_s: float = 0.0
    # ORB features of a frame smaller than feature_image_max_side are detected on it enlarged
    # to that side (False: only frames under segmentation.SMALL_FRAME_SIDE are, the paper
    # mode's). With verification on the CLI turns it on (verification.params).
    feature_image_enlarge: bool = False

    def __post_init__(self) -> None:
        reject_non_finite(self)
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ParameterError(
                    f"{name} must be one of {', '.join(allowed)}, not {getattr(self, name)!r}"
                )
        positive = (
            "image_width",
            "image_height",
            "patch_size",
            "max_features",
            "feature_image_max_side",
            "seqslam_length",
            "place_count",
            "place_queries",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise ParameterError(f"{name} must be positive, got {getattr(self, name)}")
        if self.image_width % self.patch_size or self.image_height % self.patch_size:
            raise ParameterError("image_width and image_height must be multiples of patch_size")
        if self.enhancement_window < 2 or self.enhancement_window % 2:
            raise ParameterError("enhancement_window must be an even number >= 2")
        if self.kappa_s < 0:
            raise ParameterError("kappa_s must be >= 0")
        if not 0 < self.velocity_min <= 1.0 <= self.velocity_max or self.velocity_step <= 0:
            raise ParameterError("velocities need 0 < velocity_min <= 1 <= velocity_max, step > 0")
        if not 0 < self.match_ratio <= 1:
            raise ParameterError("match_ratio must be in (0, 1]")
        if self.min_features < 0 or self.max_sequence_length < 0:
            raise ParameterError("min_features and max_sequence_length must be >= 0")
        if self.alternatives < 0 or self.alternative_separation < 1:
            raise ParameterError("alternatives must be >= 0 and alternative_separation >= 1")
        if self.place_margin < 0:
            raise ParameterError("place_margin must be >= 0")
        if self.place_index_interval_s < 0:
            raise ParameterError("place_index_interval_s must be >= 0")

    @property
    def velocities(self) -> tuple[float, ...]:
        """The velocity grid, always including 1.0, rounded to clean decimals."""
        count = round((self.velocity_max - self.velocity_min) / self.velocity_step) + 1
        grid = {round(self.velocity_min + i * self.velocity_step, 6) for i in range(count)}
        grid.add(1.0)
        return tuple(sorted(v for v in grid if v <= self.velocity_max + 1e-9))

    def to_dict(self) -> dict[str, Any]:
        """Every field, except the LATER_FIELDS that hold their default (the hash rule)."""
        values = dataclasses.asdict(self)
        defaults = {f.name: f.default for f in fields(self)}
        for name in LATER_FIELDS:
            if values[name] == defaults[name]:
                del values[name]
        return values

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Parameters:
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ParameterError(f"unknown parameter(s): {', '.join(unknown)}")
        converted: dict[str, Any] = {}
        for name, value in values.items():
            default = known[name].default
            if isinstance(default, bool) or isinstance(value, bool):
                ok = isinstance(value, type(default))
            elif isinstance(default, float):
                ok = isinstance(value, (int, float))
                value = float(value) if ok else value
            else:
                ok = isinstance(value, type(default))
            if not ok:
                raise ParameterError(
                    f"parameter {name} must be {type(default).__name__}, got {value!r}"
                )
            converted[name] = value
        return cls(**converted)

    def replace(self, **changes: Any) -> Parameters:
        return self.from_dict({**self.to_dict(), **changes})

    def to_toml(self) -> str:
        return tomli_w.dumps(self.to_dict())

    @classmethod
    def from_toml(cls, text: str) -> Parameters:
        try:
            values = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ParameterError(f"invalid TOML: {exc}") from None
        return cls.from_dict(values)

    @classmethod
    def load(cls, path: str | Path) -> Parameters:
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as exc:
            raise ParameterError(f"{path}: cannot read parameters: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise ParameterError(
                f"{path}: not a parameters file: not UTF-8 text (byte {exc.start}: "
                f"{exc.object[exc.start : exc.start + 1]!r}); expected TOML"
            ) from None
        try:
            return cls.from_toml(text)
        except ParameterError as exc:
            raise ParameterError(f"{path}: {exc}") from None

    def canonical_json(self) -> str:
        """Sorted keys, floats by their shortest repr: the same text on every machine."""
        return canonical_json(self.to_dict())

    @property
    def hash(self) -> str:
        """A stable 16-hex-digit fingerprint of every parameter."""
        return fingerprint(self.to_dict())


DEFAULT_PARAMETERS = Parameters()
