"""Docstrings and comments of `doseqslam_logs` say what the code does and why, not its history:
no issue references ("issue #17", "#20"), no dates (2026-12-03), no links into docs/research/.
The dated measurements behind the defaults live in docs/research/; a docstring that cites them
goes stale with the next version."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "doseqslam_logs"
MODULES = sorted(PACKAGE.rglob("*.py"))

# "issue #5", "issues #17 and #20", "#40": a reference to the tracker. An ISO timestamp
# (2038-01-19T03:14:07Z, an example of a time format) is not a date of the project's history.
HISTORY = {
    "an issue reference": re.compile(r"\bissues?\s+#?\d+|(?<![\w&#])#\d+\b", re.IGNORECASE),
    "a date": re.compile(r"\b20\d\d-[01]\d-[0-3]\d(?!T)"),
    "a link into docs/research/": re.compile(r"docs/research\b|\bresearch/[\w.-]+\.md"),
}


def history_in(text: str) -> list[str]:
    """What of HISTORY `text` holds, each as its kind and the text matched."""
    return [f"{kind} ({m.group(0)!r})" for kind, rx in HISTORY.items() for m in rx.finditer(text)]


def docstrings(tree: ast.Module) -> list[tuple[int, str]]:
    """(line, text) of the module's docstring and of every class's and function's."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            text = ast.get_docstring(node, clean=False)
            if text is not None:
                found.append((node.body[0].lineno, text))
    return found


def comments(source: str) -> list[tuple[int, str]]:
    """(line, text) of every comment."""
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    return [(t.start[0], t.string) for t in tokens if t.type == tokenize.COMMENT]


def test_the_patterns_catch_history() -> None:
    for text in (
        "Indexed place search (issue #17): windows.",
        "the rule of issues #5 and #20",
        "pure computation (#40)",
        "measured on 2026-12-03",
        "(docs/research/2026-12-03-precision.md, Second guesses)",
    ):
        assert history_in(text), text
    for text in (
        "nanoseconds since 2023-11-14T22:13:20.123456789Z",
        "the int64 limit (2038-01-19T03:14:07.999999999Z)",
        "chi2.ppf(0.99, 6); 10 degrees; 5 % of the frames",
        "docs/results.md describes the figures",
    ):
        assert not history_in(text), text


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_module_docstring_has_no_history(path: Path) -> None:
    text = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")), clean=False) or ""
    assert not history_in(text), f"{path.relative_to(REPO)}: {history_in(text)}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_docstrings_and_comments_have_no_history(path: Path) -> None:
    source = path.read_text(encoding="utf-8")
    found = [
        f"{path.relative_to(REPO)}:{line}: {', '.join(history_in(text))}"
        for line, text in docstrings(ast.parse(source)) + comments(source)
        if history_in(text)
    ]
    assert not found, "\n".join(found)
