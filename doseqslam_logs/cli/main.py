"""The `doseqslam-logs` command: argument parsing, exit codes and error reporting.

Every error ends the run with one line on stderr, `doseqslam-logs: error: FILE: problem`, and
the exit code of its class (errors.ExitCode); a Python traceback appears only with --debug.
SIGTERM is turned into KeyboardInterrupt, so that a run stopped by a batch system or a timeout
cleans up exactly as after Ctrl-C: no partial output, no temporary file.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import FrameType

from .. import __version__
from ..errors import DoseqslamError, ExitCode
from . import annotate, batch, diff, evaluate, export, info, layout, optimize, to_bag

SUBCOMMANDS = (info, annotate, evaluate, diff, batch, export, optimize, layout, to_bag)


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived; a KeyboardInterrupt so that every cleanup for Ctrl-C runs."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="doseqslam-logs",
        description="Replay the DOSeqSLAM loop-closure detector over robot logs.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    debug_help = "show Python tracebacks of errors (for bug reports)"
    parser.add_argument("--debug", action="store_true", help=debug_help)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(subparsers)
    for subparser in subparsers.choices.values():
        # Also after the command (`annotate --debug LOG`); SUPPRESS keeps a --debug given
        # before the command when it is not repeated after it.
        subparser.add_argument(
            "--debug", action="store_true", default=argparse.SUPPRESS, help=debug_help
        )
    return parser


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated()


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM raises Terminated while the block runs (main thread only: Python delivers
    signals there); the previous handler comes back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _names_a_standard_stream(args: argparse.Namespace) -> bool:
    """Whether a path argument (input or output, alone or in a list) is `-`."""
    for value in vars(args).values():
        values = value if isinstance(value, list) else [value]
        if any(isinstance(item, Path) and str(item) == "-" for item in values):
            return True
    return False


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; errors become one line on stderr and a documented exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if _names_a_standard_stream(args):
        print(
            "doseqslam-logs: error: -: standard input and output are not supported "
            "(logs and outputs are read and written by seeking): give a file name",
            file=sys.stderr,
        )
        return int(ExitCode.USAGE)
    try:
        with _sigterm_as_interrupt():
            code: int = args.run(args)
        return code
    except DoseqslamError as exc:
        if args.debug:
            raise
        print(f"doseqslam-logs: error: {_one_line(exc)}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt as exc:
        if args.debug:
            raise
        terminated = isinstance(exc, Terminated)
        print(f"doseqslam-logs: {'terminated' if terminated else 'interrupted'}", file=sys.stderr)
        return int(ExitCode.TERMINATED if terminated else ExitCode.INTERRUPTED)
    except BrokenPipeError:
        return 0
    except Exception as exc:  # the promise: no traceback without --debug
        if args.debug:
            raise
        print(
            f"doseqslam-logs: internal error: {type(exc).__name__}: {_one_line(exc)} "
            "(run with --debug for the traceback and report it)",
            file=sys.stderr,
        )
        return int(ExitCode.INTERNAL)


if __name__ == "__main__":
    sys.exit(main())
