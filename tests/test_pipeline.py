"""The main command end to end at the smoke scale, into a temporary MLflow store: the run it records, its
stages' curves and cache, a second invocation skipped, a failed job; a sweep's compositions and parent run."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from demon_lab import resources
from demon_lab.pipeline.identity import run_key
from tests.jobs import cli, client, compose_config, settings, smoke_overrides


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    from demon_lab.app.job import run
    from demon_lab.pipeline.settings import JobSettings

    tmp = tmp_path_factory.mktemp("smoke")
    threads = torch.get_num_threads()
    environment = os.environ.get("MLFLOW_TRACKING_URI")
    built, of = [], JobSettings.of.__func__
    JobSettings.of = classmethod(lambda cls, cfg: built.append(1) or of(cls, cfg))
    try:
        result = run(compose_config(smoke_overrides(tmp, "threads=1")))
    finally:
        torch.set_num_threads(threads)
        JobSettings.of = classmethod(of)
    # the settings are read once, by the job, and handed down to training, the keys and the evaluation
    assert len(built) == 1
    # the stage loggers set MLflow's tracking URI process-wide (and export it): the job puts it back,
    # or every process started later would log to this job's store
    assert os.environ.get("MLFLOW_TRACKING_URI") == environment
    return tmp, result


def test_smoke_pipeline_records_a_finished_run(smoke_run):
    tmp, result = smoke_run
    assert result["status"] == "finished"
    c = client(tmp)
    run = c.get_run(result["run_id"])
    assert run.info.status == "FINISHED"
    tags = run.data.tags
    assert tags["demon_lab.run_key"] == result["run_key"] and tags["demon_lab.scale"] == "smoke"
    assert tags["demon_lab.seed"] == "0" and "demon_lab.torch" in tags
    # the tests run from a checkout: the run names its commit, wherever the test process started
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(resources.PACKAGE).parent, capture_output=True,
                          text=True, check=True).stdout.strip()
    assert tags["mlflow.source.name"] and tags["mlflow.source.git.commit"] == head
    assert tags["demon_lab.git_dirty"] in ("true", "false")
    # threads=1 took effect, and the run key holds it: the nets computed with 1 thread, not the 2 keys leave out
    assert tags["demon_lab.cpu_threads"] == "1" and run.data.params["threads"] == "1"
    assert result["run_key"] == run_key(settings(compose_config(smoke_overrides(tmp, "threads=1"))))
    assert result["run_key"] != run_key(settings(compose_config(smoke_overrides(tmp, "threads=2"))))
    assert run.data.params["model.width"] == "0.0625" and run.data.params["iterations"] == "3"
    m = run.data.metrics
    for name in ("synthetic_scenes11", "synthetic_sun3d", "synthetic_mvs", "middlebury"):
        for metric in ("l1_inv", "sc_inv", "l1_rel", "rot_deg", "tran_deg"):
            assert f"test/{name}/{metric}" in m
            assert f"test/{name}/refined/{metric}" in m
            for k in range(4):
                assert f"test/{name}/it{k}/{metric}" in m
        assert f"test/{name}/it3/delta_1.25_2" in m
    # the summary metric is the refined depth and the last iteration's motion
    summary = result["summary"]["synthetic_sun3d"]
    assert m["test/synthetic_sun3d/l1_rel"] == pytest.approx(summary["refined/l1_rel"])
    assert m["test/synthetic_sun3d/rot_deg"] == pytest.approx(summary["it3/rot_deg"])
    artifacts = {a.path for a in c.list_artifacts(result["run_id"])}
    assert {"config.yaml", "per_sample_metrics.csv", "stage_keys.json", "results.txt", "images",
            "point_clouds"} <= artifacts
    assert any(a.path.endswith(".ply") for a in c.list_artifacts(result["run_id"], "point_clouds"))
    assert any(a.path.endswith(".png") for a in c.list_artifacts(result["run_id"], "images"))
    config_text = Path(c.download_artifacts(result["run_id"], "config.yaml")).read_text()
    assert "width: 0.0625" in config_text and "${" not in config_text  # resolved


def test_stage_runs_record_their_loss_curves(smoke_run):
    tmp, result = smoke_run
    c = client(tmp)
    children = c.search_runs([c.get_run(result["run_id"]).info.experiment_id],
                             filter_string=f"tags.`mlflow.parentRunId` = '{result['run_id']}'")
    stages = {r.data.tags["demon_lab.stage"]: r for r in children}
    assert set(stages) == {"flow1", "dm1", "flow2", "dm2", "iterative", "refine"}
    for name, r in stages.items():
        assert r.info.status == "FINISHED"
        history = c.get_metric_history(r.info.run_id, "train/loss")
        assert len(history) >= 1 and all(h.value == h.value for h in history), name
    assert "train/flow2_sig" in stages["flow1"].data.metrics and "train/rotation" in stages["dm1"].data.metrics
    # held-apart curves (data.val: the synthetic_sun3d validation scenes), at every step at this scale
    val = "val/synthetic_sun3d"
    assert [h.step for h in c.get_metric_history(stages["flow1"].info.run_id, f"{val}/epe")] == [1, 2]
    flow1 = stages["flow1"].data.metrics
    assert f"{val}/zero_flow_epe" in flow1 and f"{val}/rot_deg" not in flow1
    for name in ("dm1", "dm2", "iterative"):
        assert {f"{val}/{k}" for k in ("epe", "rot_deg", "tran_deg", "l1_inv")} <= set(stages[name].data.metrics), name
    assert f"{val}/l1_inv" in stages["refine"].data.metrics
    # each stage run carries its stage's figures too (a job stopped later still leaves them)
    job_metrics = c.get_run(result["run_id"]).data.metrics
    for name, stage in stages.items():
        assert stage.data.metrics["stage/seconds"] == job_metrics[f"stage/{name}/seconds"], name


def test_time_to_accuracy_figure_reads_the_flow1_stage_of_each_counted_run(smoke_run, tmp_path, monkeypatch):
    """The figure plots each counted run's flow1 held-apart curve (EPE / zero-flow EPE), and its dm1
    translation curve, against the minutes since each stage run started: the values and times of the
    stage runs' metric histories; a run
    whose flow1 came from the cache is found through its stage key; rows reading the same flow1 stages
    share one line, labelled with both; the spec's ``curves`` names the tables whose rows it draws."""
    import shutil

    from demon_lab.reporting import figures, report

    tmp, result = smoke_run
    uri = f"sqlite:///{tmp}/mlflow.db"
    shutil.copy(resources.STUDIES / "paper_numbers.csv", tmp_path / "paper_numbers.csv")
    spec = {"title": "t", "runs": [], "seeds": [0], "datasets": {"synthetic_sun3d": None},
            "figures": ["time_to_accuracy"],
            "tables": [{"name": "flow1", "caption": "c", "experiment": "default", "columns": ["epe"],
                        "rows": [{"label": "smoke", "match": {}, "metrics": "it0"},
                                 {"label": "twin", "match": {}, "metrics": "it0"}]},
                       {"name": "other", "caption": "d", "experiment": "default", "columns": ["epe"],
                        "rows": [{"label": "third", "match": {}, "metrics": "it1"}]},
                       {"name": "left", "caption": "e", "experiment": "default", "columns": ["epe"],
                        "rows": [{"label": "not drawn", "match": {}, "metrics": "it0"}]}],
            "curves": ["flow1", "other"]}
    (tmp_path / "tta.yaml").write_text(yaml.safe_dump(spec))
    drawn = []
    import matplotlib.axes

    original = matplotlib.axes.Axes.plot

    def plot(self, *args, **kwargs):
        if kwargs.get("label"):
            drawn.append((kwargs["label"], list(args[0]), list(args[1])))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", plot)
    paths = report.report("tta", uri, tmp_path / "out", tmp_path)
    assert (tmp_path / "out" / "figures" / "tta_time_to_accuracy.png") in paths.values()
    (label, minutes, ratios), (dm1_label, dm1_minutes, translations) = drawn  # flow1's panel, then dm1's
    assert label == dm1_label == "smoke; twin; third"  # the curves tables' rows, not the third table's
    c = client(tmp)
    job = c.get_run(result["run_id"])
    counted = {"run_id": job.info.run_id, "experiment_id": job.info.experiment_id}
    stage, = figures.stage_runs(c, counted)
    history = sorted((m.timestamp, m.value) for m in c.get_metric_history(stage.info.run_id,
                                                                          "val/synthetic_sun3d/epe"))
    zero = c.get_metric_history(stage.info.run_id, "val/synthetic_sun3d/zero_flow_epe")[0].value
    assert ratios == pytest.approx([v / zero for _, v in history])
    assert minutes == pytest.approx([(t - stage.info.start_time) / 60000 for t, _ in history])
    assert all(m >= 0 for m in minutes)
    dm1, = figures.stage_runs(c, counted, "dm1")
    dm1_history = sorted((m.timestamp, m.value) for m in c.get_metric_history(dm1.info.run_id,
                                                                              "val/synthetic_sun3d/tran_deg"))
    assert translations == pytest.approx([v for _, v in dm1_history])
    assert dm1_minutes == pytest.approx([(t - dm1.info.start_time) / 60000 for t, _ in dm1_history])
    cached = {"run_id": "a-job-that-found-flow1-in-the-cache", "experiment_id": job.info.experiment_id,
              "artifact_uri": job.info.artifact_uri}
    assert [r.info.run_id for r in figures.stage_runs(c, cached)] == [stage.info.run_id]
    # the report's table of the curves' end points: each seed's first, last and best point, the kept step
    ends = paths["md"].read_text().split("beside whatever else shared the machine:")[1].split("\n\n")[1]
    cells = {line.split("|")[1].strip(): [x.strip() for x in line.strip().strip("|").split("|")]
             for line in ends.splitlines()[2:]}
    steps = [m.step for m in sorted(c.get_metric_history(stage.info.run_id, "val/synthetic_sun3d/epe"),
                                    key=lambda m: m.timestamp)]
    best = min(range(len(ratios)), key=ratios.__getitem__)
    assert cells["flow1"][2:4] == ["smoke; twin; third", "0"]
    assert cells["flow1"][4] == f"{ratios[0]:.3f} (step {steps[0]:,}, {minutes[0]:.1f} min)"
    assert cells["flow1"][5] == f"{ratios[-1]:.3f} (step {steps[-1]:,}, {minutes[-1]:.1f} min)"
    assert cells["flow1"][6] == f"{ratios[best]:.3f} (step {steps[best]:,}, {minutes[best]:.1f} min)"
    assert cells["flow1"][7] == "last"  # the smoke scale keeps each stage's last nets
    assert cells["dm1"][5].startswith(f"{translations[-1]:.3f} (step ")


def test_per_sample_metrics_table_matches_the_logged_means(smoke_run):
    import csv
    import io

    tmp, result = smoke_run
    c = client(tmp)
    rows = list(csv.DictReader(io.StringIO(Path(c.download_artifacts(result["run_id"], "per_sample_metrics.csv"))
                                           .read_text())))
    mine = [float(r["l1_rel"]) for r in rows if r["dataset"] == "synthetic_mvs" and r["it"] == "2"]
    assert len(mine) == 2
    logged = c.get_run(result["run_id"]).data.metrics["test/synthetic_mvs/it2/l1_rel"]
    assert logged == pytest.approx(sum(mine) / len(mine))


def test_second_identical_invocation_is_skipped_and_stages_are_cached(smoke_run):
    from demon_lab.app.job import run

    tmp, result = smoke_run
    threads = torch.get_num_threads()
    try:  # (the smoke run's thread count, which its keys hold)
        again = run(compose_config(smoke_overrides(tmp, "threads=1")))
        assert again == {"status": "skipped", "run_id": result["run_id"], "run_key": result["run_key"]}
        # another evaluation-time setting is a new run but trains nothing: all stages come from the cache
        other = run(compose_config(smoke_overrides(tmp, "threads=1", "iterations=1")))
        assert other["status"] == "finished" and other["run_key"] != result["run_key"]
        assert all(f == {"cached": 1.0} for f in other["figures"].values())
        forced = run(compose_config(smoke_overrides(tmp, "threads=1", "force=true")))
    finally:
        torch.set_num_threads(threads)
    assert forced["status"] == "finished" and forced["run_id"] != result["run_id"]


def test_diagnosis_reads_the_cached_chain_and_needs_it(smoke_run, tmp_path, capsys):
    """``python -m demon_lab.diagnose`` on the smoke run's stage cache: every test set, passes
    0..iterations; on an empty cache it names the missing stages and exits 2 (trains nothing)."""
    import json

    from demon_lab.tools.diagnose import main

    tmp, _ = smoke_run
    out = tmp_path / "diag.json"
    threads = torch.get_num_threads()
    try:  # (the smoke run's thread count, which its stage keys hold)
        assert main([*smoke_overrides(tmp, "threads=1"), "iterations=2", "--out", str(out)]) == 0
    finally:
        torch.set_num_threads(threads)
    passes = json.loads(out.read_text())["passes"]
    assert set(passes) >= {"synthetic_scenes11", "synthetic_sun3d", "synthetic_mvs", "middlebury"}
    for rows in passes.values():  # passes 0, 1, 2 and the refined depth
        assert [r["pass"] for r in rows] == [0, 1, 2, "refined"] and rows[0]["pairs"] >= 1
        assert all(math.isfinite(r["epe"]) for r in rows[:3]) and math.isnan(rows[3]["epe"])
        assert all(0 <= r["nonpositive_depth"] <= 1 for r in rows)
        assert math.isnan(rows[0]["prior"]) and math.isfinite(rows[1]["prior"])
    assert "inv<=0" in capsys.readouterr().out
    empty = [*smoke_overrides(tmp_path), "iterations=2"]
    assert main(empty) == 2
    assert "stages not in the cache: flow1, dm1, flow2, dm2, iterative" in capsys.readouterr().err
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("weights.pt"))
    assert main([*smoke_overrides(tmp), "bogus=1"]) == 2
    assert "bogus" in capsys.readouterr().err


@pytest.mark.slow
def test_a_job_that_raises_leaves_its_run_failed(tmp_path):
    from demon_lab.app.job import run
    from demon_lab.data.sample import DataError

    unreadable = tmp_path / "not_a_pair"  # exists (validation passes), holds no pair: the evaluation raises
    unreadable.mkdir()
    cfg = compose_config(smoke_overrides(tmp_path, f"data.real_pair={unreadable}"))
    with pytest.raises(DataError, match="not_a_pair"):
        run(cfg)
    c = client(tmp_path)
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id],
                         filter_string="tags.`demon_lab.scale` = 'smoke'")
    job = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(job) == 1 and job[0].info.status == "FAILED"
    assert "not_a_pair" in job[0].data.tags["demon_lab.error"]
    assert all(r.info.status != "RUNNING" for r in runs)
    # its stages trained and were cached before the evaluation failed: their runs stay FINISHED
    stages = c.search_runs([c.get_experiment_by_name("default").experiment_id],
                           filter_string=f"tags.`mlflow.parentRunId` = '{job[0].info.run_id}'")
    assert len(stages) == 6 and all(r.info.status == "FINISHED" for r in stages)


COUNTED_RUN = """
import json, sys
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from demon_lab.app import job
from demon_lab.data.sample import DataError

loads, seen = [], []
compose = ConfigLoaderImpl.load_configuration


def counted(self, config_name, overrides, run_mode, *args, **kwargs):
    loads.append([run_mode.name, list(overrides)])
    return compose(self, config_name, overrides, run_mode, *args, **kwargs)


def run(cfg):  # the job, without its work: what it was handed
    seen.append([int(cfg.seed), job._parent_run()])
    if cfg.seed == 1:
        raise DataError("seed 1 has no data")
    return {"status": "finished"}


ConfigLoaderImpl.load_configuration = counted
job.run = run
sys.argv = ["demon_lab", *sys.argv[1:]]
from demon_lab.__main__ import main
try:
    main()
finally:
    print("COUNTED " + json.dumps({"loads": loads, "seen": seen}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("sweep", [True, False], ids=["sweep", "single"])
def test_each_job_is_composed_as_hydra_does_and_handed_the_parent_run(sweep, tmp_path):
    """``python -m demon_lab`` with the job's work left out: a sweep's job is composed three times in
    all, with the same overrides (demon_lab's check of every job before any launch, then Hydra's
    basic sweeper's own check of its batch and its launcher), a single job
    once (Hydra, to run it; the job validates what it is handed), the parent run reaches every job of a
    sweep (no single run gets one), and a job that fails neither stops the sweep nor goes uncounted.
    Besides, Hydra composes the command's primary config in multirun mode to read ``hydra.mode`` from
    it (``Hydra.get_mode``, before anything else), a sweep's primary config once more for the sweep,
    and the sweep's table of its study rows composes each shipped design once, to name its runs'
    designs."""
    import json

    args = ["-m", *smoke_overrides(tmp_path), "seed=0,1,2"] if sweep else [*smoke_overrides(tmp_path), "seed=0"]
    result = subprocess.run([sys.executable, "-c", COUNTED_RUN, *args], cwd=tmp_path, capture_output=True, text=True,
                            timeout=600)
    (line,) = [x for x in result.stdout.splitlines() if x.startswith("COUNTED ")]
    counted = json.loads(line.removeprefix("COUNTED "))
    from demon_lab.reporting.provenance import NAMED

    composed = [tuple(o) for mode, o in counted["loads"] if mode == "RUN"]
    jobs = [o for o in composed if f"cache_dir={tmp_path}/cache" in o]
    primaries = [o for mode, o in counted["loads"] if mode == "MULTIRUN"]
    seeds = [0, 1, 2] if sweep else [0]
    times = 3 if sweep else 1
    assert len(jobs) == times * len(seeds) and all(jobs.count(j) == times for j in jobs), counted["loads"]
    # the sweep's table of its study rows names each run's design: each shipped design composed once
    designs = sorted(tuple(o) for o in NAMED.values()) if sweep else []
    assert sorted(o for o in composed if o not in jobs) == designs, counted["loads"]
    assert sorted({o for j in jobs for o in j if o.startswith("seed=")}) == [f"seed={s}" for s in seeds]
    assert len(primaries) == (2 if sweep else 1)  # Hydra's mode probe; a sweep's multirun
    if not sweep:
        assert result.returncode == 0, result.stderr[-3000:]
        assert counted["seen"] == [[0, None]]
        return
    c = client(tmp_path)
    (parent,) = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    assert counted["seen"] == [[s, parent.info.run_id] for s in seeds]
    assert parent.info.status == "FAILED" and parent.data.tags["demon_lab.jobs_failed_now"] == "1"
    assert result.returncode == 1
    errors = [x for x in result.stderr.splitlines() if x.startswith("error: ")]
    assert len(errors) == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert errors[0].startswith("error: seed 1 has no data (traceback in ")
    assert errors[1].startswith("error: 1 job(s) of the sweep failed (each folder has error.txt): multirun/default/")
    (folder,) = [p.parent for p in (tmp_path / "multirun").rglob("error.txt")]
    assert "seed=1" in folder.name and errors[1].endswith(folder.name)
    assert "DataError: seed 1 has no data" in (folder / "error.txt").read_text()


@pytest.mark.slow
def test_multirun_has_one_parent_run_and_trains_once(tmp_path):
    result = cli("-m", *smoke_overrides(tmp_path), "iterations=0,2", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    c = client(tmp_path)
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    parents = [r for r in runs if r.data.tags.get("demon_lab.kind") == "sweep"]
    jobs = [r for r in runs if "demon_lab.run_key" in r.data.tags]
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert sorted(r.data.tags["demon_lab.iterations"] for r in jobs) == ["0", "2"]
    assert all(r.data.tags["mlflow.parentRunId"] == parents[0].info.run_id for r in jobs)
    assert all(r.info.status == "FINISHED" for r in runs)
    # the six stages were trained once (by the first job), the second job read the cache
    stage_runs = [r for r in runs if r.data.tags.get("demon_lab.kind") == "stage"]
    assert len(stage_runs) == 6
    assert result.stdout.count("stage flow1: cached") == 1 and result.stdout.count("[demon_lab] results") == 2
    # the sweep ends in the table of its own jobs: one row per job, the swept key, each job's last pass
    # on synthetic_sun3d as its run logged it; the parent run holds the same table
    printed = result.stdout.split("[demon_lab] the sweep's jobs on ")[1].split("\n\n")[0]
    lines = printed.splitlines()
    assert lines[0] == "synthetic_sun3d:" and lines[1].split() == ["iterations", "status", "pass", "L1-inv", "sc-inv",
                                                                   "rot", "tran", "EPE"]
    by_iterations = {r.data.tags["demon_lab.iterations"]: r.data.metrics for r in jobs}
    for line in lines[3:]:
        it, status, passes, *values = line.split()
        assert status == "finished" and passes == it
        logged = [by_iterations[it][f"test/synthetic_sun3d/it{it}/{c}"] for c in ("l1_inv", "sc_inv", "rot_deg",
                                                                                  "tran_deg", "epe")]
        assert [float(v) for v in values] == pytest.approx(logged, abs=5e-4)
    assert [line.split()[0] for line in lines[3:]] == ["0", "2"]
    on_parent = Path(c.download_artifacts(parents[0].info.run_id, "jobs.txt", str(tmp_path))).read_text()
    assert on_parent.strip() == "the sweep's jobs on " + printed.strip()
