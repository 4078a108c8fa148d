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
        if path in WRITTEN_ELSEWHERE or any(p in path for p in ("NAME", "DIR", "STUDY")) or path.endswith("S.json"):
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


def test_every_result_table_between_report_markers_is_its_reports_current_cells():
    """The tables that README and docs/ hold between ``<!-- report: ... -->`` markers are what
    ``python -m demon_lab.report --docs`` writes from the committed reports now."""
    from demon_lab.reporting import doc_tables

    assert doc_tables.stale_blocks(doc_tables.pages(ROOT), ROOT) == []


def test_the_report_command_writes_a_marked_table_from_the_reports_csv(tmp_path):
    """--docs fills a block from reports/<study>.csv (mean ± half-width, n; one seed: the mean), links
    the report relative to the page, and a block edited by hand is named stale."""
    from demon_lab.reporting import doc_tables
    from demon_lab.reporting.report import main

    (tmp_path / "reports").mkdir()
    (tmp_path / "docs").mkdir()
    header = "table,dataset,row,metric,mean,std,ci95,n,values,paper,design,config,run_ids\n"
    (tmp_path / "reports" / "s.csv").write_text(header + "t,setA,row a,epe,0.1234,0.01,0.0248,3,,,,,\n"
                                                  "t,setA,row b,epe,0.5,nan,nan,1,,,,,\n"
                                                  "t,setA,row c,epe,nan,nan,nan,0,,,,,\n")
    page = tmp_path / "docs" / "p.md"
    page.write_text("before\n<!-- report: s t setA -->\nold\n<!-- /report -->\nafter\n")
    assert doc_tables.stale_blocks([page], tmp_path) == ["docs/p.md: s t setA"]
    assert main(["--docs", "--out", str(tmp_path / "reports")]) == 0
    lines = page.read_text().splitlines()
    assert lines[0] == "before" and lines[-1] == "after"
    assert lines[2:6] == ["| row | n | EPE |", "|---|---|---|", "| row a | 3 | 0.123 ± 0.025 |",
                          "| row b | 1 | 0.500 |"]
    assert "[reports/s.md](../reports/s.md)" in page.read_text()
    assert doc_tables.stale_blocks([page], tmp_path) == []
    page.write_text(page.read_text().replace("0.500", "0.501"))
    assert doc_tables.stale_blocks([page], tmp_path) == ["docs/p.md: s t setA"]
