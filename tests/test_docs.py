"""The docs point at what the repository holds: every relative link of README, CHANGELOG, docs/ and
reports/ resolves, and every repository path they quote as code (`reports/...`, `demon_lab/...`,
`tests/FILE::test_name`, ...) exists, except the outputs of commands that need a GPU or the user's
own files (:data:`WRITTEN_ELSEWHERE`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "NOTICE.md", *sorted((ROOT / "docs").glob("*.md")),
         *sorted((ROOT / "reports").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")
QUOTED = re.compile(r"`((?:reports|docs|demon_lab|conf|ablations|tests|scripts|hydra_plugins)/[^`\s*{}<>]+)`")
WRITTEN_ELSEWHERE = {
    "reports/device_check.md": "scripts/device_check.sh writes it on a GPU",
    "reports/released_model.md": "the released_model study runs on DeMoN's files, which users fetch",
}
"""Paths the docs name as where a command writes, which no committed run has written yet."""
HISTORY = "CHANGELOG.md"
"""A changelog names files as they were then: its links are checked, its quoted paths are not."""


def _relative_links(page: Path) -> list[str]:
    return [t for t in LINK.findall(page.read_text()) if not re.match(r"[a-z]+:", t) and not t.startswith("#")]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    missing = [t for t in _relative_links(page) if not (page.parent / t.split("#")[0]).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links files the repository lacks: {missing}"


def missing_paths(text: str) -> list[str]:
    """The repository paths ``text`` quotes as code that the repository lacks (a ``FILE::test`` whose
    file does not define the test included)."""
    missing = []
    for quoted in QUOTED.findall(text):
        path, _, test = quoted.rstrip(".,;:)").partition("::")
        if path in WRITTEN_ELSEWHERE or any(p in path for p in ("NAME", "DIR")) or path.endswith("S.json"):
            continue  # (a placeholder in a command's pattern: reports/diagnose/cpu_profile_seedS.json)
        target = ROOT / path
        if not target.exists() or (test and f"def {test.split('[')[0]}(" not in target.read_text()):
            missing.append(quoted)
    return missing


@pytest.mark.parametrize("page", [p for p in PAGES if p.name != HISTORY], ids=lambda p: str(p.relative_to(ROOT)))
def test_every_quoted_repository_path_exists(page):
    missing = missing_paths(page.read_text())
    assert not missing, f"{page.relative_to(ROOT)} names paths the repository lacks: {missing}"


def test_the_checks_find_a_broken_link_and_a_missing_path(tmp_path):
    """The two checks above fail on a page that links or quotes what is not there."""
    page = tmp_path / "page.md"
    page.write_text("[a](missing.md), [b](page.md#top), [c](https://example.org), `reports/runs/none.zip`, "
                    "`tests/conftest.py::test_that_is_not_there`, `tests/conftest.py::shared_renders`, "
                    "`docs/results.md`\n")
    assert _relative_links(page) == ["missing.md", "page.md#top"]
    assert missing_paths(page.read_text()) == ["reports/runs/none.zip", "tests/conftest.py::test_that_is_not_there"]
