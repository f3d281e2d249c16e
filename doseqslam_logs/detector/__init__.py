"""The detector core: pure computation over frames (no file I/O), with an online `push` API."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from ..lazy import lazy_names
from .events import Alternative, Candidate, SequenceDecision
from .params import Parameters

if TYPE_CHECKING:
    from .difference import FrameStore
    from .doseqslam import DOSeqSLAM, PreparedFrame
    from .segmentation import OrbFeatures
    from .seqslam import SeqSLAM

__all__ = [
    "Alternative",
    "Candidate",
    "DOSeqSLAM",
    "Detector",
    "Parameters",
    "PreparedFrame",
    "SeqSLAM",
    "SequenceDecision",
    "make_detector",
]

# The detectors import OpenCV: only when used, so that `detector.params` alone stays light.
__getattr__ = lazy_names(
    __name__, {"doseqslam": ["DOSeqSLAM", "PreparedFrame"], "seqslam": ["SeqSLAM"]}
)


class Detector(Protocol):
    """What the replay pipeline drives: frames in, decisions out."""

    method: str
    params: Parameters

    @property
    def feature_detector(self) -> str: ...

    @property
    def frame_count(self) -> int: ...

    @property
    def memory_bytes(self) -> int: ...

    def prepare(
        self, gray: npt.NDArray[np.uint8], supplied: OrbFeatures | None = None
    ) -> PreparedFrame: ...

    def push(self, timestamp_ns: int, gray: npt.NDArray[np.uint8]) -> list[SequenceDecision]: ...

    def push_prepared(self, timestamp_ns: int, frame: PreparedFrame) -> list[SequenceDecision]: ...

    def finish(self) -> list[SequenceDecision]: ...


def make_detector(params: Parameters, store: FrameStore | None = None) -> Detector:
    """The detector `params.method` names; `store`: where it keeps its frame vectors (empty;
    None: in memory)."""
    from .doseqslam import DOSeqSLAM
    from .seqslam import SeqSLAM

    if params.method == "seqslam":
        return SeqSLAM(params, store)
    return DOSeqSLAM(params, store=store)
