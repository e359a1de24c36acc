"""The documentation reads as results and a changelog, not as a work log (pure text, fast).

Rules, for docs/results.md, CHANGELOG.md and the other project docs (README.md,
config/README.md, docs/*.md, docs/studies/*.md, benchmarks/**/README*):

* no absolute machine paths (``/work/...``, ``/tmp/...``, ``/home/...``, ``/root/...``,
  ``/Users/...``); relative paths (``../shared/data``, ``results/...``) and system tools
  (``/usr/bin/time``) are fine;
* no commit hashes: a token of 7 to 40 lowercase hex digits with at least one digit and
  one letter, standing alone (``\\b`` on both sides). Not counted as a commit: a colour
  (``#a1b2c3``, preceded by ``#``), a hex run longer than 40 (a SHA-256 digest: ``\\b``
  cannot fall inside it), and hex inside an identifier (``cmp_b0254``: ``_`` is a word
  character). Describe a code state in words ("before whole objects") instead;
* no work-log wording ("session");
* in docs/results.md and CHANGELOG.md, no numbered headings (``## 12. ...``);
* CHANGELOG.md follows Keep a Changelog 1.1.0: ``## [Unreleased]``, version headings
  ``## [X.Y.Z] - YYYY-MM-DD``, and only its section names at ``###``;
* every repository file that a command in docs/results.md or a study names (a path
  under ``benchmarks/``, ``workflow/``, ``config/``, ``rescu/``, ``tests/``,
  ``profiles/`` in a code span or a fenced block) exists.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results.md"
CHANGELOG = ROOT / "CHANGELOG.md"

ABSOLUTE_PATH = re.compile(r"(?<![\w.])/(work|tmp|home|root|Users)/")
HEX_TOKEN = re.compile(r"(?<!#)\b[0-9a-f]{7,40}\b")
NUMBERED_HEADING = re.compile(r"^#+\s*\d+[.)]", re.M)
SESSION = re.compile(r"\bsessions?\b", re.I)
KEEP_A_CHANGELOG_SECTIONS = {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}
REPO_PATH = re.compile(
    r"(?<![\w./-])((?:benchmarks|workflow|config|rescu|tests|profiles)/[\w./-]*\w\.(?:py|yaml|smk|sh))\b")


def _docs() -> list[Path]:
    files = [RESULTS, CHANGELOG, ROOT / "README.md", ROOT / "config" / "README.md"]
    files += sorted((ROOT / "docs").glob("*.md")) + sorted((ROOT / "docs" / "studies").glob("*.md"))
    files += sorted(p for p in (ROOT / "benchmarks").rglob("README*") if p.is_file())
    return list(dict.fromkeys(p for p in files if p.exists()))


def _rel(p: Path) -> str:
    return str(p.relative_to(ROOT))


def commit_like(text: str) -> list[str]:
    """Tokens of ``text`` that look like commit hashes (the rule in the module docstring)."""
    return [t for t in HEX_TOKEN.findall(text)
            if re.search(r"[0-9]", t) and re.search(r"[a-f]", t)]


def test_commit_like_rule():
    assert commit_like("at 9b4254c and 1a2b3c4d5e6f7a8b9c0d1e2f3a4b5c6d7e8f9a0b") == [
        "9b4254c", "1a2b3c4d5e6f7a8b9c0d1e2f3a4b5c6d7e8f9a0b"]
    assert commit_like("colour #a1b2c3d, image cmp_b0254, 1234567 px, deadbeef, "
                       "sha256 " + "ab12" * 16) == []


@pytest.mark.parametrize("path", _docs(), ids=_rel)
def test_no_absolute_machine_paths(path):
    hits = [ln for ln in path.read_text().splitlines() if ABSOLUTE_PATH.search(ln)]
    assert not hits, f"{_rel(path)}: absolute paths: {hits}"


@pytest.mark.parametrize("path", _docs(), ids=_rel)
def test_no_commit_hashes(path):
    hits = commit_like(path.read_text())
    assert not hits, f"{_rel(path)}: commit-hash-like tokens {hits}; name the code state in words"


@pytest.mark.parametrize("path", _docs(), ids=_rel)
def test_no_session_wording(path):
    hits = [ln for ln in path.read_text().splitlines() if SESSION.search(ln)]
    assert not hits, f"{_rel(path)}: work-log wording: {hits}"


@pytest.mark.parametrize("path", [RESULTS, CHANGELOG], ids=_rel)
def test_no_numbered_headings(path):
    hits = NUMBERED_HEADING.findall(path.read_text())
    assert not hits, f"{_rel(path)}: numbered headings {hits}"


def test_changelog_is_keep_a_changelog():
    text = CHANGELOG.read_text()
    assert text.startswith("# Changelog\n")
    versions = re.findall(r"^## (.*)$", text, re.M)
    assert versions and versions[0] == "[Unreleased]", versions
    for v in versions[1:]:
        assert re.fullmatch(r"\[\d+\.\d+\.\d+\] - \d{4}-\d{2}-\d{2}", v), v
    sections = set(re.findall(r"^### (.*)$", text, re.M))
    assert sections <= KEEP_A_CHANGELOG_SECTIONS, sections - KEEP_A_CHANGELOG_SECTIONS
    assert not re.search(r"^#### ", text, re.M)


def _code(text: str) -> list[str]:
    """Fenced blocks and inline code spans of a markdown text."""
    fenced = re.findall(r"^```[^\n]*\n(.*?)^```", text, re.M | re.S)
    inline = re.findall(r"`([^`\n]+(?:\n[^`\n]+)?)`", re.sub(r"^```.*?^```", "", text, flags=re.M | re.S))
    return fenced + inline


@pytest.mark.parametrize("path", [RESULTS] + sorted((ROOT / "docs" / "studies").glob("*.md")), ids=_rel)
def test_named_scripts_exist(path):
    named = {m for block in _code(path.read_text()) for m in REPO_PATH.findall(block)}
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert not missing, f"{_rel(path)} names files that are not in the repository: {missing}"


def test_results_names_its_commands():
    """Every table of results.md has a command in its section."""
    text = RESULTS.read_text()
    for section in re.split(r"^## ", text, flags=re.M)[1:]:
        title = section.splitlines()[0]
        if "|---" in section and title != "Not yet recorded":
            assert re.search(r"`[^`]*(make |python |snakemake|rescu |\.py)", section), title
