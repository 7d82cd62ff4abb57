"""The documentation stays a reference: short pages, and every relative link and image points at something.

Pure Python (no workbench import, no ../shared): README.md and every Markdown file under docs/.
"""

from __future__ import annotations

import re
import unicodedata
from collections import Counter
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").rglob("*.md"))]

# [text](target) and ![alt](target), an optional "title" after the target; text without brackets inside.
LINK = re.compile(r"!?\[([^\[\]]*)\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(`{3,}|~{3,})")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def outside_fences(text: str):
    """The lines outside fenced code blocks."""
    fence = None
    for line in text.splitlines():
        match = FENCE.match(line)
        if match:
            mark = match.group(1)
            if fence is None:
                fence = mark[0] * len(mark)
            elif line.strip().startswith(fence):
                fence = None
            continue
        if fence is None:
            yield line


def prose_lines(text: str):
    """The lines outside fenced code blocks, with their inline code spans blanked."""
    for line in outside_fences(text):
        yield re.sub(r"(`+)(.+?)\1", lambda m: " " * len(m.group(0)), line)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower-case; drop every character but letters, digits, '_', '-' and spaces;
    spaces to '-'. A link in the heading counts as its text."""
    text = re.sub(r"!?\[([^\[\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    kept = (c for c in text if c in " -_" or unicodedata.category(c)[0] in "LMN" or unicodedata.category(c) == "Pc")
    return "".join("-" if c == " " else c for c in kept)


def anchors(page: Path) -> set[str]:
    """Every heading anchor of a Markdown page, repeated headings numbered as GitHub numbers them (-1, -2, ...)."""
    seen: Counter[str] = Counter()
    found = set()
    for line in outside_fences(page.read_text(encoding="utf-8")):
        heading = HEADING.match(line)
        if heading:
            base = slug(heading.group(2))
            found.add(base if not seen[base] else f"{base}-{seen[base]}")
            seen[base] += 1
    return found


def relative_links(page: Path) -> list[str]:
    links = []
    for line in prose_lines(page.read_text(encoding="utf-8")):
        links += [target for _, target in LINK.findall(line)]
    return [t for t in links if t and not re.match(r"(https?:|mailto:)", t, re.I)]


def test_the_readme_is_a_five_minute_page():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) < 200, f"README.md has {len(lines)} lines; move detail to docs/guide.md or docs/design.md"


def test_the_benchmarks_page_holds_todays_figures_only():
    lines = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) < 400, f"docs/benchmarks.md has {len(lines)} lines; dated entries belong in docs/journal/"


def test_the_readme_gives_the_commands_ci_and_a_newcomer_run():
    text = README.read_text(encoding="utf-8")
    assert "bash scripts/test.sh" in text  # .ci/run calls it
    assert "bash scripts/demo.sh" in text
    assert '.venv/bin/python -m pytest -m "not slow"' in text


def test_the_slug_is_githubs():
    assert slug("Whole datasets on Ray (2026-11-23): `--engine ray` against `--engine local`") == (
        "whole-datasets-on-ray-2026-11-23---engine-ray-against---engine-local")
    assert slug("Newcomer's map") == "newcomers-map"
    assert slug("Set-up: two commands") == "set-up-two-commands"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_and_image_resolves(page: Path):
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        goal = page if not path else (page.parent / path).resolve()
        if not goal.exists():
            broken.append(f"{target}: no such file")
        elif anchor and goal.suffix == ".md" and anchor not in anchors(goal):
            broken.append(f"{target}: no heading with that anchor in {goal.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


# What a newcomer asked for first: each must have a row in the map, and every path the map names must
# exist, so that a module moved without its row fails here.
MAP_MUST_NAME = ("the estimate's display", "a mode's ghost", "saving labels", "the sequence timeline",
                 "the results CSV", "the session format", "a new move kind")


def newcomers_map() -> dict[str, str]:
    """docs/design.md's "Newcomer's map": {what to change: the path to look in}."""
    text = (ROOT / "docs" / "design.md").read_text(encoding="utf-8")
    section = text.split("## Newcomer's map", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\|\s*(.+?)\s*\|\s*`([^`]+)`\s*\|\s*$", section, re.M)
    return dict(rows)


def test_the_newcomers_map_names_a_module_for_each_first_question_and_every_path_exists():
    rows = newcomers_map()
    for question in MAP_MUST_NAME:
        assert any(what.startswith(question) for what in rows), f"the map has no row for {question!r}"
    missing = {what: path for what, path in rows.items() if not (ROOT / path).exists()}
    assert not missing, missing
    assert len(rows) >= len(MAP_MUST_NAME)
