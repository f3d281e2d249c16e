"""Dynamic sequence segmentation (paper III-B, eq. 5) by a running common set of local features.

A sequence starts with its first frame's features as the common set C. Each next frame is
matched against C, and C keeps only the features that found a match, with their own
descriptors: C is the intersection of the sequence's frames with its first frame. When at most
one feature survives, the sequence ends and the frame starts a new one. The KLT variant (the
authors' later code) tracks points instead and ends a sequence when none survives.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from .params import Parameters

GrayImage = npt.NDArray[np.uint8]

# The order in which "auto" tries detectors: SURF when the installed OpenCV has the non-free
# module (the paper's choice), else the free detector chosen on the tuning sets.
AUTO_ORDER = ("surf", "sift", "orb")
# Frames whose longer side is under this are enlarged for feature detection (`feature_image`):
# ORB keeps a 31-pixel border and describes 31-pixel patches, so it finds almost nothing on a
# thumbnail. Frames this size or larger are only shrunk.
SMALL_FRAME_SIDE = 160
# ORB's FAST test needs a grey-level step of 20 whatever the frame's contrast, so a dark or hazy
# frame (a night drive) gives it nearly nothing. A feature image whose grey levels between the
# 1st and 99th percentile span less than this, and every enlarged small frame (whose contrast
# interpolation flattens), is stretched to 0-255 first (`feature_image`). Frames with the
# contrast of a daylight drive span more, so they are left as they are.
LOW_CONTRAST_SPAN = 64
# ... but a span under this is left alone: a frame of a few grey levels (a lens cap, a black
# night) holds little picture, and a gain over 16 would mostly turn its sensor noise and JPEG
# blocks into corners.
MIN_STRETCH_SPAN = 16
# The percentiles that span is measured between: a few saturated or black pixels (a lamp, a
# shadow) must not decide it.
SPAN_PERCENTILES = (0.01, 0.99)
# The segmentation detectors that see enlarged small frames: ORB, the segmentation verification
# runs (VERIFIED_SEGMENTATION), and the one ORB whatever the mode (its border is the reason).
# The paper's SIFT / SURF (`--no-verify`) keep `shrink`, bit for bit.
ENLARGED_DETECTORS = ("orb",)


class Segmenter(Protocol):
    """Decides, frame by frame, where sequences start.

    `prepare` is the per-frame work that needs no other frame (feature extraction); it is
    thread-safe, so a pool can run it ahead of the sequential `update`.
    """

    name: str

    def prepare(self, gray: GrayImage) -> Any:
        """Per-frame work that depends on this frame only."""
        ...

    def update(self, prepared: Any) -> bool:
        """Feed the next prepared frame; True when it starts a new sequence (the first does)."""
        ...

    def restart(self, prepared: Any) -> None:
        """Start a new sequence at this frame regardless of its features (the length cap)."""
        ...

    def starts_sequence(self, gray: GrayImage) -> bool:
        """`update(prepare(gray))`."""
        ...


def shrink(gray: GrayImage, max_side: int) -> GrayImage:
    """Shrink so the longer side is at most max_side: features cost time in pixels."""
    scale = max_side / max(gray.shape)
    if scale >= 1.0:
        return gray
    size = (max(1, round(gray.shape[1] * scale)), max(1, round(gray.shape[0] * scale)))
    return np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_AREA), dtype=np.uint8)


def feature_image(
    gray: GrayImage, max_side: int, enlarge_below: int = SMALL_FRAME_SIDE
) -> GrayImage:
    """The frame features are detected on: `shrink` to max_side, except that a frame whose
    longer side is under `enlarge_below` (SMALL_FRAME_SIDE unless given) is enlarged
    (bicubic) to max_side, so that ORB's border and patches leave it room; an enlarged frame,
    or one whose grey levels span less than LOW_CONTRAST_SPAN (but at least MIN_STRETCH_SPAN),
    then has that span stretched to 0-255 (`stretch_contrast`), so that FAST's fixed threshold
    finds its corners. Other frames come out as `shrink` gives them, bit for bit."""
    longest = max(gray.shape)
    small = 0 < longest < min(max(enlarge_below, SMALL_FRAME_SIDE), max_side)
    if not small:
        image = shrink(gray, max_side)
    else:
        scale = max_side / longest
        size = (max(1, round(gray.shape[1] * scale)), max(1, round(gray.shape[0] * scale)))
        image = np.asarray(cv2.resize(gray, size, interpolation=cv2.INTER_CUBIC), np.uint8)
    low, high = grey_span(image)
    if high - low >= MIN_STRETCH_SPAN and (small or high - low < LOW_CONTRAST_SPAN):
        return stretch_contrast(image, low, high)
    return image


def grey_span(image: GrayImage) -> tuple[int, int]:
    """The grey levels at SPAN_PERCENTILES of the image (from the histogram of every other
    pixel of every other row: integers, and cheap enough for every feature image)."""
    sample = image[::2, ::2]
    if sample.size == 0:
        return 0, 0
    cumulative = np.cumsum(np.bincount(sample.ravel(), minlength=256))
    low, high = (int(np.searchsorted(cumulative, p * sample.size)) for p in SPAN_PERCENTILES)
    return low, high


def stretch_contrast(image: GrayImage, low: int, high: int) -> GrayImage:
    """`low`..`high` mapped linearly onto 0..255 (clipped outside), through a lookup table of
    256 exactly rounded values, so the result is the same on every machine."""
    levels = np.arange(256, dtype=np.float64)
    table = np.clip(np.rint((levels - low) * (255.0 / (high - low))), 0, 255).astype(np.uint8)
    return np.asarray(table[image], dtype=np.uint8)


def create_detector(name: str, max_features: int) -> tuple[Any, int]:
    """An OpenCV feature object and the norm its descriptors are compared with.

    Raises ValueError when the installed OpenCV lacks it (SURF is absent from PyPI builds).
    """
    xf = getattr(cv2, "xfeatures2d", None)

    def find(attr: str) -> Any:
        factory = getattr(cv2, attr, None) or getattr(xf, attr, None)
        if factory is None:
            raise ValueError(f"this OpenCV build has no {attr}")
        return factory

    try:
        if name == "orb":
            return find("ORB_create")(nfeatures=max_features), cv2.NORM_HAMMING
        if name == "sift":
            return find("SIFT_create")(nfeatures=max_features), cv2.NORM_L2
        if name == "surf":
            return find("SURF_create")(hessianThreshold=400), cv2.NORM_L2
        if name == "akaze":
            return find("AKAZE_create")(), cv2.NORM_HAMMING
        if name == "brisk":
            return find("BRISK_create")(), cv2.NORM_HAMMING
    except cv2.error as exc:  # non-free algorithm disabled in this build
        raise ValueError(f"{name} is not available in this OpenCV build: {exc.err}") from None
    raise ValueError(f"unknown feature detector {name!r}")


def resolve_detector_name(requested: str) -> str:
    """The detector "auto" stands for on this installation; other names are returned as is."""
    if requested != "auto":
        return requested
    for name in AUTO_ORDER:
        try:
            create_detector(name, 10)
        except ValueError:
            continue
        return name
    raise ValueError("no feature detector available")  # pragma: no cover - ORB is always there


# ORB's defaults (cv2.ORB_create): its pyramid, over which a budget of n features is spread.
ORB_SCALE_FACTOR = 1.2
ORB_LEVELS = 8


@functools.lru_cache(maxsize=16)
def orb_level_quota(
    n: int, scale_factor: float = ORB_SCALE_FACTOR, levels: int = ORB_LEVELS
) -> tuple[int, ...]:
    """The features ORB asked for n keeps on each pyramid level, as OpenCV's ORB computes them
    (a geometric share per level, the rest on the last one; float32 as in its source). Cached:
    every shared frame asks for the same budget."""
    factor = np.float32(1.0 / scale_factor)
    per_level = np.float32(n * (1 - factor) / (1 - float(factor) ** levels))
    quota = []
    for _ in range(levels - 1):
        quota.append(int(np.rint(per_level)))
        per_level = np.float32(per_level * factor)
    quota.append(max(n - sum(quota), 0))
    return tuple(quota)


@dataclass(frozen=True)
class OrbFeatures:
    """ORB features of a frame that a caller already extracted on the image the segmentation
    would see: descriptors strongest first, and each one's pyramid level (KeyPoint.octave)."""

    descriptors: npt.NDArray[np.uint8]
    levels: npt.NDArray[np.uint8]

    def as_if_asked_for(self, n: int) -> npt.NDArray[np.uint8]:
        """The descriptors ORB asked for n features would have kept: on each pyramid level the
        strongest of its quota (`orb_level_quota`), in the original order. ORB ranks a level's
        corners by response and keeps the level's quota, so a smaller budget keeps a prefix of
        each level (up to FAST's pre-selection of twice the quota)."""
        keep = np.zeros(len(self.levels), bool)
        for level, quota in enumerate(orb_level_quota(n)):
            on_level = np.flatnonzero(self.levels == level)
            keep[on_level[:quota]] = True
        return self.descriptors[keep]


@dataclass
class _Features:
    descriptors: npt.NDArray[Any] | None

    @property
    def count(self) -> int:
        return 0 if self.descriptors is None else len(self.descriptors)


def feature_count(prepared: Any) -> int:
    """The descriptors a `DescriptorSegmenter.prepare` found; -1 for anything else (KLT's
    prepared frame is an image: its corners are found only when it seeds)."""
    return prepared.count if isinstance(prepared, _Features) else -1


class DescriptorSegmenter:
    """Running common set of descriptors, matched with a ratio test (paper eq. 5)."""

    def __init__(self, params: Parameters, name: str) -> None:
        self.name = name
        _, norm = create_detector(name, params.max_features)  # fails early if the build lacks it
        self._local = threading.local()  # OpenCV feature objects are not shared across threads
        self._matcher = cv2.BFMatcher(norm)
        self._max_features = params.max_features
        self._max_side = params.feature_image_max_side
        enlarge_below = self._max_side if params.feature_image_enlarge else SMALL_FRAME_SIDE
        enlarged = functools.partial(feature_image, enlarge_below=enlarge_below)
        self._image = enlarged if name in ENLARGED_DETECTORS else shrink
        self._ratio = params.match_ratio
        self._min_features = params.min_features
        self._common: _Features | None = None
        self._seeded = False

    def prepare(self, gray: GrayImage) -> _Features:
        """This frame's descriptors (strongest `max_features`), on the shrunk frame (ORB: on
        `feature_image`, which also enlarges small frames)."""
        detector = getattr(self._local, "detector", None)
        if detector is None:
            detector = self._local.detector = create_detector(self.name, self._max_features)[0]
        keypoints, descriptors = detector.detectAndCompute(self._image(gray, self._max_side), None)
        if descriptors is None or len(keypoints) == 0:
            return _Features(None)
        if len(keypoints) > self._max_features:  # AKAZE/BRISK have no feature budget
            order = np.argsort([-k.response for k in keypoints], kind="stable")
            descriptors = descriptors[order[: self._max_features]]
        return _Features(descriptors)

    def supplied(self, features: OrbFeatures) -> _Features:
        """`prepare`'s result from ORB features the caller extracted: those ORB asked for
        max_features would have kept (`OrbFeatures.as_if_asked_for`)."""
        descriptors = features.as_if_asked_for(self._max_features)
        return _Features(descriptors if len(descriptors) else None)

    def _surviving(self, current: _Features) -> _Features:
        """The common features that found a match in `current` (their own descriptors, so C is
        the intersection with the sequence's first frame and cannot drift along the route)."""
        assert self._common is not None and self._common.descriptors is not None
        assert current.descriptors is not None
        if len(current.descriptors) < 2:
            return _Features(None)
        pairs = self._matcher.knnMatch(self._common.descriptors, current.descriptors, k=2)
        kept: dict[int, int] = {}  # train index -> common index: one match per new feature
        for pair in pairs:
            if len(pair) == 2 and pair[0].distance < self._ratio * pair[1].distance:
                kept.setdefault(pair[0].trainIdx, pair[0].queryIdx)
        rows = sorted(kept.values())
        return _Features(self._common.descriptors[rows] if rows else None)

    def starts_sequence(self, gray: GrayImage) -> bool:
        return self.update(self.prepare(gray))

    def update(self, current: _Features) -> bool:
        if self._common is None:
            self._start(current)
            return True
        if current.count < self._min_features:
            return False  # dark or blurred frame: joins the current sequence
        if not self._seeded:
            self._start(current)  # the sequence began on featureless frames: seed it now
            return False
        surviving = self._surviving(current)
        if surviving.count <= 1:
            self._start(current)
            return True
        self._common = surviving
        return False

    def restart(self, prepared: _Features) -> None:
        self._start(prepared)

    def _start(self, features: _Features) -> None:
        self._common = features
        # Only a frame with enough features can seed the common set; until one comes, the
        # sequence cannot end (a dark stretch stays one sequence with its neighbours).
        self._seeded = features.count >= self._min_features


class KltSegmenter:
    """Points tracked with pyramidal Lucas-Kanade (forward-backward checked); a sequence ends
    when no point survives (the authors' Tracking-DOSeqSLAM)."""

    name = "klt"
    FB_MAX_ERROR = 1.0  # pixels: forward-backward disagreement beyond this drops a point

    def __init__(self, params: Parameters) -> None:
        self._max_features = params.max_features
        self._max_side = params.feature_image_max_side
        self._min_features = params.min_features
        self._previous: GrayImage | None = None
        self._points: npt.NDArray[np.float32] | None = None
        self._seeded = False

    def _seed(self, small: GrayImage) -> None:
        corners = cv2.goodFeaturesToTrack(small, self._max_features, 0.01, 7)
        self._points = None if corners is None else corners.astype(np.float32)
        self._previous = small
        self._seeded = self._points is not None and len(self._points) >= self._min_features

    def _track(self, small: GrayImage) -> npt.NDArray[np.float32] | None:
        assert self._previous is not None and self._points is not None
        points = self._points
        # nextPts is only an initial guess when OPTFLOW_USE_INITIAL_FLOW is set; it is not here.
        forward, st1, _ = cv2.calcOpticalFlowPyrLK(
            self._previous, small, points, points.copy(), winSize=(21, 21), maxLevel=3
        )
        forward = np.asarray(forward, dtype=np.float32)
        backward, st2, _ = cv2.calcOpticalFlowPyrLK(
            small, self._previous, forward, forward.copy(), winSize=(21, 21), maxLevel=3
        )
        error = np.linalg.norm((np.asarray(backward) - points).reshape(-1, 2), axis=1)
        good = (np.asarray(st1).ravel() == 1) & (np.asarray(st2).ravel() == 1)
        good &= error < self.FB_MAX_ERROR
        return forward[good] if good.any() else None

    def prepare(self, gray: GrayImage) -> GrayImage:
        return shrink(gray, self._max_side)

    def starts_sequence(self, gray: GrayImage) -> bool:
        return self.update(self.prepare(gray))

    def update(self, small: GrayImage) -> bool:
        if self._previous is None or self._previous.shape != small.shape:
            self._seed(small)  # first frame, or the resolution changed: nothing to track
            return True
        if not self._seeded:
            self._seed(small)  # the sequence began on featureless frames: seed it now
            return False
        tracked = self._track(small)
        if tracked is None:
            self._seed(small)
            return True
        self._points, self._previous = tracked, small
        return False

    def restart(self, small: GrayImage) -> None:
        self._seed(small)


def make_segmenter(params: Parameters) -> Segmenter:
    """The segmenter the parameters ask for ("auto" resolves as `resolve_detector_name`)."""
    name = resolve_detector_name(params.feature_detector)
    if name == "klt":
        return KltSegmenter(params)
    return DescriptorSegmenter(params, name)
