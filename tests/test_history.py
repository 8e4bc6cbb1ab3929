"""The project speaks of what it does, never of how it was developed: no development sessions, issue
numbers or commits in code, help texts, configs, docs, tests or benches (git holds the history).

In mapkit a "session" is one drive of a workspace, so "the test-night session" or "a session's map" are
the domain's words; what is refused is a session with a number ("session 14", "sessions 9-10"), an
issue number ("issue 24", "issue #10"), and a commit ("clone at b6df563", "commit 4f2a9c1")."""

from __future__ import annotations

import re
import subprocess

import pytest
from conftest import REPO

PATTERNS = {
    # a number after "session" that is not a quantity ("a session 8 m off" is a drive)
    "a numbered development session": re.compile(
        r"\b[Ss]essions? \d+(?:\s*(?:-|to|and)\s*\d+)?\b(?!\s*(?:m|cm|km|deg|%|px|s)\b)"
    ),
    "an issue number": re.compile(r"\b[Ii]ssues? #?\d+|\(#\d+\)|\bPR #?\d+"),
    "a commit": re.compile(r"\b(?:clone|commit|checkout|HEAD) (?:at |of )?[0-9a-f]{7,40}\b"),
}
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".toml", ".txt", ".sh", ".cfg", ".ini", ".json", ""}


def history_references(text: str) -> list[tuple[int, str, str]]:
    """(line number, what, the line) of every reference to development history in ``text``."""
    found = []
    for n, line in enumerate(text.splitlines(), 1):
        for what, pattern in PATTERNS.items():
            if pattern.search(line):
                found.append((n, what, line.strip()[:160]))
    return found


def _project_files() -> list:
    out = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    return [
        REPO / p
        for p in out
        if (REPO / p).is_file() and (REPO / p).suffix in TEXT_SUFFIXES and not p.startswith("docs/results/")
    ]


def test_the_patterns_find_history_and_spare_the_domains_words():
    refused = [
        "since session 14 the demo drives",
        "sessions 9-10 measured",
        "Session 16's figures",
        "issue 24's height drift",
        "(issue #10)",
        "a fresh clone at b6df563",
        "fixed in #21 (#21)",
    ]
    kept = [
        "the test-night session",
        "a session's map",
        "sessions with a map",
        "3 sessions",
        "one session per worker",
        "test-seq-1",
        "sha256 9f2c1e0d",
        "a session 8 m off",
        "the session 'tiny-night'",
        "issues a warning",
        "# 2 cm",
    ]
    assert all(history_references(t) for t in refused), [t for t in refused if not history_references(t)]
    assert not any(history_references(t) for t in kept), [t for t in kept if history_references(t)]


def test_no_file_of_the_project_refers_to_its_development_history():
    files = _project_files()
    assert any(p.name == "README.md" for p in files) and any(p.suffix == ".py" for p in files)
    found = [
        f"{p.relative_to(REPO)}:{n}: {what}: {line}"
        for p in files
        for n, what, line in history_references(p.read_text(errors="replace"))
        if p.name != "test_history.py"
    ]
    if found:
        pytest.fail(f"{len(found)} references to development history:\n" + "\n".join(found[:80]))
