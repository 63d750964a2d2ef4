"""The package and the benchmark scripts speak of the software, never of how it was made: no issue
numbers, no working sessions, no lent or borrowed machines, no helpers in the sense of assistants.

Python files are searched in their comments and strings (docstrings included), so names in code such
as ``start_new_session`` pass; the viewer's HTML, JavaScript and Markdown are searched whole."""

from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUFFIXES = (".py", ".md", ".js", ".html", ".css")
CODE_NOUNS = r"(?:function|functions|module|modules|class|classes|method|methods|script|scripts)"

HISTORY = [
    # issue and ticket numbers: "issue 15", "issues 13-14", "see #12", "(#123)", "#42" (two digits: never a colour)
    re.compile(r"\b[Ii]ssues? #?\d"),
    re.compile(r"(?i)\b(?:issues?|tickets?|bugs?|PRs?|pull requests?|fix(?:es|ed)?|close[sd]?|see|in|as|from)"
               r"\s+#\d+\b"),
    re.compile(r"\(#\d+\)"),
    re.compile(r"(?<![\w&/#])#\d{2}(?![\w#])"),
    # working sessions: "the fourth session's fields", "Tenth session"
    re.compile(r"\b[Ss]ession(?:s|'s)?\b"),
    # machines lent or borrowed for the work
    re.compile(r"\b[Ll]ent\b"),
    re.compile(r"\b[Bb]orrow(?:ed|ing)?\b"),
    # a helper as a person; "a helper function" and the like are code
    re.compile(rf"\b[Hh]elpers?\b(?! {CODE_NOUNS}\b)"),
]
DIVIDER = re.compile(r"^\s*#\s*-{3}.*-{3}\s*$")  # "# --- helpers ----": a section of code, not a person


def searched_files() -> list[Path]:
    """The package's files (warp_highlights/, kernels/), the benchmark scripts and their recorded results."""
    files = [p for folder in ("warp_highlights", "kernels") for p in (ROOT / folder).rglob("*")
             if p.suffix in SUFFIXES and p.is_file() and "__pycache__" not in p.parts]
    results = sorted((ROOT / "benchmarks" / "results").glob("*.json"))  # recorded runs: their notes and machines
    return sorted(files + sorted((ROOT / "benchmarks").glob("*.py")) + results)


def prose(path: Path, text: str) -> list[tuple[int, str]]:
    """(line number, text) of what ``path`` says in words: comments and strings of Python, else every line."""
    if path.suffix != ".py":
        return list(enumerate(text.splitlines(), 1))
    kinds = {tokenize.COMMENT, tokenize.STRING, getattr(tokenize, "FSTRING_MIDDLE", tokenize.STRING)}
    found = []
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type in kinds:
            found.extend((token.start[0] + k, line) for k, line in enumerate(token.string.splitlines()))
    return found


def history_lines(path: Path, text: str) -> list[str]:
    """'LINE: text' of each line of ``text`` (the contents of ``path``) that tells how the software was made."""
    hits = []
    for number, line in prose(path, text):
        patterns = HISTORY if not DIVIDER.match(line) else HISTORY[:-1]
        if any(pattern.search(line) for pattern in patterns):
            hits.append(f"{number}: {line.strip()}")
    return hits


def test_the_search_covers_the_package_and_the_benchmarks():
    names = {p.relative_to(ROOT).as_posix() for p in searched_files()}
    assert {"warp_highlights/__init__.py", "warp_highlights/model/config.py", "kernels/raster.py",
            "benchmarks/bench_quality.py", "warp_highlights/web/static/viewer.js",
            "benchmarks/results/bench_quality_cpu.json"} <= names
    assert not any(name.startswith("tests/") for name in names)


@pytest.mark.parametrize("path", searched_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_file_tells_how_the_software_was_made(path):
    assert history_lines(path, path.read_text(encoding="utf-8")) == []


PLANTED = [
    "# fixed in issue 14's third part",
    "# as #42 found",
    "# see #123",
    "# measured in the ninth session",
    "# the fourth session's fields",
    "# 0.43 s on the lent H100",
    "# on a machine borrowed for the day",
    "# the helper measured it",
    "# Helpers ran the sweep.",
    "# the last run (#7) chose it",
]


@pytest.mark.parametrize("planted", PLANTED)
def test_the_search_finds_a_planted_comment(planted):
    text = f'"""A module."""\n\nX = 1\n{planted}\nY = 2  # a plain comment\n'
    assert history_lines(Path("m.py"), text) == [f"4: {planted}"]


@pytest.mark.parametrize("planted", [p[2:] for p in PLANTED])
def test_the_search_finds_a_planted_docstring_string_and_page_line(planted):
    docstring = f'def f():\n    """Do it.\n\n    {planted}\n    """\n'
    assert history_lines(Path("m.py"), docstring) == [f"4: {planted}"]
    assert history_lines(Path("m.py"), f"raise ValueError({planted!r})\n") == [f"1: {planted!r}"]
    assert history_lines(Path("viewer.js"), f"const a = 1;\n// {planted}\n") == [f"2: // {planted}"]


@pytest.mark.parametrize("legitimate", [
    "subprocess.Popen(command, start_new_session=True)  # its own process group",
    "@pytest.fixture(scope='module')",
    "COLOURS = ['#9467bd', '#17becf', '#000']  # matplotlib's tab colours",
    "# --- writing helpers ----------------------------------------------------------------",
    "# a helper function; the helper module writes it; helper methods",
    "# each issued light is a unit vector; silently ignored values; lenticular prints",
    "# no issue for valid input; the problem is an ill-conditioned matrix",
    "# the 2-core CPU, an NVIDIA H100 (benchmarks/bench_quality.py)",
])
def test_the_search_lets_ordinary_code_and_words_pass(legitimate):
    assert history_lines(Path("m.py"), legitimate + "\n") == []
    assert history_lines(Path("page.html"), "<style>body { background: #000; color: #111 }</style>\n") == []


def test_no_file_name_tells_how_the_software_was_made():
    """Recorded results are named by what and where they measured, and the commit, not by a working session."""
    folders = ("warp_highlights", "kernels", "benchmarks", "docs", "tests", "notebooks")
    names = [p.relative_to(ROOT).as_posix() for folder in folders for p in (ROOT / folder).rglob("*") if p.is_file()]
    assert "benchmarks/results/bench_quality_cpu.json" in names
    assert [name for name in names if re.search(r"(?i)session|issue\d", name)] == []
