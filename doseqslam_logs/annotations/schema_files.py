"""Access to the output message definitions in `schemas/`, installed or in a source checkout."""

from __future__ import annotations

import importlib.resources
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    from importlib.resources.abc import Traversable
else:  # pragma: no cover - Python 3.10
    from importlib.abc import Traversable


def schema_dir() -> Traversable:
    """The folder of message definitions.

    Installed, `schemas/` is the subpackage `doseqslam_logs.schemas`; run from a source checkout
    (e.g. pytest from the repository root, where the checkout shadows the install) it is the
    top-level `schemas/` folder beside the package.
    """
    try:
        return importlib.resources.files("doseqslam_logs.schemas")
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "schemas"


def read_schema(name: str) -> str:
    """The text of one definition file, e.g. `read_schema("ros2/LoopClosure.msg")`."""
    node = schema_dir()
    for part in name.split("/"):
        node = node / part
    text: str = node.read_text(encoding="utf-8")
    return text
