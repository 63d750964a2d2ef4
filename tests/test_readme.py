"""The documents: README.md's length, its test command and its demo table (against a real ``demo`` run),
internal links, picture sizes, and no account of how the software was made in any document."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCUMENTS = sorted([README, ROOT / "CHANGELOG.md", ROOT / "ARCHITECTURE.md", ROOT / "benchmarks" / "README.md",
                    *(ROOT / "docs").glob("*.md")])
TEST_COMMAND = ("python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[test]' "
                "&& python -m pytest -q -m \"not slow\"")

# Work history: issue numbers, numbered tickets, working sessions, machines lent or borrowed, helpers.
# "helper" stays allowed before the nouns that make it code ("a helper function").
HISTORY = [
    re.compile(r"\b[Ii]ssues? \d"),
    re.compile(r"(?<![\w&/])#\d{2,}\b"),
    re.compile(r"\b[Ss]ession(s|'s)?\b"),
    re.compile(r"\b[Ll]ent\b"),
    re.compile(r"\b[Bb]orrowed\b"),
    re.compile(
        r"\b[Hh]elpers?\b(?! (function|functions|module|modules|class|classes|method|methods|script|scripts)\b)"),
]


def history_lines(text: str) -> list[str]:
    """The lines of ``text`` that speak of how the software was made."""
    return [line for line in text.splitlines() if any(pattern.search(line) for pattern in HISTORY)]


def section(text: str, start: str, end: str) -> str:
    """The text between the first ``start`` and the next ``end`` after it."""
    begin = text.index(start) + len(start)
    return text[begin:text.index(end, begin)]


def test_readme_is_at_most_300_lines():
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 300


def test_readme_holds_the_test_command_that_ci_extracts():
    """.ci/run takes the lines between the markers that are neither markers, fences nor blank."""
    block = section(README.read_text(encoding="utf-8"), "<!-- test-command -->", "<!-- /test-command -->")
    lines = [line for line in block.splitlines() if line and not line.startswith("<!--") and not line.startswith("```")]
    assert lines == [TEST_COMMAND]


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_document_tells_how_the_software_was_made(document):
    assert history_lines(document.read_text(encoding="utf-8")) == []


@pytest.mark.parametrize("planted", [
    "Fixed in issue 14's third part.",
    "Issue 19 asks for 0.5 s.",
    "as #42 found",
    "measured in the ninth session",
    "The Session's device time ran out.",
    "on a lent H100",
    "a machine borrowed for the day",
    "the helper measured it",
    "Helpers work in worktrees.",
])
def test_the_history_check_finds_a_planted_line(planted):
    text = "# Title\n\nA plain sentence.\n" + planted + "\nAnother plain sentence.\n"
    assert history_lines(text) == [planted]


@pytest.mark.parametrize("legitimate", [
    "Each issued light is a unit vector; silently ignored values; lenticular prints.",
    "The lentil-shaped highlight; a helper function; the helper module writes it.",
    "See [the table](#bench_webpy) and `#include <x>`; colour #fff.",
    "Bad input is answered in one line; no issue for valid input.",
])
def test_the_history_check_lets_ordinary_words_pass(legitimate):
    assert history_lines(legitimate) == []


def anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a Markdown file's headings."""
    found = set()
    for heading in re.findall(r"^#{1,6} +(.+?) *$", markdown, flags=re.MULTILINE):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        found.add(slug)
    return found


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_internal_links_resolve(document):
    text = document.read_text(encoding="utf-8")
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue  # http:, https:, mailto:
        path, _, anchor = target.partition("#")
        linked = (document.parent / path).resolve() if path else document
        if not linked.exists():
            broken.append(target)
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked.read_text(encoding="utf-8")):
            broken.append(target)
    assert broken == []


def test_the_pictures_are_small():
    pictures = sorted((ROOT / "docs" / "images").glob("*.png"))
    assert pictures, "docs/images holds no PNG"
    assert {p.name: p.stat().st_size for p in pictures if p.stat().st_size >= 300_000} == {}


def demo_table() -> list[str]:
    """The first column of README.md's table of what ``demo`` writes."""
    block = section(README.read_text(encoding="utf-8"), "<!-- demo-files -->", "<!-- /demo-files -->")
    rows = [line for line in block.splitlines() if line.startswith("|")][2:]
    return [re.fullmatch(r"`([^`]+)`", row.split("|")[1].strip()).group(1) for row in rows]


def test_the_readme_states_no_demo_figure_that_demo_json_does_not_give():
    """Times, sizes and scores differ between machines: the README leaves them to demo.json."""
    text = README.read_text(encoding="utf-8")
    demo_part = section(text, "## Two commands", "<!-- /demo-files -->")
    figures = re.findall(r"\d+(?:\.\d+)? ?(?:s|ms|min|minutes|seconds|MB|kB|KB|GB|dB|%)\b", demo_part)
    assert figures == []


@pytest.mark.slow
def test_the_readme_demo_table_lists_what_demo_writes(tmp_path):
    out = tmp_path / "demo"
    run = subprocess.run([sys.executable, "-m", "warp_highlights", "demo", str(out), "--lights", "16", "--size",
                          "64x36",
                          "--frames", "4", "--device", "cpu", "--residual", "lowrank", "-q"],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr
    written = sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir() if not p.name.startswith("."))
    assert sorted(demo_table()) == written
    demo = json.loads((out / "demo.json").read_text())
    assert sorted(demo["files"]) == sorted(set(written) - {"demo.json", "index.md"})
