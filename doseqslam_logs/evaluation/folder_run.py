"""The detector on an image folder against a ground-truth matrix (`evaluate --images`).

The folder is replayed at a fixed rate, the candidate pairs verified geometrically (unless
verification is None), and both the raw and the verified decisions scored at the run's th.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .. import __version__
from ..detector import Parameters, make_detector
from ..detector.events import SequenceDecision
from ..errors import GroundTruthError
from ..pipeline.feature_health import (
    ADVICE,
    CheckFeasibility,
    FeatureHealth,
    check_feasibility,
    run_feature_health,
)
from ..pipeline.feature_spill import FeatureSpill, feature_spill_for
from ..pipeline.replay import ReplayResult, replay
from ..pipeline.reread import FolderFrameReader
from ..sources.image_folder import folder_frames, folder_time_ns, list_images
from ..sources.image_header import DEFAULT_MAX_PIXELS
from ..verification import (
    DEFAULT_VERIFICATION,
    Intrinsics,
    VerificationParameters,
    VerificationStats,
    command_detector_parameters,
)
from ..verification.stage import verify_in_threads
from ..verification.summary import verification_summary
from .groundtruth import GroundTruth, load_ground_truth
from .metrics import Evaluation, evaluate, format_report, format_side_by_side
from .verified import verified_decisions

# Threads that verify the candidates (each with its own feature cache); results do not depend
# on it.
VERIFY_THREADS = 2


@dataclass(frozen=True)
class FolderVerification:
    """What the verification stage decided over the folder's run, and what it cost."""

    params: VerificationParameters
    intrinsics: Intrinsics | None
    decisions: list[SequenceDecision]  # reduced to their accepted pairs (verified_decisions)
    stats: VerificationStats  # seconds summed over the threads
    wall_s: float  # of the whole stage
    checks: CheckFeasibility | None = None  # the checks the frames' features made impossible

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
    `evaluate --images` does. params=None takes the command's defaults: the verified ones with
    verification, else the paper's. `expected(images)` is called once the folder is listed,
    `progress(frames done)` after each frame, `stage("replay" | "verify")` as each begins.

    Raises SourceError (no images, or one that cannot be decoded), ImageDecodeError (an
    image over `max_pixels`, refused from its header), GroundTruthError (unreadable ground
    truth, or not one row per image: checked before the run), ParameterError.
    """
    images = Path(images)
    if params is None:
        params = command_detector_parameters(verification)
    truth = gt if isinstance(gt, GroundTruth) else load_ground_truth(gt, gt_variable)
    files = list_images(images)
    if len(files) != truth.n_frames:  # before the run: a wrong GT file is the usual cause
        raise GroundTruthError(
            f"{truth.source}: ground truth has {truth.n_frames} frames but {images} has "
            f"{len(files)} images"
        )
    if expected is not None:
        expected(len(files))
    if stage is not None:
        stage("replay")
    # verification's features, extracted as the replay decodes the images
    with feature_spill_for(verification, params) as features:
        frames = folder_frames(images, fps, max_pixels)
        result = replay(frames, make_detector(params), progress, side=features)
        if stage is not None and verification is not None:
            stage("verify")
        checked = (
            None
            if verification is None
            else _verify(files, result, verification, intrinsics, max_pixels, features)
        )
    scores = _scores(result, checked, truth, params, fps, tolerance)
    checks = None if checked is None else checked.checks
    accepted = result.loop_closures if checked is None else checked.stats.accepted
    health = run_feature_health(params, result, checks, accepted)
    return FolderEvaluation(
        images, fps, params, result, verification=checked, health=health, **scores
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


def _verify(
    files: list[Path],
    result: ReplayResult,
    params: VerificationParameters,
    intrinsics: Intrinsics | None,
    max_pixels: int,
    features: FeatureSpill | None,
) -> FolderVerification:
    start = time.perf_counter()
    reader = FolderFrameReader(files, max_pixels)  # stateless: one for every thread
    checked, stats = verify_in_threads(
        result.decisions,
        lambda: nullcontext(reader),
        params,
        intrinsics,
        VERIFY_THREADS,
        stored_features=None if features is None else features.get,
    )
    wall_s = time.perf_counter() - start
    feasible = check_feasibility(checked)
    return FolderVerification(
        params, intrinsics, verified_decisions(checked), stats, wall_s, feasible
    )
