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
    """The folder of message definitions that belongs with this copy of the code.

    Installed, `schemas/` is the subpackage `doseqslam_logs.schemas` inside the package; in a
    source checkout it is the top-level `schemas/` folder beside the package. Both are looked
    for beside this file first: an editable install maps `doseqslam_logs.schemas` to the
    checkout it was made from, which would give another checkout's definitions to code run
    from this one (PYTHONPATH=checkout).
    """
    package = Path(__file__).resolve().parents[1]
    for folder in (package / "schemas", package.parent / "schemas"):
        if (folder / "json" / "LoopClosure.json").is_file():
            return folder
    return importlib.resources.files("doseqslam_logs.schemas")


def read_schema(name: str) -> str:
    """The text of one definition file, e.g. `read_schema("ros2/LoopClosure.msg")`."""
    node = schema_dir()
    for part in name.split("/"):
        node = node / part
    text: str = node.read_text(encoding="utf-8")
    return text
