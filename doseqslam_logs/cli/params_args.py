"""Command-line options that build the detector parameters (shared by every subcommand)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..detector import Parameters
from ..errors import ParameterError, UsageError

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib
from ..verification import VERIFIED_THRESHOLD, VerificationParameters, verified_defaults

if TYPE_CHECKING:
    from ..verification import Intrinsics


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
        params = params.replace(**{name.strip(): _toml_value(value.strip())})
    return params


def add_verification_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("geometric verification")
    group.add_argument(
        "--no-verify",
        dest="verify",
        action="store_false",
        help="report the detector's decisions unchecked (the paper's behaviour; th defaults to "
        f"the paper's 0.75 instead of {VERIFIED_THRESHOLD:g}, no next-best trajectories "
        "are recorded, and sequences are segmented with the paper-like 'auto' detector, SIFT "
        "where SURF is absent, instead of ORB)",
    )
    group.add_argument(
        "--intrinsics",
        metavar="FX,FY,CX,CY",
        help="camera intrinsics in pixels of the images (default: the log's CameraInfo; "
        "without either, the fundamental matrix is fitted and no relative pose is given)",
    )
    group.add_argument(
        "--vset",
        dest="verification_overrides",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override one verification parameter, e.g. --vset min_inliers=40 (repeatable)",
    )


def verification_from_args(args: argparse.Namespace) -> VerificationParameters | None:
    """The verification parameters, or None with --no-verify.

    Raises ParameterError for a bad name or value.
    """
    if not args.verify:
        return None
    values: dict[str, object] = {}
    for item in args.verification_overrides:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ParameterError(f"--vset expects NAME=VALUE, got {item!r}")
        values[name.strip()] = _plain_value(value.strip())
    return VerificationParameters.from_dict(values)


def _toml_value(text: str) -> object:
    """The TOML value `text` spells (`10`, `0.5`, `true`, `nan`), else the text itself: bare
    words are strings (--set association=greedy)."""
    try:
        return tomllib.loads(f"value = {text}")["value"]
    except tomllib.TOMLDecodeError:
        return text


def _plain_value(text: str) -> object:
    """An int, a float, true/false (TOML's spelling, as --set), else the text."""
    if text in ("true", "false"):
        return text == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            continue
    return text


def intrinsics_from_args(args: argparse.Namespace) -> Intrinsics | None:
    """--intrinsics fx,fy,cx,cy, or None. Raises UsageError for a malformed value."""
    if not getattr(args, "intrinsics", None):
        return None
    from ..verification import Intrinsics  # the pair checks: OpenCV, SciPy, when needed

    try:
        fx, fy, cx, cy = (float(v) for v in args.intrinsics.split(","))
        return Intrinsics(fx, fy, cx, cy)
    except ValueError as exc:
        raise UsageError(
            f"--intrinsics expects four numbers FX,FY,CX,CY with FX, FY > 0, got "
            f"{args.intrinsics!r}"
        ) from exc


def run_parameters(args: argparse.Namespace) -> Parameters:
    """The detector parameters of a run: with verification on, th, alternatives and the
    segmentation default to the verified ones (`verified_defaults`: the check supplies the
    precision, picks among the alternatives, and makes the faster segmentation as good),
    unless --config or --set gave them (either segmentation parameter keeps the other at its
    plain default).

    Raises ParameterError as parameters_from_args.
    """
    params = parameters_from_args(args)
    if getattr(args, "verify", False):
        params = params.replace(**verified_defaults(lambda name: parameter_given(args, name)))
    return params


def threshold_given(args: argparse.Namespace) -> bool:
    """True when --set or --config gave th."""
    return parameter_given(args, "threshold")


def parameter_given(args: argparse.Namespace, name: str) -> bool:
    """True when --set or --config gave the detector parameter `name`."""
    if any(item.partition("=")[0].strip() == name for item in args.overrides):
        return True
    if args.config:  # already read and validated by parameters_from_args
        return name in tomllib.loads(Path(args.config).read_text(encoding="utf-8"))
    return False
