"""The detector on an image folder against a ground-truth matrix (`evaluate --images`).

The folder, a Source stamped at a fixed rate, goes through annotate's own run (replay, then
the candidate pairs verified geometrically unless verification is None); this module scores
the raw and the verified decisions at the run's th.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .. import __version__
from ..detector import Parameters
from ..detector.events import SequenceDecision
from ..errors import GroundTruthError
from ..pipeline.annotate import AnnotateOptions, Decided, OpenLog, decide_log
from ..pipeline.feature_health import ADVICE, FeatureHealth
from ..pipeline.replay import ReplayResult
from ..sources.image_folder import ImageFolderSource, folder_time_ns
from ..sources.image_header import DEFAULT_MAX_PIXELS
from ..verification import (
    DEFAULT_VERIFICATION,
    Intrinsics,
    VerificationParameters,
    VerificationStats,
    command_detector_parameters,
)
from ..verification.summary import verification_summary
from .groundtruth import GroundTruth, load_ground_truth
from .metrics import Evaluation, evaluate, format_report, format_side_by_side
from .verified import verified_decisions

# Threads that prepare the frames and verify the candidates; results do not depend on it.
VERIFY_THREADS = 2


@dataclass(frozen=True)
class FolderVerification:
    """What the verification stage decided over the folder's run, and what it cost."""

    params: VerificationParameters
    intrinsics: Intrinsics | None
    decisions: list[SequenceDecision]  # reduced to their accepted pairs (verified_decisions)
    stats: VerificationStats  # seconds summed over the threads
    wall_s: float  # of the whole stage

    def describe(self) -> str:
        """The report's account: hash, pairs verified and accepted, and the cost."""
        pose = (
            "essential matrix, intrinsics from --intrinsics"
            if self.intrinsics
            else "fundamental matrix, no intrinsics"
        )
        counts = verification_summary(self.stats, self.wall_s, pose, "images")
        verified = f"{self.stats.candidates} candidate pairs verified"
        return f"verification {self.params.hash}: {verified}, {counts}"

    def to_json_dict(self) -> dict[str, Any]:
        k, stats = self.intrinsics, self.stats
        return {
            "verification": "on",
            "verification_hash": self.params.hash,
            "verification_parameters": self.params.to_dict(),
            "intrinsics": None if k is None else [k.fx, k.fy, k.cx, k.cy],
            "verification_cost": {
                "candidate_pairs": stats.candidates,
                "accepted_pairs": stats.accepted,
                "accepted_on_alternatives": stats.from_alternatives,
                "frame_pairs_checked": stats.pairs,
                "ms_per_pair": round(stats.ms_per_pair, 3),
                "wall_time_s": round(self.wall_s, 3),
            },
        }


_VERIFICATION_OFF: dict[str, Any] = {
    "verification": "off",
    "verification_hash": None,
    "verification_parameters": None,
    "intrinsics": None,
    "verification_cost": None,
}


@dataclass(frozen=True)
class FolderEvaluation:
    """One `evaluate --images` run: the replay, its figures, and the verified ones."""

    images: Path
    fps: float
    params: Parameters
    result: ReplayResult
    evaluation: Evaluation  # every candidate (the paper's figures)
    verification: FolderVerification | None  # None when verification was off
    verified: Evaluation | None  # the accepted pairs only, at the same th
    health: FeatureHealth | None = None  # too few features to segment or verify?

    def format_report(self, threshold_note: str = "default with verification") -> str:
        """The `evaluate --images` report: the paper's without verification, else raw and
        verified side by side (`threshold_note` says where th came from)."""
        headline = (
            f"{self.params.method} on {self.images} at {self.fps:g} fps "
            f"(features: {self.result.feature_detector}, parameters {self.params.hash}, "
            f"{self.result.frames_per_second:.0f} frames/s)"
        )
        warnings = _warning_lines(self.health)
        if self.verification is None:
            return "\n".join([headline, *warnings, format_report(self.evaluation)])
        side_by_side = format_side_by_side(self.evaluation, self.verified, threshold_note)
        headline += f"; {self.verification.describe()}"
        return "\n".join([headline, *warnings, side_by_side])

    def scored_against(self, gt: GroundTruth, tolerance: int = 0) -> FolderEvaluation:
        """The same run's decisions scored against another ground truth (no new run).

        Raises GroundTruthError when `gt` does not have one row per image of the run.
        """
        scores = _scores(self.result, self.verification, gt, self.params, self.fps, tolerance)
        return replace(self, **scores)

    def to_json_dict(self) -> dict[str, Any]:
        """The `evaluate --images --json` document."""
        verification = self.verification
        return {
            "tool_version": __version__,
            "images": str(self.images),
            "fps": self.fps,
            "method": self.params.method,
            "feature_detector": self.result.feature_detector,
            "parameters_hash": self.params.hash,
            "wall_time_s": round(self.result.wall_time_s, 3),
            "parameters": self.params.to_dict(),
            **(_VERIFICATION_OFF if verification is None else verification.to_json_dict()),
            **self.evaluation.to_json_dict(),
            "verified": None if self.verified is None else self.verified.to_json_dict(),
            "features": None if self.health is None else self.health.to_json(),
        }


def evaluate_folder(
    images: str | Path,
    fps: float,
    gt: GroundTruth | str | Path,
    params: Parameters | None = None,
    verification: VerificationParameters | None = DEFAULT_VERIFICATION,
    intrinsics: Intrinsics | None = None,
    tolerance: int = 0,
    gt_variable: str | None = None,
    progress: Callable[[int], None] | None = None,
    expected: Callable[[int], None] | None = None,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    stage: Callable[[str], None] | None = None,
) -> FolderEvaluation:
    """Replay the detector over the folder's images (natural file-name order, stamped at `fps`),
    verify its candidates, and score both against `gt` (one row per image), as
    `evaluate --images` does: the folder is a Source (`ImageFolderSource`) and the run is
    annotate's (`pipeline.annotate.decide_log`), nothing written. params=None takes the
    command's defaults: the verified ones with verification, else the paper's.
    `expected(images)` is called once the folder is listed, `progress(frames done)` after each
    frame, `stage("replay" | "verify")` as each begins.

    Raises SourceError (no images, or one that cannot be decoded), ImageDecodeError (an
    image over `max_pixels`, refused from its header), GroundTruthError (unreadable ground
    truth, or not one row per image: checked before the run), ParameterError.
    """
    images = Path(images)
    if params is None:
        params = command_detector_parameters(verification)
    truth = gt if isinstance(gt, GroundTruth) else load_ground_truth(gt, gt_variable)
    source = ImageFolderSource(images, fps, max_pixels)
    if len(source.files) != truth.n_frames:  # before the run: a wrong GT file is the usual cause
        raise GroundTruthError(
            f"{truth.source}: ground truth has {truth.n_frames} frames but {images} has "
            f"{len(source.files)} images"
        )
    options = AnnotateOptions(
        time_source="log",
        on_error="fail",
        workers=VERIFY_THREADS,
        verification=verification,
        intrinsics=intrinsics,
        max_pixels=max_pixels,
    )
    announced = None if expected is None else lambda count: expected(count or 0)
    with source:
        decided = decide_log(
            OpenLog(source, None, images, None), params, options, progress, announced, stage
        )
    result = decided.replayed.result
    checked = None if decided.verification is None else _folder_verification(decided)
    scores = _scores(result, checked, truth, params, fps, tolerance)
    health = decided.feature_health(params)
    return FolderEvaluation(
        images, fps, params, result, verification=checked, health=health, **scores
    )


def _folder_verification(decided: Decided) -> FolderVerification:
    """The run's verification as the report gives it: each decision reduced to its accepted
    pairs."""
    run = decided.verification
    assert run is not None
    checked = list(run.decisions.values())
    return FolderVerification(
        run.params, run.intrinsics, verified_decisions(checked), run.stats, run.wall_s
    )


def _scores(
    result: ReplayResult,
    checked: FolderVerification | None,
    gt: GroundTruth,
    params: Parameters,
    fps: float,
    tolerance: int,
) -> dict[str, Any]:
    """The raw and verified figures at the run's th, with the revisit coverage."""
    times = [folder_time_ns(index, fps) for index in range(result.frames)]
    th = params.threshold
    verified = None
    if checked is not None:
        verified = evaluate(checked.decisions, gt, th, tolerance, times)
    return {
        "evaluation": evaluate(result.decisions, gt, th, tolerance, times),
        "verified": verified,
    }


def _warning_lines(health: FeatureHealth | None) -> list[str]:
    """The feature-poor warnings and the advice, one a line (none for a healthy run)."""
    if health is None or not health.poor:
        return []
    return [f"WARNING: {text}" for text in health.warnings] + [f"         {ADVICE}"]
