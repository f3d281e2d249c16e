"""The shown outputs are real: the README's quick start and the `annotate`, `evaluate --images`,
`evaluate OUT.mcap`, `diff`, `export` and `optimize` blocks of docs/cli.md are parsed, their
commands run (on the shared RTAB-Map samples, on a fresh annotation of the sample), and the
printed lines compared with the shown ones, with only machine-dependent fields (timings, the
optimizer's error sums) masked. The `batch`
block is left out (too slow), and so are the README's `evo_ape` lines (evo is not a dependency:
they were run with evo 1.38.1 from PyPI in a separate virtual environment on the files the
commands before them wrote; their output is shown as it printed). The README's links into
docs/cli.md lead to real headings.
After a change of behaviour, DOSEQSLAM_REFRESH_DOCS=1 writes the new outputs in (REFRESH)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from doseqslam_logs.cli.main import main

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
REFERENCE = REPO / "docs" / "cli.md"
# The fresh annotation the diff and export blocks start from (the evaluate block shows it made).
ANNOTATE = "annotate sample_logs/drive_loops.ros2.mcap -o drive_loops.annotated.mcap"

# Timings: "6.1 s," "12.0 s;" (not "40 s apart"), "40 frames/s", "1.8 ms each".
_MASKS = [
    (re.compile(r"\b\d+(?:\.\d+)? s(?=[,;)])"), "<t> s"),
    (re.compile(r"\b\d+ frames/s\b"), "<n> frames/s"),
    (re.compile(r"\b\d+(?:\.\d+)? ms each\b"), "<t> ms each"),
    # optimize: GTSAM's iterations and error sums, which floating-point kernels may change
    # (the calibrated odometry is stiff: 16 or 17 iterations on drive_loops).
    (re.compile(r"\b\d+ iterations, error \S+ -> \S+;"), "<n> iterations, error <e> -> <e>;"),
    # optimize: the odometry calibration's bias and factor, fitted to the metric poses.
    (
        re.compile(r"yaw-rate bias \S+ deg/s, (?:yaw scale \S+ %|no yaw scale), covariance x \S+$"),
        "yaw-rate bias <b>, x <s>",
    ),
    # Full-precision floats (the csv row: SAD values, fitted rotations, metric poses): another
    # processor's kernels (AVX2 against AVX-512) may round them differently.
    (re.compile(r"-?\d+\.\d{6,}(?:e[-+]?\d+)?"), "<f>"),
]


def mask(line: str) -> str:
    for pattern, replacement in _MASKS:
        line = pattern.sub(replacement, line)
    return line.rstrip()


# -- the README ---------------------------------------------------------------------------

# Commands shown with their real output but not run here (module docstring).
NOT_RUN = ("evo_ape",)


def not_run(line: str) -> bool:
    return line.split(maxsplit=1)[0] in NOT_RUN


@dataclass
class Command:
    line: str  # as shown after "$ ", continuation lines joined
    expected: list[str] = field(default_factory=list)


def section(heading: str, document: Path = REFERENCE, level: str = "###") -> str:
    """The text of the `level` section of `document` whose heading starts with `heading`."""
    text = document.read_text(encoding="utf-8")
    parts = re.split(rf"^{level} ", text, flags=re.MULTILINE)
    found = [part for part in parts if part.startswith(heading)]
    assert len(found) == 1, f"{document.name}: section {heading!r} not found"
    return found[0]


def github_anchor(heading: str) -> str:
    """The fragment GitHub gives a heading: lower case, punctuation dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def blocks(text: str) -> list[list[Command]]:
    """Each ```text block (indented ones too) as its commands and their shown output."""
    result = []
    for match in re.finditer(r"^( *)```text\n(.*?)^\1```$", text, flags=re.MULTILINE | re.DOTALL):
        indent = len(match.group(1))
        commands: list[Command] = []
        continued = False
        for raw in match.group(2).splitlines():
            line = raw[indent:]
            if continued:
                commands[-1].line = commands[-1].line[:-1].rstrip() + " " + line.strip()
            elif line.startswith("$ "):
                commands.append(Command(line[2:].strip()))
            else:
                assert commands, f"output before any command: {line!r}"
                commands[-1].expected.append(line)
            continued = line.endswith("\\")
        assert commands, f"a block without commands:\n{match.group(2)}"
        result.append(commands)
    return result


# -- running what the README shows --------------------------------------------------------


class _Tee(io.StringIO):
    """One stream (stdout or stderr) that also writes into the shared terminal."""

    def __init__(self, terminal: io.StringIO) -> None:
        super().__init__()
        self.terminal = terminal

    def write(self, text: str) -> int:
        self.terminal.write(text)
        return super().write(text)


def jq(filter_: str, document: str) -> str:
    """`jq -c` for a comma-separated list of plain paths (`.a, .b.c`), the README's one use."""
    value = json.loads(document)
    out = []
    for path in filter_.split(","):
        path = path.strip()
        assert re.fullmatch(r"(\.[A-Za-z_]\w*)+", path), f"jq filter not emulated: {path!r}"
        item = value
        for key in path[1:].split("."):
            item = item[key]
        out.append(json.dumps(item, separators=(",", ":"), ensure_ascii=False) + "\n")
    return "".join(out)


@dataclass
class Shell:
    """Runs `$` lines in one folder: doseqslam-logs in-process, `head -N`, `echo $?`, `| jq -c`.
    The same `annotate` command is run once (its output is byte-identical every time)."""

    cwd: Path
    status: int = 0
    annotated: dict[str, tuple[int, str]] = field(default_factory=dict)

    @contextlib.contextmanager
    def _inside(self) -> Iterator[None]:
        previous = Path.cwd()
        os.chdir(self.cwd)
        try:
            yield
        finally:
            os.chdir(previous)

    def _tool(self, argv: list[str]) -> tuple[int, str, str]:
        terminal = io.StringIO()
        out, err = _Tee(terminal), _Tee(terminal)
        with self._inside(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
        return code, out.getvalue(), terminal.getvalue()

    def run(self, line: str) -> str:
        """What the line prints on the terminal; sets `status` like $?."""
        words = shlex.split(line, comments=True)
        stages = [list(group) for group in _split(words, "|")]
        first = stages[0]
        if first == ["echo", "$?"]:
            return f"{self.status}\n"
        if first[0] == "head":
            assert len(first) == 3 and re.fullmatch(r"-\d+", first[1]), line
            text = (self.cwd / first[2]).read_text(encoding="utf-8")
            self.status = 0
            return "".join(text.splitlines(keepends=True)[: int(first[1][1:])])
        assert first[0] == "doseqslam-logs", f"command not emulated: {line}"
        key = " ".join(first[1:])
        if first[1] == "annotate" and key in self.annotated:
            self.status, shown = self.annotated[key]
            return shown
        self.status, stdout, shown = self._tool(first[1:])
        if first[1] == "annotate":
            self.annotated[key] = (self.status, shown)
        for stage in stages[1:]:
            assert stage[:2] == ["jq", "-c"] and len(stage) == 3, f"not emulated: {stage}"
            shown = shown.replace(stdout, "") + jq(stage[2], stdout)
        return shown


def _split(words: list[str], separator: str) -> Iterator[list[str]]:
    group: list[str] = []
    for word in words:
        if word == separator:
            yield group
            group = []
        else:
            group.append(word)
    yield group


@pytest.fixture(scope="module")
def shell(tmp_path_factory: pytest.TempPathFactory) -> Shell:
    """A folder laid out like the repository root for the README's relative paths, holding a
    fresh annotation of the sample."""
    folder = tmp_path_factory.mktemp("readme") / "repo"  # its parent can hold ../shared
    folder.mkdir()
    (folder / "sample_logs").symlink_to(REPO / "sample_logs", target_is_directory=True)
    shell = Shell(folder)
    shell.run(f"doseqslam-logs {ANNOTATE}")
    assert shell.status == 0
    return shell


# DOSEQSLAM_REFRESH_DOCS=1 pytest tests/test_readme.py writes the outputs the commands print
# into the documents instead of comparing them (then review the diff: it is the behaviour).
REFRESH = os.environ.get("DOSEQSLAM_REFRESH_DOCS") == "1"
# Commands a block may show without their output: the set-up of what the block is about.
SET_UP = ("doseqslam-logs annotate", "doseqslam-logs batch")


def refreshed_block(raw: str, indent: int, outputs: list[str]) -> str:
    """A ```text block's body with each command's shown output replaced by `outputs`."""
    lines: list[str] = []
    remaining, continued = iter(outputs), False
    for line in raw.splitlines():
        body = line[indent:]
        if not (continued or body.startswith("$ ")):
            continue  # an output line shown before: replaced below
        lines.append(line)
        continued = body.endswith("\\")
        if not continued:
            lines += [" " * indent + out for out in next(remaining).splitlines()]
    return "".join(f"{line}\n" for line in lines)


def refresh(document: Path, text: str, shell: Shell) -> None:
    """Run every block of `text` (a part of `document`) and write what it prints into it."""
    content = document.read_text(encoding="utf-8")
    for match in re.finditer(r"^( *)```text\n(.*?)^\1```$", text, flags=re.MULTILINE | re.DOTALL):
        commands = blocks(match.group(0) + "\n")[0]
        outputs = [
            "".join(f"{line}\n" for line in command.expected)
            if not_run(command.line)
            else shell.run(command.line)
            for command in commands
        ]
        for index, command in enumerate(commands):  # set-up steps stay without their summary
            if command.line.startswith(SET_UP) and not command.expected:
                outputs[index] = ""
        raw = match.group(2)
        content = content.replace(raw, refreshed_block(raw, len(match.group(1)), outputs), 1)
    document.write_text(content, encoding="utf-8")


def check_section(
    shell: Shell,
    heading: str,
    expected_blocks: int,
    text: str | None = None,
    document: Path = REFERENCE,
) -> None:
    text = section(heading, document) if text is None else text
    if REFRESH:
        refresh(document, text, shell)
        text = section(heading, document, "##" if document == README else "###")
    found = blocks(text)
    assert len(found) == expected_blocks, f"{heading}: {len(found)} text blocks"
    for commands in found:
        for index, command in enumerate(commands):
            if not_run(command.line):
                continue
            shown = shell.run(command.line)
            followed_by_status = index + 1 < len(commands) and commands[index + 1].line == "echo $?"
            if command.line == "echo $?":
                followed_by_status = True  # its output is the status, compared below
            allowed = {0, 1} if command.line.startswith("doseqslam-logs diff") else {0}
            assert followed_by_status or shell.status in allowed, (command.line, shown)
            actual = [mask(line) for line in shown.splitlines()]
            expected = [mask(line) for line in command.expected]
            if not expected and command.line.startswith(SET_UP):
                continue  # a set-up step shown without its summary line
            assert actual == expected, f"$ {command.line}"


@pytest.mark.slow
def test_quick_start_blocks(shell: Shell) -> None:
    check_section(shell, "Quick start", 2, section("Quick start", README, level="##"), README)


def test_pose_graph_block(shell: Shell) -> None:
    pytest.importorskip("gtsam")
    heading = "A pose graph with metric loop edges"
    check_section(shell, heading, 1, section(heading, README, level="##"), README)


def test_readme_links_into_the_reference_reach_its_headings() -> None:
    headings = re.findall(r"^#+ (.+)$", REFERENCE.read_text(encoding="utf-8"), re.MULTILINE)
    anchors = {github_anchor(h) for h in headings}
    links = re.findall(r"\(docs/cli\.md#([^)]+)\)", README.read_text(encoding="utf-8"))
    assert len(links) >= 8 and set(links) <= anchors, set(links) - anchors


def test_readme_stays_a_front_door() -> None:
    # 8.3 KiB: the pose-graph block grew by the odometry's and the truth's TUM exports and the
    # two evo_ape lines (issue #20's "annotate, optimize and evo with their real output").
    assert len(README.read_bytes()) <= round(8.3 * 1024)


def test_annotate_block(shell: Shell) -> None:
    check_section(shell, "`annotate LOG -o OUT.mcap`", 1)


def test_evaluate_images_block(shell: Shell, shared_data: Path) -> None:
    shared = shell.cwd.parent / "shared"  # the README's ../shared/data
    shared.mkdir(exist_ok=True)
    if not (shared / "data").exists():
        (shared / "data").symlink_to(shared_data, target_is_directory=True)
    check_section(shell, "`evaluate --images", 1)


def test_evaluate_annotated_log_blocks(shell: Shell) -> None:
    pytest.importorskip("matplotlib")  # the second block draws the pictures
    check_section(shell, "`evaluate OUT.mcap`", 2)
    for name in ["pr_curve.png", "difference_matrix.png", "trajectory.png"]:
        assert (shell.cwd / "docs" / "images" / name).is_file()


@pytest.mark.slow
def test_diff_blocks(shell: Shell) -> None:
    pytest.importorskip("matplotlib")  # the folder block writes a report
    check_section(shell, "`diff A B`", 2)


def test_export_blocks(shell: Shell) -> None:
    check_section(shell, "`export OUT.mcap", 1)


def test_optimize_block(shell: Shell) -> None:
    pytest.importorskip("gtsam")
    check_section(shell, "`optimize OUT.mcap", 1)


def test_masks_hide_timings_only() -> None:
    line = (
        "x.mcap: 240 frames of /c, 22 sequences, 83 loop closures, 0 skipped frames, 6.1 s, "
        "40 frames/s; verified 132 candidate pairs: 83 accepted (6061 frame pairs checked, "
        "1.8 ms each, 12.0 s; essential matrix)"
    )
    assert mask(line) == (
        "x.mcap: 240 frames of /c, 22 sequences, 83 loop closures, 0 skipped frames, <t> s, "
        "<n> frames/s; verified 132 candidate pairs: 83 accepted (6061 frame pairs checked, "
        "<t> ms each, <t> s; essential matrix)"
    )
    assert mask("40 loop edges; 4 iterations, error 2.83306 -> 2.43347; loop edges") == (
        "40 loop edges; <n> iterations, error <e> -> <e>; loop edges"
    )
    for heading in ("no yaw scale", "yaw scale -1.20 %"):
        line = f"46 metric loop edges: yaw-rate bias +0.0051 deg/s, {heading}, covariance x 0.0001"
        assert mask(line) == "46 metric loop edges: yaw-rate bias <b>, x <s>"
    assert mask("(within 2 m, 20 deg, >= 40 s apart, >= 20 m driven)").endswith(
        "40 s apart, >= 20 m driven)"
    )
