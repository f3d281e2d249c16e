"""The user guide stays a guide (issue #36, item 4): README.md and docs/*.md together at most
120 KiB, every relative link in them and in docs/research/*.md reaching an existing file and,
with an anchor, a heading of it (GitHub's rule), and no research-log prose (issue numbers,
dated headings) in the guide pages. The dated measurements live under docs/research/."""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
GUIDE_LIMIT_BYTES = 120 * 1024

# [text](target) and ![alt](target), not inside code; the target up to a space or ")".
_LINK = re.compile(r"!?\[(?:[^\]\\]|\\.)*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_FENCE = re.compile(r"^ *(```|~~~)")
_HEADING = re.compile(r"^ {0,3}(#{1,6})[ \t]+(.*?)(?:[ \t]+#+)?[ \t]*$")
_INLINE_CODE = re.compile(r"(`+)(.+?)\1")


def guide_pages() -> list[Path]:
    return [REPO / "README.md", *sorted(DOCS.glob("*.md"))]


def research_pages() -> list[Path]:
    return sorted((DOCS / "research").glob("*.md"))


def prose_lines(text: str) -> list[str]:
    """The lines of a page with fenced code blocks blanked and inline code spans blanked (their
    brackets are not links, their `#` lines not headings); line numbers stay."""
    lines, fenced = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            lines.append("")
            continue
        lines.append("" if fenced else _INLINE_CODE.sub(lambda m: " " * len(m.group(0)), line))
    return lines


def headings(path: Path) -> list[str]:
    """The text of every ATX heading outside code blocks, in order."""
    found = []
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if _FENCE.match(line):
            fenced = not fenced
        elif not fenced and (match := _HEADING.match(line)):
            found.append(match.group(2))
    return found


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text: markdown marks and punctuation other than '-' and
    '_' dropped, lower case, each space a '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link: its text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading's anchor, duplicates numbered as GitHub numbers them (-1, -2, ...)."""
    seen: dict[str, int] = {}
    result: set[str] = set()
    for heading in headings(path):
        base = slug(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        result.add(base if count == 0 else f"{base}-{count}")
    return result


def links(path: Path) -> list[tuple[int, str]]:
    """The relative links of a page, (line number, target); link text may span lines."""
    text = "\n".join(prose_lines(path.read_text(encoding="utf-8")))
    found = []
    for match in _LINK.finditer(text):
        target = match.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("//"):
            continue  # http:, https:, mailto:, ...
        found.append((text.count("\n", 0, match.start(1)) + 1, target))
    return found


def broken_link(page: Path, target: str) -> str | None:
    """Why a link does not resolve, or None."""
    path_part, _, anchor = target.partition("#")
    file = page if not path_part else (page.parent / unquote(path_part)).resolve()
    if not file.exists():
        return f"{target}: no file {file}"
    if anchor and file.suffix == ".md" and unquote(anchor).lower() not in anchors(file):
        return f"{target}: no heading #{anchor} in {file}"
    return None


def test_the_slug_follows_github() -> None:
    assert slug("`info LOG`: what a log holds") == "info-log-what-a-log-holds"
    assert slug("`annotate LOG -o OUT.mcap`: the main job") == (
        "annotate-log--o-outmcap-the-main-job"
    )
    assert slug("Pipes and `-`") == "pipes-and--"
    assert slug("The motion rule: the camera left and came back") == (
        "the-motion-rule-the-camera-left-and-came-back"
    )


def test_duplicate_headings_are_numbered(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# Measured\n\n```sh\n# Measured\n```\n\n## Measured\n\n### Measured\n")
    assert anchors(page) == {"measured", "measured-1", "measured-2"}


def test_the_checker_finds_what_is_broken(tmp_path: Path) -> None:
    (tmp_path / "other.md").write_text("# Other page\n")
    page = tmp_path / "page.md"
    page.write_text(
        "## Here\n\nSee [the other\npage](other.md#other-page), [here](#here), "
        "[gone](missing.md), [no such heading](other.md#elsewhere) and "
        "[a site](https://example.org/x.md).\n\n```text\n[not a link](nowhere.md)\n```\n"
        "`[nor this](nowhere.md)`\n"
    )
    found = links(page)
    assert [target for _, target in found] == [
        "other.md#other-page",
        "#here",
        "missing.md",
        "other.md#elsewhere",
    ]
    assert found[0][0] == 4  # the line the target is on
    assert [target for _, target in found if broken_link(page, target)] == [
        "missing.md",
        "other.md#elsewhere",
    ]


def test_the_guide_fits_in_120_kib() -> None:
    sizes = {page.relative_to(REPO).as_posix(): page.stat().st_size for page in guide_pages()}
    assert sum(sizes.values()) <= GUIDE_LIMIT_BYTES, sizes


@pytest.mark.parametrize(
    "page",
    [*guide_pages(), *research_pages()],
    ids=lambda page: page.relative_to(REPO).as_posix(),
)
def test_relative_links_resolve(page: Path) -> None:
    problems = [
        f"{page.relative_to(REPO)}:{number}: {why}"
        for number, target in links(page)
        if (why := broken_link(page, target)) is not None
    ]
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("page", sorted(DOCS.glob("*.md")), ids=lambda page: page.name)
def test_guide_pages_are_not_a_research_log(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    issues = re.findall(r"issue #\d+|#\d+'s\b", text, flags=re.IGNORECASE)
    dated = [heading for heading in headings(page) if re.search(r"\b20\d\d-\d\d-", heading)]
    assert not issues, f"{page.name}: {sorted(set(issues))}"
    assert not dated, f"{page.name}: {dated}"
