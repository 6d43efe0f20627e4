"""The repository's text states facts, not the history of its own making: no docs page, comment or
docstring speaks of issues by number, work sessions, periods of work or stops, or of "the issue"."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: What the text of a library is read for: its docs, its code (comments and docstrings), its configs.
FOLDERS = ("core", "plugins", "conditioners", "sensors", "bench", "docs", "tests")
SUFFIXES = {".py", ".md", ".toml", ".txt"}
#: History words, each a pattern that a fact never needs (pytest's ``scope="session"`` is not one).
HISTORY = re.compile(
    r"\bissue[- ]#?\d+"
    r"|\bthe issue'?s?\b"
    r"|\b(?:this|last|earlier|previous|next|work) sessions?\b"
    r"|\bperiods? of work\b"
    r"|\bstop \d+\b"
    r"|\b(?:the|our) (?:old|new) default\b"
    r"|\bprevious bundle\b",
    re.IGNORECASE,
)
#: A third-party project's issue tracker cited as the source of a fact is not our history.
CITATION = re.compile(r"[\w.-]+/[\w.-]+ issue #\d+")


def repository_files() -> list[Path]:
    files = [ROOT / name for name in ("README.md", "CHANGELOG.md", "pyproject.toml", "Makefile")]
    for folder in FOLDERS:
        files += sorted(path for path in (ROOT / folder).rglob("*") if path.suffix in SUFFIXES)
    return [path for path in files if path.is_file() and path.resolve() != Path(__file__).resolve()]


def history_lines(text: str) -> list[tuple[int, str]]:
    """(line number, line) of every line of ``text`` that tells history."""
    return [
        (number, line.strip())
        for number, line in enumerate(text.splitlines(), 1)
        if HISTORY.search(CITATION.sub("", line))
    ]


@pytest.mark.parametrize(
    "line",
    [
        "as issue 12 asked",
        "the issue-11 tables",
        "The issue's tolerance",
        "measured in the last session",
        "the third period of work on the generator",
        "1:1 (the new default)",
        "Table 2 with the previous bundle",
    ],
)
def test_history_words_are_found(line):
    assert history_lines(line) == [(1, line)]


@pytest.mark.parametrize(
    "line",
    ['@pytest.fixture(scope="session")', "(Max-Fu/tvl issue #9; a fixed release)", "the default is 1:1"],
)
def test_facts_are_not_history(line):
    assert history_lines(line) == []


def test_no_file_tells_the_history_of_its_making():
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line}"
        for path in repository_files()
        for number, line in history_lines(path.read_text(encoding="utf-8", errors="replace"))
    ]
    assert not found, "state the fact without its history (issues, sessions, stops):\n" + "\n".join(found[:40])
