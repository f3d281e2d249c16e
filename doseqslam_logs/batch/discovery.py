"""Which logs a batch runs, and where each one's output goes.

Inputs are files, directories (searched recursively) and glob patterns. A directory holding a
`metadata.yaml` is a rosbag2 log, one log: its .db3/.mcap files are not searched separately.
Files inside the output folder and files named `*.annotated.mcap` found while searching are our
own outputs and are left out (a file named explicitly is always taken).

Each log's output mirrors its path relative to the common folder of all inputs, with
`.annotated.mcap` in place of `.mcap` (other names keep their suffix: `x.bag` becomes
`x.bag.annotated.mcap`), so logs of the same name in different folders never collide.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import UsageError
from ..sources.formats import is_log_folder, log_file_suffixes

OUTPUT_SUFFIX = ".annotated.mcap"
GLOB_MAGIC = frozenset("*?[")


@dataclass(frozen=True)
class LogInput:
    """One log to annotate: its absolute path and its output's path relative to OUTDIR."""

    path: Path
    relative_output: Path


def output_name(log: Path) -> str:
    """`x.mcap` -> `x.annotated.mcap`; any other name keeps its suffix: `x.bag.annotated.mcap`."""
    name = log.name[: -len(".mcap")] if log.name.endswith(".mcap") else log.name
    return name + OUTPUT_SUFFIX


def _is_inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _search(folder: Path, outdir: Path) -> Iterator[Path]:
    """The logs under `folder`, in name order; rosbag2 folders are not entered."""
    suffixes = log_file_suffixes()
    for dirpath, dirnames, filenames in os.walk(folder):
        here = Path(dirpath)
        dirnames.sort()
        kept = []
        for name in dirnames:
            child = here / name
            if _is_inside(child, outdir):
                continue
            if is_log_folder(child):
                yield child
            else:
                kept.append(name)
        dirnames[:] = kept  # os.walk descends only into these
        for name in sorted(filenames):
            if name.endswith(suffixes) and not name.endswith(OUTPUT_SUFFIX):
                yield here / name


def _expand(path: Path) -> tuple[list[Path], list[Path]]:
    """(folders to search, logs) of one existing path: a folder, or a log (a rosbag2 folder
    is a log)."""
    path = path.resolve()
    if path.is_dir() and not is_log_folder(path):
        return [path], []
    return [], [path]


def _expand_argument(argument: str) -> tuple[list[Path], list[Path]]:
    """(folders to search, logs) of one command-line input: a path or a glob pattern."""
    path = Path(argument)
    if path.exists():
        return _expand(path)
    if not GLOB_MAGIC & set(argument):
        raise UsageError(f"{argument}: no such file or directory")
    matches = sorted(glob.glob(argument, recursive=True))
    if not matches:
        raise UsageError(f"{argument}: no file matches this pattern")
    roots: list[Path] = []
    logs: list[Path] = []
    for match in matches:
        more_roots, more_logs = _expand(Path(match))
        roots += more_roots
        logs += more_logs
    return roots, logs


def discover_logs(inputs: Sequence[str], outdir: Path) -> list[LogInput]:
    """Every log of `inputs`, each once, in a stable order, with collision-free output names.

    Raises UsageError for an input that does not exist or a pattern that matches nothing, no
    log at all, or two logs whose output names would collide (`x` and `x.mcap` side by side).
    """
    outdir = outdir.resolve()
    anchors: list[Path] = []
    found: list[Path] = []
    for argument in inputs:
        roots, logs = _expand_argument(argument)
        for root in roots:
            anchors.append(root)
            found += _search(root, outdir)
        for log in logs:
            anchors.append(log.parent)
            found.append(log)
    unique = list(dict.fromkeys(found))
    if not unique:
        kinds = ", ".join(log_file_suffixes())
        raise UsageError(f"no logs ({kinds}, rosbag2 folders) in {' '.join(inputs)}")
    base = Path(os.path.commonpath(anchors))
    return _with_output_names(unique, base)


def _with_output_names(logs: Iterable[Path], base: Path) -> list[LogInput]:
    planned: dict[Path, Path] = {}
    result = []
    for log in logs:
        relative = log.parent.relative_to(base) / output_name(log)
        if relative in planned:
            raise UsageError(
                f"{log} and {planned[relative]} would both be written to {relative}; "
                "rename one or run them in separate batches"
            )
        planned[relative] = log
        result.append(LogInput(log, relative))
    return result
