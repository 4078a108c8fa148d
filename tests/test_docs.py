"""The docs point at what the repository holds: every relative link of README, CHANGELOG, docs/ and
reports/ resolves, and every repository path they quote as code (`reports/...`, `demon_lab/...`,
`tests/FILE::test_name`, ...) exists, except the outputs of commands that need a GPU or the user's
own files (:data:`WRITTEN_ELSEWHERE`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import table_alignment, table_rows

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "NOTICE.md", *sorted((ROOT / "docs").rglob("*.md")),
         *sorted((ROOT / "reports").glob("*.md"))]
REPORTS = sorted((ROOT / "reports").glob("*.md"))
"""The committed reports a reader can trace a number to: those an archive in reports/runs/ redraws (the
records in docs/notes/unarchived/ have no archive, so the user pages do not quote their cells)."""
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
    ``python -m demon_lab.report --docs`` writes from the committed reports now, and
    reports/data_stats.md is what ``--data-stats`` writes from the committed statistics."""
    from demon_lab.reporting import doc_tables

    assert doc_tables.stale_blocks(doc_tables.pages(ROOT), ROOT) == []
    reports = ROOT / "reports"
    assert (reports / "data_stats.md").read_text() == doc_tables.camera_statistics(reports)


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
                                                  "t,setA,row c,epe,nan,nan,nan,0,,,,,\n"
                                                  "t,setA,row e,epe,0.25,,,1,,,,,\n"  # (pandas: NaN empty)
                                                  "t,setA,row f,epe,,,,0,,,,,\n")
    page = tmp_path / "docs" / "p.md"
    page.write_text("before\n<!-- report: s t setA -->\nold\n<!-- /report -->\nafter\n")
    assert doc_tables.stale_blocks([page], tmp_path) == ["docs/p.md: s t setA"]
    assert main(["--docs", "--out", str(tmp_path / "reports")]) == 0
    lines = page.read_text().splitlines()
    assert lines[0] == "before" and lines[-1] == "after"
    assert lines[2].startswith("| row ") and lines[7] == ""
    assert table_rows("\n".join(lines[2:7])) == [["row", "n", "EPE"], ["row a", "3", "0.123 ± 0.025"],
                                                ["row b", "1", "0.500"], ["row e", "1", "0.250"]]
    assert table_alignment(page.read_text()) == [["l", "l", "l"]]
    assert "[reports/s.md](../reports/s.md)" in page.read_text()
    assert doc_tables.stale_blocks([page], tmp_path) == []
    page.write_text(page.read_text().replace("0.500", "0.501"))
    assert doc_tables.stale_blocks([page], tmp_path) == ["docs/p.md: s t setA"]
    # a cell as the report's Markdown prints it: large values without decimals, fewer seeds marked
    (tmp_path / "reports" / "w.csv").write_text(header + "t,setA,row d,epe,7332.19,1,15785.614,3,,,,,\n"
                                                  "t,setA,row d,sc_inv,0.097,1,0.45,2,,,,,\n")
    assert table_rows(doc_tables.render(tmp_path / "reports", "w", "t", "setA"))[1] == \
        ["row d", "3", "7332 ± 15786", "0.097 ± 0.450 (n = 2)"]


INTERVAL = re.compile(r"-?\d[\d,]*\.?\d* ± \d[\d,]*\.?\d*")
"""A number quoted with its interval (or spread): ``0.089 ± 0.005``."""
THREE_DECIMALS = re.compile(r"(?<![\w.])-?\d+\.\d{3}(?!\d)")


def _outside_blocks(text: str) -> str:
    """A page's prose: without its report blocks (checked against their reports above) and code."""
    from demon_lab.reporting.doc_tables import BLOCK

    return re.sub(r"```.*?```", "", BLOCK.sub("", text), flags=re.S)


def untraced(text: str, reports: str) -> list[str]:
    """The numbers ``text`` quotes with an interval that no committed report prints as such."""
    return [m for m in INTERVAL.findall(_outside_blocks(text)) if m not in reports]


def _reports_text() -> str:
    return "".join(p.read_text() for p in REPORTS)


@pytest.mark.parametrize("page", [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_every_number_quoted_with_its_interval_is_a_reports_cell(page):
    """Prose that quotes a result with its interval quotes a committed report's cell as the report
    prints it (a cell re-typed with other digits, or from a run no report holds, fails)."""
    assert untraced(page.read_text(), _reports_text()) == []


def test_every_result_on_the_front_page_is_a_reports_number():
    """README quotes no result (a number with three decimals) that no committed report prints."""
    reports = {n.lstrip("-") for n in THREE_DECIMALS.findall(_reports_text())}  # (a difference quoted as a size)
    readme = _outside_blocks((ROOT / "README.md").read_text())
    assert [n for n in THREE_DECIMALS.findall(readme) if n.lstrip("-") not in reports] == []


def test_the_number_checks_find_a_retyped_cell():
    reports = "| row | 3 | 0.089 ± 0.005 | 69.888 ± 10.897 |"
    page = "EPE 0.089 ± 0.005, translation 69.89 ± 10.9°\n<!-- report: s t d -->\n1.0 ± 2.0\n<!-- /report -->\n"
    assert untraced(page, reports) == ["69.89 ± 10.9"]


def test_the_bench_and_data_statistics_blocks_are_their_files_tables(tmp_path):
    """``bench SECTION K``: the K-th table of that section of reports/bench.md, as written;
    ``data_stats table1 1``: reports/data_stats.md's table, each preset's JSON statistics beside the
    paper's Table 1 (``--data-stats`` writes it)."""
    import json

    from demon_lab.reporting import doc_tables

    reports = tmp_path / "reports"
    reports.mkdir()
    (reports / "bench.md").write_text("# b\n\n## data\n\ntext\n\n| a |\n|---|\n| 1 |\n\nmore\n\n| b |\n|---|\n| 2 |\n\n"
                                      "## train\n\n| c |\n|---|\n| 3 |\n")
    assert doc_tables.render(reports, "bench", "data", "2").startswith("| b |\n|---|\n| 2 |\n\n*From")
    assert doc_tables.render(reports, "bench", "train", "1").startswith("| c |\n|---|\n| 3 |\n")
    with pytest.raises(ValueError, match="section 'data' has no table 3"):
        doc_tables.render(reports, "bench", "data", "3")
    for i, preset in enumerate(doc_tables.PRESETS):
        (reports / f"data_stats_{preset}.json").write_text(json.dumps(
            {"n_pairs": 500, "rot_mean_deg": 1.0 + i, "rot_std_deg": 0.5, "tri_mean_deg": 2.0, "tri_std_deg": 0.25}))
    from demon_lab.reporting.report import main

    assert main(["--data-stats", "--out", str(reports)]) == 0
    table = doc_tables.render(reports, "data_stats", "table1", "1")
    assert "| `synthetic_sun3d` | 500 | 2.00 ± 0.50 | 10.6 ± 7.5 | 2.00 ± 0.25 | 5.2 ± 4.6 | SUN3D |" in table


def test_the_diagnosis_block_reads_each_seeds_passes(tmp_path):
    """``diagnose NAME SET``: per seed file, pass 0's EPE and each iterative pass's prior EPE / EPE,
    the refined depth's row left out."""
    import json

    from demon_lab.reporting import doc_tables

    (tmp_path / "diagnose").mkdir()
    for seed in (0, 1):
        passes = [{"pass": 0, "epe": 0.1 + seed, "prior_epe": float("nan")},
                  {"pass": 1, "epe": 0.2, "prior_epe": 0.25}, {"pass": "refined", "epe": 9.0, "prior_epe": 9.0}]
        (tmp_path / "diagnose" / f"x_seed{seed}.json").write_text(json.dumps({"passes": {"setA": passes}}))
    table = doc_tables.render(tmp_path, "diagnose", "x", "setA")
    assert table_rows(table) == [["seed", "pass 0 EPE", "pass 1: prior EPE / EPE"], ["0", "0.100", "0.250 / 0.200"],
                                 ["1", "1.100", "0.250 / 0.200"]]
    assert table_alignment(table) == [["l", "r", "l"]]
    assert table.split("\n\n")[1].startswith("*From reports/diagnose/x_seed*.json, setA")


def test_the_configuration_reference_is_current_and_gives_every_key_a_meaning():
    """docs/config.md is what ``python -m demon_lab.config_docs`` writes from conf/ and the schema now;
    every key of the default job and every option of each stage kind has its row, with a meaning."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from demon_lab.pipeline.kinds import STAGE_SPECS, options_of
    from demon_lab.resources import CONF
    from demon_lab.tools import config_docs

    page = (ROOT / "docs" / "config.md").read_text()
    assert config_docs.main(["--check", "--out", str(ROOT / "docs" / "config.md")]) == 0
    rows = {line.split(" | ")[0].strip("| `"): line for line in page.splitlines() if line.startswith("| `")}
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = OmegaConf.to_container(compose("config"), resolve=False)
    stack = [("", cfg)]
    keys = []
    while stack:
        prefix, node = stack.pop()
        for k, v in node.items():
            dotted = f"{prefix}{k}"
            if isinstance(v, dict) and dotted != "schedule.stages" and dotted != "scale":
                stack.append((dotted + ".", v))
            elif dotted not in ("schedule.stages", "scale"):
                keys.append(dotted)
    assert len(keys) > 70
    for key in keys:
        assert key in rows, key
        assert not rows[key].rstrip().endswith("|  |"), f"{key}: no meaning"
    stage_rows = [line for line in page.splitlines() if line.startswith("| `") and line.count(" | ") == 4
                  and line.split(" | ")[0].strip("| `") in STAGE_SPECS]
    assert {(r.split(" | ")[0].strip("| `"), r.split(" | ")[1].strip("`")) for r in stage_rows} == \
        {(kind, o) for kind in STAGE_SPECS for o in options_of(kind) if o != "kind"}
    assert all(not r.rstrip().endswith("|  |") for r in stage_rows)
