"""Command-line options that build the detector parameters (shared by every subcommand)."""

from __future__ import annotations

import argparse

from ..detector import Parameters
from ..errors import ParameterError


def add_parameter_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("detector parameters")
    group.add_argument("--config", metavar="PARAMS.toml", help="parameters file (TOML)")
    group.add_argument(
        "--method", choices=["doseqslam", "seqslam"], help="detector (default: doseqslam)"
    )
    group.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override one parameter, e.g. --set kappa_s=10 (TOML value syntax; repeatable)",
    )


def parameters_from_args(args: argparse.Namespace) -> Parameters:
    """--config, then --method, then each --set, later ones winning.

    Raises ParameterError for an unreadable file or a bad name or value.
    """
    params = Parameters.load(args.config) if args.config else Parameters()
    if args.method:
        params = params.replace(method=args.method)
    for item in args.overrides:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ParameterError(f"--set expects NAME=VALUE, got {item!r}")
        text = f"{name.strip()} = {value.strip()}"
        try:
            changed = Parameters.from_toml(text)
        except ParameterError:
            # Bare words are strings: --set association=greedy.
            changed = Parameters.from_toml(f'{name.strip()} = "{value.strip()}"')
        params = params.replace(**{name.strip(): getattr(changed, name.strip())})
    return params
