"""python -m demon_lab.report: the cells and their statistics, the runs a row counts, the Markdown, CSV and
LaTeX tables, its one-line errors, publishing on a run, a report of real smoke runs, its figures."""

from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from conftest import table_alignment, table_rows

from demon_lab import resources
from demon_lab.pipeline.tracking import TAG, Tracker
from demon_lab.reporting import report
from tests.report_helpers import _fake_store, _spec, version_tags


def test_cell_statistics_by_hand():
    values = pd.DataFrame({"table": "t", "dataset": "d", "row": ["a", "a", "a", "b"], "column": "c",
                           "seed": [2, 0, 1, 0], "value": [3.0, 1.0, 2.0, 5.0]})
    result = {"cells": report.aggregate(values)}
    cell = report.cell(result, "t", "d", "a", "c")
    assert cell.n == 3 and cell.mean == 2.0 and cell.std == 1.0 and cell.values == (1.0, 2.0, 3.0)  # by seed
    assert cell.ci95 == pytest.approx(4.302653 / math.sqrt(3), rel=1e-6)  # t(0.975, 2) = 4.302653
    one = report.cell(result, "t", "d", "b", "c")
    assert one.n == 1 and one.mean == 5.0 and math.isnan(one.std) and math.isnan(one.ci95)
    empty = report.cell(result, "t", "d", "no such row", "c")
    assert empty.n == 0 and math.isnan(empty.mean) and empty.values == ()
    assert type(cell.mean) is float and type(cell.n) is int  # what csv writes as 2.0 and 3


def test_newest_finished_run_per_row_and_seed():
    """Row selection by tag-or-param masks on search_runs' frame, the newest FINISHED run per seed."""
    t = pd.Timestamp("2026-01-01", tz="UTC")
    runs = pd.DataFrame({
        "run_id": ["old", "new", "failed", "other", "param", "b"],
        "experiment": ["e", "e", "e", "f", "e", "e"],
        "status": ["FINISHED", "FINISHED", "FAILED", "FINISHED", "FINISHED", "FINISHED"],
        "start_time": [t, t + pd.Timedelta(1, "s"), t + pd.Timedelta(2, "s"), t + pd.Timedelta(3, "s"),
                       t, t],
        f"tags.{TAG}row": ["a", "a", "a", "a", None, "b"],
        "params.row": [None, None, None, None, "a", "b"],
        "seed": [0, 0, 0, 0, 1, 0]})
    spec = {"tables": [{"name": "t", "experiment": "e", "columns": [],
                        "rows": [{"label": "A", "match": {"row": "a"}}, {"label": "B", "match": {"row": "b"}}]}]}
    chosen = report.choose(spec, runs)
    assert sorted(zip(chosen["row"], chosen["seed"], chosen["run_id"])) == [("A", 0, "new"), ("A", 1, "param"),
                                                                           ("B", 0, "b")]
    assert list(report.field(runs, "row")) == ["a", "a", "a", "a", "a", "b"]  # the tag, else the param


def test_a_match_on_none_counts_the_runs_without_the_option():
    """``match: {k: null}`` counts the runs that logged "None" and those that never logged ``k`` (an option
    added after they ran); a value counts only the runs that logged it."""
    runs = pd.DataFrame({"run_id": ["before", "none", "set"], "experiment": "e", "status": "FINISHED",
                         "start_time": pd.Timestamp("2026-01-01", tz="UTC"), f"tags.{TAG}row": "a",
                         "params.loss.w": [None, "None", "10.0"], "seed": [0, 1, 2]})
    spec = {"tables": [{"name": "t", "experiment": "e", "columns": [],
                        "rows": [{"label": "off", "match": {"row": "a", "loss.w": None}},
                                 {"label": "on", "match": {"row": "a", "loss.w": 10.0}}]}]}
    chosen = report.choose(spec, runs)
    assert sorted(zip(chosen["row"], chosen["run_id"])) == [("off", "before"), ("off", "none"), ("on", "set")]


def test_paper_numbers_merge_the_rows_of_one_cell():
    rows = report.paper_numbers()
    ref = {"table": "2", "method": "depth-motion net", "rows": ["GT flow (depth)", "GT flow (motion)"]}
    cells = report.paper_cells(rows, ref, "SUN3D", ["l1_inv", "sc_inv", "l1_rel", "rot_deg", "tran_deg"])
    assert cells == {"l1_inv": 0.007, "sc_inv": 0.058, "l1_rel": 0.066, "rot_deg": 0.340, "tran_deg": 2.235}
    it3 = report.paper_cells(rows, {"table": "3", "method": "DeMoN", "rows": ["iteration 3"]}, "SUN3D", ["epe"])
    assert it3 == {"epe": 0.019}


@pytest.mark.slow
def test_every_shipped_spec_loads_and_names_known_paper_rows():
    from demon_lab.__main__ import check

    rows = report.paper_numbers()
    for path in sorted(report.STUDIES.glob("*.yaml")):
        spec = report.load_spec(path.stem)
        for overrides in spec["runs"] if not spec.get("requires") else []:
            # every job of the spec's commands composes and validates (a spec on files a user supplies,
            # released_model, runs in tests/test_released.py on tiny files)
            assert check(["-m", *overrides]) is None, (path.stem, overrides)
        for table in spec["tables"]:
            assert (resources.CONF / "experiment" / f"{table['experiment']}.yaml").is_file(), path.stem
            for row in table["rows"]:
                ref = row.get("paper")
                if ref:
                    datasets = {d for d in spec["datasets"].values() if d}
                    assert any(report.paper_cells(rows, ref, d, table["columns"]) for d in datasets), (path, row)


def test_report_aggregates_seeds_and_lists_failed_and_missing_runs(tmp_path):
    uri = _fake_store(tmp_path)
    _spec(tmp_path)
    paths = report.report("study", uri, tmp_path / "reports", tmp_path)
    with open(paths["csv"], newline="") as f:
        rows = {(r["row"], r["metric"]): r for r in csv.DictReader(f)}
    a, b = rows[("row a", "l1_inv")], rows[("row b", "l1_inv")]
    assert float(a["mean"]) == 2.0 and int(a["n"]) == 3 and float(a["std"]) == 1.0
    assert float(a["ci95"]) == pytest.approx(4.302653 / math.sqrt(3), rel=1e-6)
    assert float(b["mean"]) == 12.0 and int(b["n"]) == 2
    assert float(rows[("row a", "tran_deg")]["mean"]) == 20.0
    assert float(a["paper"]) == 0.058  # Table 2, depth-motion net, no GT, SUN3D
    md = paths["md"].read_text()
    assert ["row a", "3", "2.000 ± 2.484", "20.000 ± 24.841"] in table_rows(md)
    assert md.count("- FAILED run") == 1 and "NaN loss at step 7" in md  # row b, seed 2
    assert "1 FAILED run(s) followed by a FINISHED run of the same job, or of the same row and seed" in md
    assert "missing: t / row b: no FINISHED run for seed(s) 2" in md
    assert "- 2 FINISHED run(s) of older code or scene-generator versions" in md
    assert "python -m demon_lab -m +experiment=study" in md
    tex = paths["tex"].read_text()
    assert "\\begin{tabular}" in tex and "2.000 $\\pm$ 2.484" in tex


def test_a_cell_with_fewer_seeds_than_its_row_says_so(tmp_path):
    """Seed 2 logs no finite L1-inv (a depth map without one pixel of positive depth): the row
    counts 3 seeds (its translation cell), the L1-inv cell is the mean of 2 and is marked."""
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    tracker = Tracker(uri, "study", str(tmp_path / "artifacts"))
    for seed, value in enumerate([1.0, 3.0, math.nan]):
        run = tracker.start(f"a-{seed}", {f"{TAG}run_key": f"a{seed}", f"{TAG}row": "a",
                                          f"{TAG}seed": str(seed), **version_tags()})
        tracker.log_metrics(run, {"test/setA/it0/l1_inv": value, "test/setA/it0/tran_deg": 10.0 + seed})
        tracker.finish(run, "FINISHED")
    _spec(tmp_path)
    paths = report.report("study", uri, tmp_path / "reports", tmp_path)
    md = paths["md"].read_text()
    assert ["row a", "3", "2.000 ± 12.706 (n = 2)", "11.000 ± 2.484"] in table_rows(md)
    assert "($n=2$)" in paths["tex"].read_text()


def test_the_markdown_csv_and_latex_tables_hold_the_cells_in_the_specs_order(tmp_path):
    """pandas writes a report's three tables. Markdown: each cell's text, rows in the spec's order, the
    paper's row in italics under its row, the difference row last, left-aligned as before. CSV: one line
    per cell in that order, the numbers to full precision, a value that is not defined empty (a metric
    no run logged, the paper's value of a row without one). LaTeX: a booktabs tabular in its float under
    the caption, labels escaped, the paper's and the difference row in italics."""
    uri = _fake_store(tmp_path)
    _spec(tmp_path)
    spec = yaml.safe_load((tmp_path / "study.yaml").read_text())
    table = spec["tables"][0]
    table["columns"].append("epe")  # no run logs it
    table["rows"][1]["label"] = "row_b & 5%"
    table["differences"] = [{"label": "a minus b", "rows": ["row a", "row_b & 5%"]}]
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(spec))
    paths = report.report("study", uri, tmp_path / "reports", tmp_path)
    md = paths["md"].read_text()
    results = md[md.index("### setA"):md.index("## Provenance")]
    assert table_rows(results) == [["row", "n", "L1-inv", "tran (°)", "EPE"],
                                   ["row a", "3", "2.000 ± 2.484", "20.000 ± 24.841", "-"],
                                   ["*paper: row a*", "", "0.058", "41.766", "-"],
                                   ["row_b & 5%", "2", "12.000 ± 25.412", "120.000 ± 254.124", "-"],
                                   ["*a minus b*", "2", "-10.500 ± 19.059", "-105.000 ± 190.593", "-"]]
    assert table_alignment(results) == [["l"] * 5]

    with open(paths["csv"], newline="") as f:
        lines = list(csv.reader(f))
    assert lines[0] == ["table", "dataset", "row", "metric", "mean", "std", "ci95", "n", "values", "paper", "design",
                        "config", "run_ids"]
    assert [tuple(line[2:4]) for line in lines[1:]] == [(r, m) for r in ("row a", "row_b & 5%", "a minus b")
                                                        for m in ("l1_inv", "tran_deg", "epe")]
    values = pd.DataFrame({"table": "t", "dataset": "setA", "row": "row a", "column": "l1_inv", "seed": [0, 1, 2],
                           "value": [1.0, 2.0, 3.0]})
    a = report.cell({"cells": report.aggregate(values)}, "t", "setA", "row a", "l1_inv")
    assert lines[1][4:10] == [repr(a.mean), repr(a.std), repr(a.ci95), "3", "1 2 3", "0.058"]
    assert len(lines[1][6]) > 10  # (the CI to full precision, not the tables' 3 decimals)
    assert lines[3][4:10] == ["", "", "", "0", "", ""]  # epe of row a: no run logged it, the paper has none
    assert lines[4][9] == "" and lines[4][12] and lines[7][10:] == ["", "", ""]  # no paper row; no runs of its own

    tex = paths["tex"].read_text()
    assert tex.startswith("% A study\n% generated by python -m demon_lab.report study; ")
    assert tex[tex.index("\\begin{table}"):] == "\n".join([
        r"\begin{table}[t]\centering\small",
        r"\caption{cap; setA, mean $\pm$ 95\% CI over seeds; paper (SUN3D) in italics.}",
        r"\begin{tabular}{lrrr}",
        r"\toprule",
        r" & L1-inv & tran & EPE \\",
        r"\midrule",
        r"row a & 2.000 $\pm$ 2.484 & 20.000 $\pm$ 24.841 & - \\",
        r"\quad\textit{paper} & \textit{0.058} & \textit{41.766} & \textit{-} \\",
        r"row\_b \& 5\% & 12.000 $\pm$ 25.412 & 120.000 $\pm$ 254.124 & - \\",
        r"\textit{a minus b} & -10.500 $\pm$ 19.059 & -105.000 $\pm$ 190.593 & - \\",
        r"\bottomrule",
        r"\end{tabular}",
        r"\end{table}", "", ""])


def test_report_names_counted_runs_whose_artifacts_are_gone(tmp_path, capsys):
    """Runs logged metrics but no artifacts (as when a store's artifact folder is lost): the tables
    count them, the artifact-based figures cannot, and the report says so instead of drawing less."""
    uri = _fake_store(tmp_path)
    _spec(tmp_path, figures=["qualitative", "pixel_histograms"])
    md = report.report("study", uri, tmp_path / "reports", tmp_path)["md"].read_text()
    assert any(r[:2] == ["row a", "3"] for r in table_rows(md))
    assert "leave out 5 of the 5 counted runs" in md
    assert "5 of 5 counted runs have no artifacts" in capsys.readouterr().err


def test_report_of_an_unknown_spec_is_one_line(tmp_path):
    result = subprocess.run([sys.executable, "-m", "demon_lab.report", "no_such_study"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().startswith(
        "error: study spec 'no_such_study': no ablations/no_such_study.yaml; known: baseline_thresholds, baselines, ")
    assert len(result.stderr.splitlines()) == 1


def test_an_experiment_reported_inside_another_study_names_it(capsys):
    assert report.study_of("gt_depth_motion_oracle") == "gt_flow_oracle"  # a table of gt_flow_oracle's spec
    assert report.study_of("gt_flow_oracle") == "gt_flow_oracle" and report.study_of("iterations") == "iterations"
    assert report.study_of("no_such_experiment") is None
    assert report.main(["gt_depth_motion_oracle"]) == 2
    err = capsys.readouterr().err
    assert err == ("error: gt_depth_motion_oracle is reported by the study gt_flow_oracle: "
                   "python -m demon_lab.report gt_flow_oracle\n")


def test_publish_logs_the_report_on_a_run_and_leaves_reports_alone(tmp_path, monkeypatch):
    """What the sweep callback does at the end of a multirun: the study's report, built from the
    store, becomes artifacts of the sweep's parent run under report/ (figures under report/figures/)."""
    uri = _fake_store(tmp_path)
    _spec(tmp_path, figures=["iterations", "qualitative"])
    parent = Tracker(uri, "study", str(tmp_path / "artifacts")).start("sweep study", {f"{TAG}kind": "sweep"})
    monkeypatch.chdir(tmp_path)
    env = os.environ.get("MLFLOW_TRACKING_URI")
    paths = report.publish("study", uri, parent, tmp_path)
    assert paths == ["report/study.md", "report/study.csv", "report/study.tex", "report/figures/study_iterations.png"]
    assert not (tmp_path / "reports").exists()
    assert os.environ.get("MLFLOW_TRACKING_URI") == env  # the process's tracking URI is put back
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    assert {a.path for a in client.list_artifacts(parent, "report")} == {
        "report/study.md", "report/study.csv", "report/study.tex", "report/figures"}
    assert [a.path for a in client.list_artifacts(parent, "report/figures")] == ["report/figures/study_iterations.png"]
    md = Path(client.download_artifacts(parent, "report/study.md", str(tmp_path / "down"))).read_text()
    direct = report.report("study", uri, tmp_path / "direct", tmp_path)["md"].read_text()
    assert md == direct and ["row a", "3", "2.000 ± 2.484", "20.000 ± 24.841"] in table_rows(md)


@pytest.mark.slow
def test_report_from_real_smoke_runs(tmp_path):
    """A real smoke sweep of the flow-oracle experiment, then the Table 2 report from its runs."""
    overrides = ["scale=smoke", f"cache_dir={tmp_path}/cache", "seed=0"]
    job = subprocess.run([sys.executable, "-m", "demon_lab", "-m", "+experiment=gt_depth_motion_oracle", *overrides],
                         cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert job.returncode == 0, job.stderr[-2000:]
    result = subprocess.run([sys.executable, "-m", "demon_lab.report", "gt_flow_oracle"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    with open(tmp_path / "reports" / "gt_flow_oracle.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["table"] == "flow" and r["dataset"] == "synthetic_sun3d"]
    epe = {r["row"]: r for r in rows}
    assert int(epe["image pair only"]["n"]) == 1 and int(epe["GT depth+motion"]["n"]) == 1
    from mlflow.tracking import MlflowClient

    c = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    (job_run,) = [r for r in c.search_runs([c.get_experiment_by_name("gt_depth_motion_oracle").experiment_id])
                  if "demon_lab.run_key" in r.data.tags]  # the job, not its stages or the sweep's parent
    logged = job_run.data.metrics
    assert float(epe["GT depth+motion"]["mean"]) == logged["test/synthetic_sun3d/it1/epe"]
    assert float(epe["image pair only"]["mean"]) == logged["test/synthetic_sun3d/it0/epe"]
    assert float(epe["GT depth+motion"]["paper"]) == 0.005
    md = (tmp_path / "reports" / "gt_flow_oracle.md").read_text()
    assert "scale: smoke" in md and "missing: flow / image pair only: no FINISHED run for seed(s) 1, 2" in md
    assert "missing: depth_motion / image pair only: no FINISHED run for seed(s) 0, 1, 2" in md


def test_a_report_redraws_only_its_own_figures(tmp_path):
    """Regenerating gt_flow_oracle leaves gt_flow_oracle_long's figures alone."""
    from demon_lab.reporting.figures import study_figures

    names = ["gt_flow_oracle_motion_a.png", "gt_flow_oracle_qualitative_GT_flow_a.png",
             "gt_flow_oracle_long_motion_a.png", "gt_flow_oracle_long_pixel_errors_a.png", "iterations_iterations.png"]
    for n in names:
        (tmp_path / n).write_bytes(b"")
    assert [p.name for p in study_figures(tmp_path, "gt_flow_oracle")] == names[:2]
    assert [p.name for p in study_figures(tmp_path, "gt_flow_oracle_long")] == names[2:4]
    assert [p.name for p in study_figures(tmp_path, "iterations")] == names[4:]
