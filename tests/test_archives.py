"""Run archives: a study carried to another store and imported once, idempotent round trips, and the
committed reports redrawn from their committed archives."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from conftest import table_rows

from demon_lab.pipeline.tracking import TAG, Tracker
from demon_lab.reporting import report
from tests.report_helpers import _fake_store, _spec, version_tags


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
