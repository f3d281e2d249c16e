"""Error classes of each layer and the documented exit codes of the command line."""

from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    """Process exit codes; documented in docs/cli.md and docs/robustness.md."""

    OK = 0
    DIFFERENT = 1  # `diff`: the two logs differ; `batch`: some log failed
    USAGE = 2  # bad arguments, unreadable config, unknown option value
    UNREADABLE_INPUT = 3  # the input is missing, not a log, or corrupt beyond use
    NO_CAMERA = 4  # the log holds no usable camera channel (or the topic asked for is absent)
    # A frame could not be used (undecodable image, timestamp before the previous frame) and
    # --on-error fail was asked for; or not a single image of the camera topic could be decoded.
    BAD_IMAGE = 5
    OUTPUT_ERROR = 6  # the output could not be written
    REGRESSION = 7  # `diff --fail-on`: B regressed against A by a rule given
    INTERNAL = 70  # a bug: please report it (run with --debug for the traceback)
    INTERRUPTED = 130  # SIGINT (Ctrl-C): 128 + 2
    TERMINATED = 143  # SIGTERM: 128 + 15


class DoseqslamError(Exception):
    """Base of every error this package raises on purpose; carries its exit code."""

    exit_code: ExitCode = ExitCode.USAGE


class UsageError(DoseqslamError):
    """Bad arguments or parameters."""

    exit_code = ExitCode.USAGE


class ParameterError(UsageError):
    """A parameters file or value is invalid."""


class SourceError(DoseqslamError):
    """A log could not be opened or read."""

    exit_code = ExitCode.UNREADABLE_INPUT


class NoCameraError(SourceError):
    """The log has no camera channel, or not the one asked for."""

    exit_code = ExitCode.NO_CAMERA


class TimestampError(SourceError):
    """A frame is stamped before the previous one and --on-error fail was asked for."""

    exit_code = ExitCode.BAD_IMAGE


class ImageDecodeError(DoseqslamError):
    """One image message could not be turned into pixels.

    `problem` names the kind of failure in a few words ("empty image", "corrupt compressed
    image", ...): runs count skipped frames by it.
    """

    exit_code = ExitCode.BAD_IMAGE

    def __init__(self, message: str, problem: str = "undecodable image") -> None:
        super().__init__(message)
        self.problem = problem


class DepthTopicError(UsageError):
    """A depth topic asked for is absent from the log or does not carry depth images."""


class GroundTruthError(UsageError):
    """A ground-truth file could not be read or does not fit the frames."""


class OutputError(DoseqslamError):
    """The output could not be written."""

    exit_code = ExitCode.OUTPUT_ERROR
