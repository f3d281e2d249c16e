"""Geometric verification of loop-closure pairs: pure computation, no file I/O.

After the detector, each (query, match) pair is checked with local features, a ratio test and
a robust fundamental-matrix fit (essential matrix and relative pose when intrinsics are known;
then also a rotation limit and bracketing of the refined match: `bracketed_match`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..lazy import lazy_names
from .params import (
    DEFAULT_VERIFICATION,
    VERIFIED_ALTERNATIVES,
    VERIFIED_SEGMENTATION,
    VERIFIED_THRESHOLD,
    VerificationParameters,
    command_detector_parameters,
    verified_defaults,
    verified_detector_parameters,
)

if TYPE_CHECKING:
    from .geometry import (
        NOT_BRACKETED,
        FrameFeatures,
        InlierPoints,
        Intrinsics,
        Verdict,
        best_verdict,
        bracketed_match,
        extract_features,
        match_camera_direction,
        refine_match,
        verify_pair,
    )
    from .stage import PairCheck, VerificationStats, VerifiedDecision, Verifier

__all__ = [
    "DEFAULT_VERIFICATION",
    "NOT_BRACKETED",
    "VERIFIED_ALTERNATIVES",
    "VERIFIED_SEGMENTATION",
    "VERIFIED_THRESHOLD",
    "FrameFeatures",
    "InlierPoints",
    "Intrinsics",
    "PairCheck",
    "Verdict",
    "VerificationParameters",
    "VerificationStats",
    "VerifiedDecision",
    "Verifier",
    "best_verdict",
    "bracketed_match",
    "command_detector_parameters",
    "extract_features",
    "match_camera_direction",
    "refine_match",
    "verified_defaults",
    "verified_detector_parameters",
    "verify_pair",
]

# The pair checks import OpenCV and SciPy: only when used, so that `verification.params`
# (the command line's defaults) stays light.
__getattr__ = lazy_names(
    __name__,
    {
        "geometry": [
            "NOT_BRACKETED",
            "FrameFeatures",
            "InlierPoints",
            "Intrinsics",
            "Verdict",
            "best_verdict",
            "bracketed_match",
            "extract_features",
            "match_camera_direction",
            "refine_match",
            "verify_pair",
        ],
        "stage": ["PairCheck", "VerificationStats", "VerifiedDecision", "Verifier"],
    },
)
