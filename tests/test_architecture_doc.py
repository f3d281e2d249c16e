"""docs/architecture.md stays true (issue #36, item 7): its table of packages names, for each,
exactly the packages of `doseqslam_logs` it imports (read from the source, lazy imports
included), every package of the source is in the table, and its Python API examples run and
print what they say."""

from __future__ import annotations

import ast
import contextlib
import io
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "doseqslam_logs"
ARCHITECTURE = REPO / "docs" / "architecture.md"
SAMPLE = REPO / "sample_logs" / "drive_loops.ros2.mcap"


def packages() -> set[str]:
    return {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}


def imported_modules(path: Path) -> set[str]:
    """The dotted names of `doseqslam_logs` that one module imports, relative imports resolved."""
    package = path.relative_to(REPO).parts[:-1]  # ("doseqslam_logs", "pkg"[, "sub"])
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else ()
            module = tuple(node.module.split(".")) if node.module else ()
            if node.module:
                found.add(".".join(base + module))
            else:
                found |= {".".join((*base, alias.name)) for alias in node.names}
    return {name for name in found if name.startswith("doseqslam_logs.")}


def import_graph() -> dict[str, set[str]]:
    """Package -> the other packages (folders, not the root modules) its modules import."""
    names = packages()
    graph: dict[str, set[str]] = {name: set() for name in names}
    for name in names:
        for module in (PACKAGE / name).rglob("*.py"):
            for imported in imported_modules(module):
                other = imported.split(".")[1]
                if other in names and other != name:
                    graph[name].add(other)
    return graph


def documented_graph() -> dict[str, set[str]]:
    """The table's rows: `` `package/` | holds | depends on ``; the last cell's package names."""
    names = packages()
    rows = re.findall(r"^\| `(\w+)/` \|.*\| ([^|]*) \|$", ARCHITECTURE.read_text(), re.MULTILINE)
    assert rows, "docs/architecture.md: the table of packages is gone"
    graph = {}
    for package, cell in rows:
        graph[package] = {word for word in re.findall(r"\w+", cell) if word in names}
    return graph


def test_the_import_reader_resolves_relative_imports() -> None:
    # batch/job.py: `from ..detector import Parameters`, `from ..pipeline.annotate import (`.
    imported = imported_modules(PACKAGE / "batch" / "job.py")
    assert {"doseqslam_logs.detector", "doseqslam_logs.pipeline.annotate"} <= imported
    assert not any(name.startswith("doseqslam_logs.batch.detector") for name in imported)


def test_the_table_lists_every_package() -> None:
    assert set(documented_graph()) == packages()


@pytest.mark.parametrize("package", sorted(packages()))
def test_the_table_names_what_each_package_imports(package: str) -> None:
    assert documented_graph()[package] == import_graph()[package]


def test_nothing_downstream_is_imported_by_the_pure_cores() -> None:
    # The detector and the verification do no file I/O: they import no sources nor sinks.
    graph = import_graph()
    assert graph["detector"] == set()
    assert graph["verification"] <= {"detector"}


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", ARCHITECTURE.read_text(), re.DOTALL)


@pytest.mark.slow
def test_the_annotate_example_prints_what_it_says(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (block,) = [b for b in _python_blocks() if "annotate_log(" in b]
    said = re.search(r"print\((.+?)\)\s+# (\d+)", block)
    assert said, "the example's print says what it prints in a comment"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sample_logs").mkdir()
    (tmp_path / "sample_logs" / SAMPLE.name).symlink_to(SAMPLE)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(io.StringIO()):
        exec(compile(block, "architecture.md", "exec"), {})
    assert printed.getvalue().split() == [said.group(2)]


def test_the_detector_example_runs_on_the_sample() -> None:
    from doseqslam_logs.pipeline.decode import FrameCounts, decoded_frames
    from doseqslam_logs.sources import open_source

    (block,) = [b for b in _python_blocks() if "detector.push(" in b]
    with open_source(SAMPLE) as source:
        messages = source.image_messages("/camera/image/compressed")
        decoded = decoded_frames(messages, FrameCounts())
        frames = [(frame.timestamp_ns, frame.image) for frame in decoded]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        example = compile(block.replace("    ...", "    pass"), "architecture.md", "exec")
        exec(example, {"frames": frames})
    lines = printed.getvalue().splitlines()
    assert lines and all(len(line.split()) == 3 for line in lines)  # query, match, f
