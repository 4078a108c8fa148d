"""The report command: seed aggregation, paper numbers, failed/missing runs, real smoke runs."""

from __future__ import annotations

import csv
import json
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
from demon_lab.pipeline import tracking
from demon_lab.pipeline.tracking import TAG, Tracker
from demon_lab.reporting import report

ROOT = Path(__file__).resolve().parents[1]


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


def _fake_store(tmp: Path) -> str:
    """Runs with known metrics, logged through demon_lab's tracking layer: 3 seeds of one row,
    2 of another, a FAILED run and an older duplicate that must be superseded."""
    uri = f"sqlite:///{tmp}/mlflow.db"
    tracker = Tracker(uri, "study", str(tmp / "artifacts"))

    def add(row: str, seed: int, value: float, status: str = "FINISHED", **versions):
        run = tracker.start(f"{row}-{seed}", {f"{TAG}run_key": f"{row}{seed}", f"{TAG}row": row,
                                              f"{TAG}seed": str(seed), **version_tags(**versions)})
        tracker.log_metrics(run, {"test/setA/it0/l1_inv": value, "test/setA/it0/tran_deg": 10 * value})
        if status == "FINISHED":
            tracker.finish(run, "FINISHED")
        else:
            tracker.fail(run, RuntimeError("NaN loss at step 7"))

    add("a", 0, 99.0)  # superseded by the newer seed-0 run below
    for seed, value in enumerate([1.0, 2.0, 3.0]):
        add("a", seed, value)
    for seed, value in enumerate([10.0, 14.0]):
        add("b", seed, value)
    add("b", 2, 0.0, status="FAILED")
    add("a", 2, 555.0, generator_version="3")  # newest, but of another scene generator: stale
    add("b", 2, 777.0, code_version=None)  # a run from before runs were tagged with versions: stale
    old = tracker.start("a-1-old", {f"{TAG}run_key": "a1-old", f"{TAG}row": "a", f"{TAG}seed": "1",
                                    **version_tags()})
    tracker.fail(old, RuntimeError("killed"))  # an attempt of row a, seed 1 under another run key...
    run = tracker.start("a-1-again", {f"{TAG}run_key": "a1-again", f"{TAG}row": "a", f"{TAG}seed": "1",
                                      **version_tags()})
    tracker.log_metrics(run, {"test/setA/it0/l1_inv": 2.0, "test/setA/it0/tran_deg": 20.0})
    tracker.finish(run, "FINISHED")  # ...superseded by this newer FINISHED run (same value as before)
    return uri


def version_tags(**changed: str | None) -> dict[str, str]:
    """This checkout's version tags, with some changed (None: left out)."""
    tags = {**tracking.version_tags(), **{f"{TAG}{k}": v for k, v in changed.items()}}
    return {k: v for k, v in tags.items() if v is not None}


def _spec(directory: Path, **extra) -> None:
    (directory / "paper_numbers.csv").write_text((report.STUDIES / "paper_numbers.csv").read_text())
    spec = {**extra, "title": "A study", "runs": [["+experiment=study"]], "seeds": [0, 1, 2],
            "datasets": {"setA": "SUN3D"},
            "tables": [{"name": "t", "caption": "cap", "experiment": "study", "columns": ["l1_inv", "tran_deg"],
                        "rows": [{"label": "row a", "match": {"row": "a"}, "metrics": "it0",
                                  "paper": {"table": "2", "method": "depth-motion net", "rows": ["no GT"]}},
                                 {"label": "row b", "match": {"row": "b"}, "metrics": "it0"}]}]}
    (directory / "study.yaml").write_text(yaml.safe_dump(spec))


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


def test_a_run_archive_carries_a_study_to_another_store_and_imports_once(tmp_path, capsys):
    """--export writes the study's ended runs (the unfinished one left out), their stage runs' full
    histories, their artifacts and the stage run of another experiment that a job read from the
    cache; --import into an empty store gives the same report, keeps times, histories and the
    parent of each stage run, and importing again adds nothing."""
    import json

    from mlflow.tracking import MlflowClient

    from demon_lab.reporting.archive import IMPORTED_FROM, PARENT

    uri = _fake_store(tmp_path)
    tracker = Tracker(uri, "study", str(tmp_path / "artifacts"))
    job = tracker.start("a-0-stages", {f"{TAG}run_key": "a0-stages", f"{TAG}row": "c", f"{TAG}seed": "0",
                                       **version_tags()})
    stage = tracker.start("flow1", {f"{TAG}kind": "stage", f"{TAG}stage": "flow1", f"{TAG}stage_key": "k1"},
                          parent_id=job)
    for step in range(3):
        tracker.log_metrics(stage, {"val/setA/epe": 1.0 / (step + 1)}, step=step)
    tracker.finish(stage, "FINISHED")
    other = Tracker(uri, "elsewhere", str(tmp_path / "artifacts"))
    trainer = other.start("b-0", {f"{TAG}seed": "0"})  # the job of another experiment that trained dm1
    cached = other.start("dm1", {f"{TAG}kind": "stage", f"{TAG}stage": "dm1", f"{TAG}stage_key": "k2"},
                         parent_id=trainer)
    tracker.log_metrics(cached, {"loss": 0.5})
    tracker.log_metrics(trainer, {"stage/dm1/keep_best_step": 250.0, "stage/dm1/seconds": 9.0,
                                  "stage/flow1/seconds": 3.0})
    tracker.finish(trainer, "FINISHED")
    tracker.finish(cached, "FINISHED")
    other.start("dm1", {f"{TAG}kind": "stage", f"{TAG}stage": "dm1", f"{TAG}stage_key": "k3"})  # not read by a job
    tracker.log_text(job, json.dumps({"flow1": {"key": "k1"}, "dm1": {"key": "k2"}}), "stage_keys.json")
    for name in ("images/panel.png", "point_clouds/cloud.ply", "report/study.md"):
        tracker.log_text(job, name, name)
    tracker.log_metrics(job, {"test/setA/it0/l1_inv": 5.0, "test/setA/it0/tran_deg": 50.0})
    tracker.finish(job, "FINISHED")
    tracker.start("running", {f"{TAG}run_key": "r", f"{TAG}row": "a", f"{TAG}seed": "0", **version_tags()})
    _spec(tmp_path)
    archive = tmp_path / "runs" / "study.zip"
    assert report.main(["study", "--studies", str(tmp_path), "--tracking-uri", uri, "--out",
                        str(tmp_path / "before"), "--export", str(archive)]) == 0
    assert f"{archive}: 14 runs of study" in capsys.readouterr().out  # 12 jobs, the stage, the cached stage
    import zipfile

    def files(path: Path) -> set[str]:
        names = zipfile.ZipFile(path).namelist()
        return {name.split("/", 2)[2] for name in names if name.startswith(f"artifacts/{job}/")}

    assert files(archive) == {"stage_keys.json", "images/panel.png"}
    lean = tmp_path / "runs" / "lean.zip"
    assert report.main(["study", "--studies", str(tmp_path), "--tracking-uri", uri, "--out", str(tmp_path / "lean"),
                        "--export", str(lean), "--without-images"]) == 0
    assert files(lean) == {"stage_keys.json"}

    copy = f"sqlite:///{tmp_path}/copy.db"
    argv = ["study", "--studies", str(tmp_path), "--tracking-uri", copy, "--artifact-dir", str(tmp_path / "copied"),
            "--import", str(archive), "--out", str(tmp_path / "after")]
    assert report.main(argv) == 0
    assert f"{archive}: 14 runs imported, 0 already in the store" in capsys.readouterr().out
    assert report.main(argv) == 0
    assert f"{archive}: 0 runs imported, 14 already in the store" in capsys.readouterr().out

    source, client = MlflowClient(tracking_uri=uri), MlflowClient(tracking_uri=copy)
    runs = {r.data.tags[IMPORTED_FROM]: r for e in client.search_experiments()
            for r in client.search_runs([e.experiment_id])}
    assert len(runs) == 14 and {job, stage, cached} <= set(runs)
    after = (tmp_path / "after" / "study.md").read_text()
    for old, new in runs.items():  # (the report names a FAILED run by its id in the store)
        after = after.replace(new.info.run_id, old)
    before = (tmp_path / "before" / "study.md").read_text()
    assert after == before and "- FAILED run" in before
    assert any(r[:3] == ["row a", "3", "2.000 ± 2.484"] for r in table_rows(before))
    assert runs[stage].data.tags[PARENT] == runs[job].info.run_id and PARENT not in runs[cached].data.tags
    # the cached stage's job stays out, and the stage run takes along what that job logged of it
    assert trainer not in runs and runs[cached].data.metrics == {"loss": 0.5, "stage/keep_best_step": 250.0,
                                                                 "stage/seconds": 9.0}
    assert "stage/seconds" not in runs[stage].data.metrics  # its job is in the archive
    assert client.get_experiment(runs[cached].info.experiment_id).name == "elsewhere"
    assert [(m.step, m.value) for m in client.get_metric_history(runs[stage].info.run_id, "val/setA/epe")] == [
        (0, 1.0), (1, 0.5), (2, 1.0 / 3)]
    for old, new in runs.items():
        was = source.get_run(old).info
        assert (new.info.status, new.info.start_time, new.info.end_time) == (was.status, was.start_time, was.end_time)
    keys = client.download_artifacts(runs[job].info.run_id, "stage_keys.json", str(tmp_path / "down"))
    assert json.loads(Path(keys).read_text())["dm1"] == {"key": "k2"}
    assert Path(runs[job].info.artifact_uri.removeprefix("file://")).is_relative_to(tmp_path / "copied")


def test_an_archive_that_went_round_two_stores_adds_nothing_and_a_late_parent_is_linked(tmp_path, capsys):
    """A store's runs exported to a second store and back add nothing to the first; a stage run
    exported while its job still ran arrives without a parent, and the import that later brings the
    finished job links them."""
    from mlflow.tracking import MlflowClient

    from demon_lab.reporting.archive import IMPORTED_FROM, PARENT, export_runs, import_runs

    first, second = f"sqlite:///{tmp_path}/a.db", f"sqlite:///{tmp_path}/b.db"
    tracker = Tracker(first, "study", str(tmp_path / "a"))
    done = tracker.start("a-0", {f"{TAG}run_key": "a0", f"{TAG}row": "a", f"{TAG}seed": "0", **version_tags()})
    tracker.finish(done, "FINISHED")
    job = tracker.start("b-0", {f"{TAG}run_key": "b0", f"{TAG}row": "b", f"{TAG}seed": "0", **version_tags()})
    stage = tracker.start("flow1", {f"{TAG}kind": "stage", f"{TAG}stage": "flow1"}, parent_id=job)
    tracker.finish(stage, "FINISHED")
    export_runs(first, ["study"], tmp_path / "early.zip")  # the job still runs: left out
    assert import_runs(second, tmp_path / "early.zip", tmp_path / "b") == (2, 0)
    back = tmp_path / "back.zip"
    export_runs(second, ["study"], back)
    assert import_runs(first, back, tmp_path / "a") == (0, 2)  # both are the first store's own runs

    client = MlflowClient(tracking_uri=second)
    runs = lambda: {r.data.tags[IMPORTED_FROM]: r for r in client.search_runs(  # noqa: E731
        [client.get_experiment_by_name("study").experiment_id])}
    assert PARENT not in runs()[stage].data.tags
    tracker.finish(job, "FINISHED")
    export_runs(first, ["study"], tmp_path / "late.zip")
    assert import_runs(second, tmp_path / "late.zip", tmp_path / "b") == (1, 2)
    linked = runs()
    assert linked[stage].data.tags[PARENT] == linked[job].info.run_id
    assert linked[job].data.tags[f"{TAG}run_key"] == "b0"


def test_a_single_jobs_study_rows_stand_beside_each_other_from_the_store(tmp_path):
    """study_rows: the study's table of one experiment, as a single job prints it after its own
    result: each row's n and mean ± half-width on the spec's first test set with values."""
    uri = _fake_store(tmp_path)
    _spec(tmp_path)
    text = report.study_rows("study", uri, "study", tmp_path)
    lines = text.splitlines()
    assert lines[0] == "study / t on setA (python -m demon_lab.report study):"
    assert lines[1].split() == ["row", "n", "L1-inv", "tran"]
    assert lines[3].split() == ["row", "a", "3", "2.000", "±", "2.484", "20.000", "±", "24.841"]
    assert lines[4].split() == ["row", "b", "2", "12.000", "±", "25.412", "120.000", "±", "254.124"]
    assert report.study_rows("study", uri, "another", tmp_path) is None


def test_any_experiment_is_reported_without_a_spec_grouped_by_what_differs(tmp_path):
    """--experiment NAME: the FINISHED runs of this checkout's versions, grouped by the result-changing
    params that differ (the seed aggregated, the thread count and stale runs left out), each row
    reading its runs' own last pass."""
    from demon_lab.pipeline.tracking import Tracker

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    tracker = Tracker(uri, "default", str(tmp_path / "artifacts"))
    for iterations, seed, value, versions in ((0, 0, 1.0, {}), (0, 1, 3.0, {}), (2, 0, 5.0, {}),
                                              (2, 1, 50.0, {"generator_version": "3"})):
        run = tracker.start("job", {f"{TAG}run_key": f"{iterations}{seed}", f"{TAG}seed": str(seed),
                                    f"{TAG}iterations": str(iterations), f"{TAG}method": "demon",
                                    **version_tags(**versions)})
        tracker.log_params(run, {"iterations": str(iterations), "seed": str(seed), "threads": str(seed + 1),
                                 "model.width": "0.25", "method": "demon"})
        tracker.log_metrics(run, {f"test/setA/it{iterations}/epe": value, "test/setA/it1/epe": 100.0})
        tracker.finish(run, "FINISHED")
    assert report.main(["--experiment", "default", "--tracking-uri", uri, "--out", str(tmp_path / "out")]) == 0
    with open(tmp_path / "out" / "experiment_default.csv", newline="") as f:
        cells = {r["row"]: r for r in csv.DictReader(f) if r["metric"] == "epe"}
    assert set(cells) == {"iterations=0", "iterations=2"}
    assert float(cells["iterations=0"]["mean"]) == 2.0 and cells["iterations=0"]["n"] == "2"
    assert float(cells["iterations=2"]["mean"]) == 5.0 and cells["iterations=2"]["n"] == "1"
    md = (tmp_path / "out" / "experiment_default.md").read_text()
    assert "Generated by `python -m demon_lab.report --experiment default`" in md
    assert report.main(["--experiment", "none", "--tracking-uri", uri, "--out", str(tmp_path / "out")]) == 2


def test_a_design_is_named_by_its_departures_from_demons():
    """The shipped designs by name where a run's departures are exactly theirs; others by the nearest
    with what differs; options at their defaults are no departure."""
    from demon_lab.reporting import provenance

    profile, learned = provenance.named_designs()["the cpu profile"], provenance.named_designs()["the learned design"]
    assert profile == {"model.dm1_prior": "ransac_prior", "model.dm2_prior": "previous",
                       "model.flow1_prior": "dis_x2", "model.flow2_prior": "previous"}
    assert learned["model.correlation"] == "[8, 2]" and "model.flow1_prior" not in learned
    assert learned["schedule.stages.flow1.fresh_scenes"] == "0.02"
    assert provenance.design_name(provenance.departures({"model.flow1_prior": "None", "seed": "1"})) == "DeMoN's design"
    assert provenance.design_name(profile) == "the cpu profile"
    assert provenance.design_name(learned) == "the learned design"
    fewer = {k: v for k, v in learned.items() if "fresh_scenes" not in k}
    assert provenance.design_name(provenance.departures({**fewer, "schedule.stages.dm1.fresh_scenes": "0"})) == (
        "the learned design without schedule.stages.dm1.fresh_scenes, schedule.stages.flow1.fresh_scenes")
    assert provenance.design_name({"model.correlation": "[8, 2]"}) == "DeMoN's design with model.correlation=[8, 2]"


def test_every_report_names_each_rows_design_code_and_runs_and_refuses_a_row_of_two_designs(tmp_path):
    """The md's header and Provenance section, the csv's columns and the tex's comments name each
    row's design, config digest and run ids; a row whose seeds ran different designs is refused in
    one line naming them."""
    from demon_lab.pipeline.tracking import Tracker

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    tracker = Tracker(uri, "study", str(tmp_path / "artifacts"))
    ids = {}
    for row, seed, prior in (("a", 0, "None"), ("a", 1, "None"), ("b", 0, "dis_x2"), ("b", 1, "dis_x2")):
        run = tracker.start(f"{row}{seed}", {f"{TAG}run_key": f"{row}{seed}", f"{TAG}row": row,
                                             f"{TAG}seed": str(seed), **version_tags()})
        tracker.log_params(run, {"seed": str(seed), "model.flow1_prior": prior, "model.width": "0.25"})
        tracker.log_metrics(run, {"test/setA/it0/l1_inv": 1.0 + seed, "test/setA/it0/tran_deg": 5.0})
        tracker.finish(run, "FINISHED")
        ids[(row, seed)] = run
    _spec(tmp_path)
    paths = report.report("study", uri, tmp_path / "reports", tmp_path)
    md = paths["md"].read_text()
    assert "- design: DeMoN's design; DeMoN's design with model.flow1_prior=dis_x2" in md
    line = next(r for r in table_rows(md) if r[:2] == ["t", "row a"])  # the provenance table's
    assert line[2] == "DeMoN's design" and line[4] == "0, 1" and line[5] == f"{ids[('a', 0)]} {ids[('a', 1)]}"
    with open(paths["csv"], newline="") as f:
        b = next(r for r in csv.DictReader(f) if r["row"] == "row b")
    assert b["design"] == "DeMoN's design with model.flow1_prior=dis_x2" and ids[("b", 1)] in b["run_ids"]
    assert "% t / row b: DeMoN's design with model.flow1_prior=dis_x2" in paths["tex"].read_text()
    mixed = tracker.start("a2", {f"{TAG}run_key": "a2", f"{TAG}row": "a", f"{TAG}seed": "2", **version_tags()})
    tracker.log_params(mixed, {"seed": "2", "model.flow1_prior": "dis", "model.width": "0.25"})
    tracker.finish(mixed, "FINISHED")
    with pytest.raises(report.ReportError, match="row 'row a' has runs of different designs") as e:
        report.report("study", uri, tmp_path / "reports", tmp_path)
    assert "DeMoN's design (seed 0, 1); DeMoN's design with model.flow1_prior=dis (seed 2)" in str(e.value)


@pytest.mark.slow
def test_a_committed_report_redraws_from_its_committed_archive_cell_by_cell(tmp_path):
    """On a fresh store, ``--import`` of the committed run archive and the report command give the
    committed report's CSV again, cell by cell (means, intervals, per-seed values, designs, run ids),
    and its Markdown tables (the loss-weight study; its archive also holds cpu_departures')."""
    study = "loss_weights"
    root = Path(__file__).resolve().parents[1] / "reports"
    archive = root / "runs" / "loss_weights_cpu_departures.zip"
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    out = tmp_path / "reports"
    (out / "runs").mkdir(parents=True)
    (out / "runs" / archive.name).symlink_to(archive)
    assert report.main(["--import", str(archive), "--tracking-uri", uri, "--artifact-dir", str(tmp_path / "art"),
                        "--out", str(out), study]) == 0
    with open(root / f"{study}.csv", newline="") as f:
        committed = list(csv.DictReader(f))
    with open(out / f"{study}.csv", newline="") as f:
        redrawn = list(csv.DictReader(f))
    assert len(redrawn) == len(committed) > 0
    for mine, theirs in zip(redrawn, committed, strict=True):
        assert mine == theirs
    tables = lambda text: [line for line in text.splitlines() if line.startswith("|")]  # noqa: E731
    assert tables((out / f"{study}.md").read_text()) == tables((root / f"{study}.md").read_text())


def test_a_difference_row_is_the_paired_per_seed_difference_with_its_interval(tmp_path):
    """A table's ``differences`` row: per seed both rows have, row a minus row b, aggregated like a
    row (row a: 1, 2, 3 at seeds 0-2; row b: 10, 14 at seeds 0-1 -> -9, -12: n = 2); a difference
    naming a row the table lacks is refused when the spec loads."""
    uri = _fake_store(tmp_path)
    _spec(tmp_path)
    spec = yaml.safe_load((tmp_path / "study.yaml").read_text())
    spec["tables"][0]["differences"] = [{"label": "a minus b", "rows": ["row a", "row b"]}]
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(spec))
    paths = report.report("study", uri, tmp_path / "reports", tmp_path)
    with open(paths["csv"], newline="") as f:
        cell = next(r for r in csv.DictReader(f) if r["row"] == "a minus b" and r["metric"] == "l1_inv")
    assert float(cell["mean"]) == -10.5 and cell["n"] == "2" and cell["values"] == "-9 -12"
    assert float(cell["ci95"]) == pytest.approx(12.706205 * 3 / math.sqrt(2) / math.sqrt(2), rel=1e-6)
    assert any(r[:3] == ["*a minus b*", "2", "-10.500 ± 19.059"] for r in table_rows(paths["md"].read_text()))
    spec["tables"][0]["differences"] = [{"label": "x", "rows": ["row a", "row z"]}]
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(spec))
    with pytest.raises(report.ReportError, match="difference 'x': expected rows: \\[A, B\\]"):
        report.report("study", uri, tmp_path / "reports", tmp_path)


def test_a_spec_of_one_design_extends_another_and_counts_only_runs_of_its_design(tmp_path):
    """``design: learned`` adds ``design=learned`` to the spec's commands and counts only runs whose
    departures are the learned design's (the profile's runs of the same experiment and rows are
    passed over, not mixed in); ``extends`` inherits a spec and ``drop_rows`` leaves rows out with the
    differences that read them; the profile's spec counts the profile's runs only."""
    from demon_lab.pipeline.tracking import Tracker
    from demon_lab.reporting import provenance

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    tracker = Tracker(uri, "study", str(tmp_path / "artifacts"))
    designs = {"profile": provenance.named_designs()["the cpu profile"],
               "learned": provenance.named_designs()["the learned design"]}
    for design, base in (("profile", 1.0), ("learned", 100.0)):
        for row in ("a", "b"):
            for seed in range(3):
                run = tracker.start(f"{design}{row}{seed}", {f"{TAG}run_key": f"{design}{row}{seed}", f"{TAG}row": row,
                                                             f"{TAG}seed": str(seed), **version_tags()})
                tracker.log_params(run, {"seed": str(seed), **designs[design]})
                tracker.log_metrics(run, {"test/setA/it0/l1_inv": base + seed + (row == "b"),
                                          "test/setA/it0/tran_deg": 1.0})
                tracker.finish(run, "FINISHED")
    for seed in range(3):  # a classical method's runs (the learned design's params, as its sweep logs them)
        run = tracker.start(f"c{seed}", {f"{TAG}run_key": f"c{seed}", f"{TAG}row": "c", f"{TAG}seed": str(seed),
                                         **version_tags()})
        tracker.log_params(run, {"seed": str(seed), "method": "base_ff", **designs["learned"]})
        tracker.log_metrics(run, {"test/setA/it0/l1_inv": 50.0, "test/setA/it0/tran_deg": 1.0})
        tracker.finish(run, "FINISHED")
    _spec(tmp_path, design="profile")
    spec = yaml.safe_load((tmp_path / "study.yaml").read_text())
    spec["tables"][0]["rows"].append({"label": "row c", "match": {"row": "c"}, "metrics": "it0"})
    spec["tables"][0]["differences"] = [{"label": "a minus b", "rows": ["row a", "row b"]}]
    (tmp_path / "study.yaml").write_text(yaml.safe_dump(spec))
    (tmp_path / "study_learned.yaml").write_text(yaml.safe_dump(
        {"extends": "study", "title": "The study, learned", "design": "learned", "drop_rows": ["row b"]}))
    learned = report.load_spec("study_learned", tmp_path)
    assert learned["runs"] == [["+experiment=study", "design=learned"]] and learned["datasets"] == {"setA": "SUN3D"}
    assert [r["label"] for r in learned["tables"][0]["rows"]] == ["row a", "row c"]
    assert learned["tables"][0]["differences"] == []
    assert report.load_spec("study", tmp_path)["runs"] == [["+experiment=study"]]

    def means(name: str) -> dict[str, float]:
        paths = report.report(name, uri, tmp_path / "reports", tmp_path)
        with open(paths["csv"], newline="") as f:
            return {r["row"]: float(r["mean"]) for r in csv.DictReader(f) if r["metric"] == "l1_inv"}

    assert means("study") == {"row a": 2.0, "row b": 3.0, "row c": 50.0, "a minus b": -1.0}
    assert means("study_learned") == {"row a": 101.0, "row c": 50.0}  # a classical method measures no design
    md = (tmp_path / "reports" / "study_learned.md").read_text()
    assert "- design: the learned design; no net (a classical method) (" in md
    assert report.study_of("study", tmp_path, design="learned") == "study_learned"
    # a scale's own design is the profile's spec's: DeMoN's design at the smoke and paper scales
    assert provenance.shipped({}) == "profile" and provenance.shipped(designs["learned"]) == "learned"
    assert report.study_of("study", tmp_path, design="profile") == report.study_of("study", tmp_path) == "study"
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"extends": "study", "design": "fast"}))
    with pytest.raises(report.ReportError, match="design: expected one of \\['learned', 'profile'\\], got 'fast'"):
        report.load_spec("bad", tmp_path)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"extends": "study", "drop_rows": ["row z"]}))
    with pytest.raises(report.ReportError, match="drop_rows: \\['row z'\\] are rows of no table of study"):
        report.load_spec("bad", tmp_path)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"extends": "study", "curves": ["nope"]}))
    with pytest.raises(report.ReportError, match=r"curves: expected a list of the spec's table names .*\['nope'\]"):
        report.load_spec("bad", tmp_path)


def test_a_report_names_the_run_archives_that_hold_its_experiments(tmp_path):
    """The Provenance section links each archive beside the report that holds job runs of the spec's
    experiments (an archive's comment names them; an archive of another study is not named)."""
    import zipfile

    from demon_lab.reporting.archive import archived_experiments

    uri = _fake_store(tmp_path)
    _spec(tmp_path)
    runs = tmp_path / "reports" / "runs"
    runs.mkdir(parents=True)
    for name, experiments in (("mine.zip", "study other"), ("theirs.zip", "other")):
        with zipfile.ZipFile(runs / name, "w") as archive:
            archive.comment = experiments.encode()
            archive.writestr("runs.json", "[]\n")
    with zipfile.ZipFile(runs / "old.zip", "w") as archive:  # an archive without the comment: its runs say
        archive.writestr("runs.json", json.dumps([
            {"experiment": "study", "tags": {}}, {"experiment": "elsewhere", "tags": {f"{TAG}kind": "stage"}}]))
    assert archived_experiments(runs / "old.zip") == {"study"}
    md = report.report("study", uri, tmp_path / "reports", tmp_path)["md"].read_text()
    assert "the run archive(s) [runs/mine.zip](runs/mine.zip), [runs/old.zip](runs/old.zip) beside" in md
    assert "theirs.zip" not in md


class _Metric:
    def __init__(self, timestamp, step, value):
        self.timestamp, self.step, self.value = timestamp, step, value


class _Run:
    def __init__(self, run_id, start_minute, metrics=None, tags=None, status="FINISHED", experiment="e"):
        from types import SimpleNamespace

        self.info = SimpleNamespace(run_id=run_id, start_time=start_minute * 60000, status=status,
                                    experiment_id=experiment)
        self.data = SimpleNamespace(metrics=metrics or {}, tags=tags or {})


class _Client:
    """The calls of MlflowClient the held-apart curves make, over in-memory runs (histories in minutes)."""

    def __init__(self, histories, runs=()):
        self.histories, self.runs = histories, {r.info.run_id: r for r in runs}

    def get_metric_history(self, run_id, key):
        return [_Metric(t * 60000, s, v) for t, s, v in self.histories.get((run_id, key), [])]

    def get_run(self, run_id):
        from mlflow.exceptions import MlflowException

        if run_id not in self.runs:
            raise MlflowException(f"Run '{run_id}' not found")
        return self.runs[run_id]

    def search_experiments(self):
        from types import SimpleNamespace

        return [SimpleNamespace(experiment_id=e) for e in sorted({r.info.experiment_id for r in self.runs.values()})]

    def search_runs(self, experiments, filter_string, order_by=None):
        import re

        wanted = dict(re.findall(r"tags\.`([^`]+)` = '([^']*)'", filter_string))
        found = [r for r in self.runs.values() if r.info.experiment_id in experiments
                 and all(r.data.tags.get(k) == v for k, v in wanted.items())]
        return sorted(found, key=lambda r: r.info.start_time)


def test_a_resumed_stages_curve_joins_its_runs_and_a_retrained_one_starts_again():
    """A stage stopped at step 300 and resumed from its step-200 checkpoint in a new run: the resumed
    run's points follow the first run's last point before step 250 (its first), the steps trained again
    and the pause between the runs not counted; a run that starts at the first step again replaces them."""
    from demon_lab.reporting.figures import _joined_curve

    first, resumed = _Run("a", 0), _Run("b", 100)  # the second run starts 100 minutes later
    key, zero = "val/s/epe", "val/s/zero_flow_epe"
    client = _Client({("a", key): [(1, 100, 0.9), (2, 200, 0.8), (3, 300, 0.7)], ("a", zero): [(1, 100, 2.0)],
                      ("b", key): [(101, 250, 0.6), (102, 350, 0.5)], ("b", zero): [(101, 250, 2.0)]})
    curve = _joined_curve(client, [first, resumed], key, zero)
    assert curve["steps"] == [100, 200, 250, 350]
    assert curve["values"] == pytest.approx([0.45, 0.4, 0.3, 0.25])
    assert curve["minutes"] == pytest.approx([1, 2, 3, 4])
    assert curve["runs"] == [first, resumed]
    again = _Run("c", 200)
    client.histories[("c", key)] = [(201, 100, 0.95)]
    client.histories[("c", zero)] = [(201, 100, 1.0)]
    assert _joined_curve(client, [first, resumed, again], key, zero) == {
        "minutes": [pytest.approx(1.0)], "steps": [100], "values": [pytest.approx(0.95)], "runs": [again]}
    empty = _Run("d", 300)  # a run that logged no point (stopped before its first scoring) adds nothing
    assert _joined_curve(client, [first, resumed, empty], key, zero)["runs"] == [first, resumed]
    assert _joined_curve(client, [first], "val/s/tran_deg", None) is None


def test_a_stage_resumed_in_its_own_run_is_cut_where_its_steps_start_again():
    """A job stopped unawares and run again resumes its stage's own run: the run's history logs steps
    250 and 300 again. The curve drops the first process's points from step 250 on, and the second
    process's minutes start where its training loss starts again (minute 50), not at the run's start."""
    from demon_lab.reporting.figures import _joined_curve

    run = _Run("a", 0)
    key = "val/s/tran_deg"
    client = _Client({("a", key): [(1, 100, 90.0), (2, 200, 80.0), (3, 300, 75.0), (52, 250, 70.0), (53, 350, 60.0)],
                      ("a", "train/loss"): [(0.5, 50, 1.0), (2.5, 250, 0.8), (50, 200, 0.9), (52.5, 300, 0.7)]})
    curve = _joined_curve(client, [run], key, None)
    assert curve["steps"] == [100, 200, 250, 350]
    assert curve["values"] == [90.0, 80.0, 70.0, 60.0]
    assert curve["minutes"] == pytest.approx([1, 2, 4, 5])  # 2 + (52 - 50), 2 + (53 - 50)


def test_a_jobs_stage_runs_are_those_of_its_stage_before_it_read_the_stage(tmp_path, monkeypatch):
    """The runs of a job's stage key: up to its own child run (an earlier stopped run of the same key
    included), or, for a stage found in the cache, those started before the job; a run of the key
    trained again later for another job, and a RUNNING one (stopped unawares), are left out."""
    from demon_lab.reporting import figures

    def stage(run_id, minute, parent, status="FINISHED"):
        return _Run(run_id, minute, tags={"demon_lab.stage": "flow1", "demon_lab.stage_key": "k",
                                          "mlflow.parentRunId": parent}, status=status)

    stopped, own, running, later = (stage("s0", 0, "j0", "FAILED"), stage("s1", 10, "j1"),
                                    stage("s3", 5, "j5", "RUNNING"), stage("s2", 90, "j9"))
    client = _Client({}, [stopped, own, running, later])
    assert figures.stage_runs(client, {"run_id": "j1", "experiment_id": "e"}) == [stopped, own]
    (tmp_path / "stage_keys.json").write_text(json.dumps({"flow1": {"key": "k"}}))  # a job that found it cached
    monkeypatch.setattr(figures, "local_artifact", lambda run, path: tmp_path / path)
    cached = {"run_id": "j2", "experiment_id": "e", "start_time": 50 * 60000}
    assert figures.stage_runs(client, cached) == [stopped, own]
    assert figures.stage_runs(client, {**cached, "start_time": None}) == [stopped, own, later]  # (no start known)


def test_the_kept_nets_are_read_from_the_stage_run_else_from_the_job_that_trained_it():
    from demon_lab.reporting.figures import _kept

    tags = {"demon_lab.stage": "dm1", "mlflow.parentRunId": "job"}
    client = _Client({}, [_Run("job", 0, {"stage/dm1/keep_best_step": 2250.0})])
    assert _kept(client, _Run("s", 0, {"stage/seconds": 9.0, "stage/keep_best_step": 3500.0}, tags)) == "step 3,500"
    assert _kept(client, _Run("s", 0, {"stage/seconds": 9.0}, tags)) == "last"
    assert _kept(client, _Run("s", 0, {}, tags)) == "step 2,250"  # a stage run logged before it carried its figures
    client.runs["job"] = _Run("job", 0, {}, status="FINISHED")
    assert _kept(client, _Run("s", 0, {}, tags)) == "last"
    client.runs["job"] = _Run("job", 0, {}, status="FAILED")
    assert _kept(client, _Run("s", 0, {}, tags)) == "not logged"
    del client.runs["job"]  # (removed from the store)
    assert _kept(client, _Run("s", 0, {}, tags)) == "not logged"
