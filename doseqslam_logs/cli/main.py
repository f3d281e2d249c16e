"""The `doseqslam-logs` command: argument parsing, exit codes and error reporting."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from .. import __version__
from ..errors import DoseqslamError, ExitCode
from . import annotate, evaluate, info

SUBCOMMANDS = (info, annotate, evaluate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="doseqslam-logs",
        description="Replay the DOSeqSLAM loop-closure detector over robot logs.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument(
        "--debug", action="store_true", help="show Python tracebacks of errors (for bug reports)"
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        module.add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one subcommand; errors become one line on stderr and a documented exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code: int = args.run(args)
        return code
    except DoseqslamError as exc:
        if args.debug:
            raise
        print(f"doseqslam-logs: error: {exc}", file=sys.stderr)
        return int(exc.exit_code)
    except KeyboardInterrupt:
        print("doseqslam-logs: interrupted", file=sys.stderr)
        return int(ExitCode.INTERRUPTED)
    except BrokenPipeError:
        return 0
    except Exception as exc:  # the promise: no traceback without --debug
        if args.debug:
            raise
        print(
            f"doseqslam-logs: internal error: {type(exc).__name__}: {exc} "
            "(run with --debug for the traceback and report it)",
            file=sys.stderr,
        )
        return int(ExitCode.INTERNAL)


if __name__ == "__main__":
    sys.exit(main())
