"""The main command end to end at the smoke scale, into a temporary MLflow store."""

from __future__ import annotations

import inspect
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from demon_lab import resources
from demon_lab.__main__ import CONF, check
from demon_lab.pipeline.identity import run_key
from tests.conftest import shared_renders

ROOT = Path(__file__).resolve().parents[1]


def smoke_overrides(tmp: Path, *extra: str) -> list[str]:
    """A smoke job whose store, artifacts and stage cache lie in ``tmp``; its scenes come from the
    tests' shared render cache."""
    return ["scale=smoke", f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"tracking.artifact_dir={tmp}/artifacts",
            f"cache_dir={tmp}/cache", f"data.cache_dir={shared_renders()}", *extra]


def compose_config(overrides: list[str]):
    with initialize_config_dir(CONF, version_base="1.3"):
        return compose("config", overrides=overrides)


def client(tmp: Path):
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=f"sqlite:///{tmp}/mlflow.db")


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "demon_lab", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600)


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    from demon_lab.app.job import run

    tmp = tmp_path_factory.mktemp("smoke")
    threads = torch.get_num_threads()
    environment = os.environ.get("MLFLOW_TRACKING_URI")
    try:
        result = run(compose_config(smoke_overrides(tmp, "threads=1")))
    finally:
        torch.set_num_threads(threads)
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
    assert result["run_key"] == run_key(compose_config(smoke_overrides(tmp, "threads=1")))
    assert result["run_key"] != run_key(compose_config(smoke_overrides(tmp, "threads=2")))
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

    import yaml

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


def test_a_data_config_without_held_apart_sets_validates(tmp_path):
    """``data.val`` null or left empty: no held-apart curves (a stage with keep_best refuses it)."""
    from demon_lab.pipeline.validate import validate

    assert validate(compose_config(smoke_overrides(tmp_path, "data.val=null"))).data.val == ()


@pytest.mark.parametrize("args, message", [
    (["iterations=-1"], "iterations: expected an integer >= 0"),
    (["threads=0"], "threads: expected an integer >= 1"),
    (["model.width=0"], "model.width: expected a positive number"),
    (["data.size=[100,128]"], "data.size: expected [H, W] with sides positive multiples of 32"),
    (["model.variant=v3"], "model.variant: expected one of v1, v2"),
    (["oracle=perfect"], "oracle: expected one of null, flow, depth_motion"),
    (["no_such_key=1"], "Could not override 'no_such_key'"),
    (["iterations=three"], "iterations: expected an integer"),
    (["loss=no_such_preset"], "Could not find 'loss/no_such_preset'"),
    (["schedule.stages.dm1.oracle=depth_motion"], "schedule.stages.dm1.oracle: expected one of null, flow"),
    (["-m", "iterations=0,1,-2"], "iterations: expected an integer >= 0, got -2"),
    (["schedule.until=dm1"], "iterations: expected 0 when schedule.until=dm1"),
    (["schedule.stages.flow1.sig_start=1.5"],
     "schedule.stages.flow1.sig_start: expected a fraction of the stage in [0, 1] (1: never)"),
    (["schedule.stages.flow1.warmup_steps=-5"], "schedule.stages.flow1.warmup_steps: expected an integer >= 0"),
    (["+schedule.stages.flow1.level5_fade=0"], "schedule.stages.flow1.level5_fade: expected a positive number"),
    (["+schedule.stages.dm1.level5_fade=1"], "schedule.stages.dm1.level5_fade: only flow stages have level-5 terms"),
    (["+schedule.stages.dm1.gt_flow_warmup=1.5"],
     "schedule.stages.dm1.gt_flow_warmup: expected a fraction of the stage in [0, 1]"),
    (["+schedule.stages.flow1.gt_flow_warmup=0.5"], "schedule.stages.flow1.gt_flow_warmup: only depth-motion"),
    (["+schedule.stages.flow1.easy_first=[0,0.5]"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["+schedule.stages.flow1.easy_first=0.5"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["+schedule.stages.flow1.easy_first=[1.5,0.5]"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["+schedule.stages.flow1.easy_first=[0.25,0]"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["model.correlation=[2,8]"], "model.correlation: expected [max_displacement, stride], positive integers"),
    (["model.correlation=[4,1]", "model.compat=demon_original"],
     "model.correlation: compat=demon_original reproduces DeMoN's released graph, which has no correlation front"),
    (["model.flow1_prior=flownet"], "model.flow1_prior: expected one of null, dis, dis_x2, got 'flownet'"),
    (["model.dm1_prior=lmeds"], "model.dm1_prior: expected one of null, ransac, ransac_prior, got 'lmeds'"),
    (["model.dm1_prior=ransac_prior"], "model.dm1_prior: ransac_prior reads flow1's classical prior flow; set "
                                       "model.flow1_prior (dis or dis_x2)"),
    (["model.dm2_prior=ransac"], "model.dm2_prior: expected one of null, previous, got 'ransac'"),
    (["model.flow2_prior=dis"], "model.flow2_prior: expected one of null, previous, got 'dis'"),
    (["model.flow2_prior=previous", "model.compat=demon_original"],
     "model.flow2_prior: compat=demon_original reproduces DeMoN's released graph, whose nets have no priors"),
    (["model.dm2_prior=previous", "model.compat=demon_original"],
     "model.dm2_prior: compat=demon_original reproduces DeMoN's released graph, whose nets have no priors"),
    (["model.flow1_prior=dis", "model.compat=demon_original"],
     "model.flow1_prior: compat=demon_original reproduces DeMoN's released graph, whose nets have no priors"),
    (["+schedule.stages.dm1.layers_first=0.5"], "schedule.stages.dm1.layers_first: only the bootstrap flow net's"),
    (["+schedule.stages.flow1.layers_first=0"], "schedule.stages.flow1.layers_first: expected a fraction of the stage"),
    (["+schedule.stages.flow1.restarts=[3,0]"], "schedule.stages.flow1.restarts: expected [starts, steps]"),
    (["+schedule.stages.dm1.sig_start=0.5"],
     "schedule.stages.dm1.sig_start: not an option of a depth_motion stage (its options: kind, steps, lr, "
     "warmup_steps, batch_size, oracle, easy_first, fresh_scenes, keep_best, net, gt_flow_warmup)"),
    (["+schedule.stages.flow1.fresh_scenes=2"],
     "schedule.stages.flow1.fresh_scenes: expected new scenes per training draw in [0, 1], got 2"),
    (["+schedule.stages.dm1.fresh_scenes=0.1", "+schedule.stages.dm1.easy_first=[0.5,0.5]"],
     "schedule.stages.dm1.fresh_scenes: the easy_first order is of a fixed set of scenes; leave easy_first unset"),
    (["+schedule.stages.flow1.keep_best=-1"], "schedule.stages.flow1.keep_best: expected an integer >= 0, got -1"),
    (["+schedule.stages.flow1.keep_best=10", "data.val=[]"],
     "schedule.stages.flow1.keep_best: scores the held-apart sets, and data.val has none"),
    (["+schedule.stages.refine.queue_size=4"], "schedule.stages.refine.queue_size: not an option of a refine stage"),
    (["trainer.reuse_frozen=sometimes"], "trainer.reuse_frozen: expected true or false, got 'sometimes'"),
    (["data.train=null"], "data.train: expected at least one training source"),
    (["schedule.stages.iterative.queue_size=-3"], "schedule.stages.iterative.queue_size: expected an integer >= 0"),
    (["baseline.size=[16,16]"], "baseline.size: expected native or [H, W] with sides >= 32 pixels"),
    (["baseline.size=full"], "baseline.size: expected native or [H, W] with sides >= 32 pixels, got full"),
    (["data.real_pair=/does/not/exist"], "data.test[3].path (data.real_pair): /does/not/exist: no such file"),
    (["data=pair_folder", "data.path=/no/pairs"], "data.test[0].path (data.path): /no/pairs: no such file"),
    (["data=tum", "data.root=/no/tum"], "data.test[0].root (data.root): /no/tum: no such file or directory"),
])
def test_bad_configuration_is_one_line_before_any_work(args, message, tmp_path, monkeypatch, capsys):
    """In the process: ``python -m demon_lab``'s own entry point, its exit status and its stderr (the
    process itself, for two of these cases: the next test)."""
    import logging

    from demon_lab.__main__ import main

    monkeypatch.chdir(tmp_path)
    # Hydra sets the root logger's handlers up for the job, on the stream this test captures: the
    # tests after this one get the handlers back
    monkeypatch.setattr(logging.root, "handlers", list(logging.root.handlers))
    flags = [a for a in args if a.startswith("-")]  # Hydra reads its flags before the overrides
    monkeypatch.setattr(sys, "argv", ["demon_lab", *flags, *smoke_overrides(tmp_path),
                                      *[a for a in args if a not in flags]])
    with pytest.raises(SystemExit) as exited:
        main()
    captured = capsys.readouterr()
    assert exited.value.code == 2, captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], captured.err
    assert not captured.out
    assert not (tmp_path / "mlflow.db").exists()  # nothing was recorded


@pytest.mark.parametrize("args, message", [
    (["model.width=0"], "model.width: expected a positive number"),
    (["-m", "iterations=0,1,-2"], "iterations: expected an integer >= 0, got -2"),
])
def test_a_bad_configuration_exits_the_process_with_status_2_and_one_line(args, message, tmp_path):
    flags = [a for a in args if a.startswith("-")]  # Hydra reads its flags before the overrides
    result = cli(*flags, *smoke_overrides(tmp_path), *[a for a in args if a not in flags], cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not result.stdout
    assert not (tmp_path / "mlflow.db").exists()  # nothing was recorded


@pytest.mark.parametrize("overrides", [
    ["scale=cpu"], ["scale=paper"], ["scale=smoke", "model.variant=v2"], ["loss=supplementary"],
    ["loss=no_sig"], ["loss=no_normals"], ["loss=no_confidence"], ["loss=depth_sig_1000"],
    ["schedule=supplementary"], ["data=synthetic_scenes11"], ["data=middlebury"],
    ["-m", "iterations=0,1,2,3,4,5"], ["-m", "loss=supplementary,released_code,no_sig"],
])
def test_documented_configurations_compose_and_validate(overrides):
    assert check(overrides) is None


EXPERIMENTS = sorted(p.stem for p in (resources.CONF / "experiment").glob("*.yaml") if p.stem != "released_model")
"""The experiments that run on demon_lab's own data (released_model needs DeMoN's files and weights:
tests/test_released.py)."""
SWEPT = [e for e in EXPERIMENTS if e not in ("cpu_recipe", "cpu_design", "cpu_motion", "cpu_prior", "cpu_departures",
                                             "learned_design", "learned_rerun", "baseline_thresholds")]
"""The experiments that declare a sweep (the probes of cpu_recipe, cpu_design, cpu_motion, cpu_prior,
cpu_departures, learned_design, learned_rerun and baseline_thresholds are single jobs, the commands of their
study specs in ablations/, which tests/test_report.py composes)."""


@pytest.mark.parametrize("experiment", SWEPT)
@pytest.mark.parametrize("scale", ["smoke", pytest.param("cpu", marks=pytest.mark.slow),
                                   pytest.param("paper", marks=pytest.mark.slow)])
def test_every_experiment_sweep_composes_and_validates(experiment, scale):
    """Each job of an experiment's declared sweep (hydra.sweeper.params) composes and validates."""
    from demon_lab.__main__ import sweep_jobs

    args = ["-m", f"+experiment={experiment}", f"scale={scale}"]
    jobs = sweep_jobs(args)
    assert len(jobs) >= 3 and {o.split("=")[0] for job in jobs for o in job} >= {"seed"}
    assert check(args) is None


@pytest.mark.slow
def test_checking_a_configuration_imports_neither_lightning_nor_mlflow():
    """``python -m demon_lab``'s check of every experiment (what runs before any work) in a fresh
    process: composing and validating a config needs neither the training nor the tracking library."""
    code = ("import sys\n"
            "from demon_lab.__main__ import check\n"
            f"swept = {SWEPT!r}\n"
            f"for e in {EXPERIMENTS!r}:\n"
            "    assert check(['-m', f'+experiment={e}'] if e in swept else [f'+experiment={e}']) is None\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'lightning', 'pytorch_lightning', 'mlflow'}))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]", result.stdout


def test_each_stage_kind_carries_its_module_nets_oracles_and_scores_and_the_rate_schedules_are_implemented():
    from demon_lab.core.losses import WEIGHT_KEYS
    from demon_lab.nets.chain import ORACLES
    from demon_lab.pipeline.schema import LR_SCHEDULES, STAGE_SPECS
    from demon_lab.pipeline.stages import modules
    from demon_lab.pipeline.stages.base import StageModule, learning_rate

    nets = {"flow1", "dm1", "flow2", "dm2", "refine_net"}
    for kind, spec in STAGE_SPECS.items():  # its module takes every option it sets
        module = getattr(modules, spec.module)
        assert issubclass(module, StageModule), kind
        stage = spec(name=kind, steps=10, lr=1e-3)
        assert set(stage.module_options()) <= set(inspect.signature(module).parameters) | {
            "steps", "lr", "warmup_steps", "oracle"}, kind
        assert set(stage.trained_nets()) <= nets and set(stage.weight_keys()) <= set(WEIGHT_KEYS), kind
        assert set(spec.oracles) - {None} <= set(ORACLES), kind
    flow2 = STAGE_SPECS["flow"](name="flow2", steps=1, lr=1.0, net="flow2", sig_start=1.0)
    assert flow2.trained_nets() == ("flow2",) and flow2.validation_passes() == 1
    assert flow2.weight_keys() == ("flow", "flow_conf")  # its sig terms never start: not read, not in its key
    assert STAGE_SPECS["iterative"](name="iterative", steps=1, lr=1.0).trained_nets() == ("flow2", "dm2")
    assert STAGE_SPECS["refine"](name="refine", steps=1, lr=1.0, iterations=2).validation_passes() == 2
    for schedule in LR_SCHEDULES:  # each is implemented: the base rate at step 0, decayed by mid-stage
        assert learning_rate(0, 1000, 1e-3, schedule) == 1e-3
        assert 0 < learning_rate(500, 1000, 1e-3, schedule) < learning_rate(399, 1000, 1e-3, schedule) <= 1e-3
    with pytest.raises(ValueError, match=r"schedule\.lr_schedule: expected one of"):
        learning_rate(500, 1000, 1e-3, "cosine")


def test_experiments_exist_for_every_study():
    assert set(EXPERIMENTS) >= {"gt_flow_oracle", "gt_depth_motion_oracle", "iterations", "loss_weights", "baselines"}


@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_longer_oracle_study_trains_dm1_four_times_the_profile_and_shares_flow1(scale):
    import demon_lab.pipeline.config  # noqa: F401  (registers the ${times:} resolver, as the app does)
    from demon_lab.pipeline.stages.schedule import stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        base = compose("config", [f"scale={scale}", "+experiment=gt_flow_oracle", "oracle=flow"])
        long = compose("config", [f"scale={scale}", "+experiment=gt_flow_oracle_long", "oracle=flow"])
    assert long.experiment == "gt_flow_oracle_long" and long.schedule.stages.dm1.oracle == "flow"
    assert long.schedule.stages.dm1.steps == 4 * base.scale.steps.dm1 == 4 * base.schedule.stages.dm1.steps
    (flow1, dm1), (flow1_long, dm1_long) = stage_dirs(base), stage_dirs(long)
    assert flow1.key == flow1_long.key and dm1.key != dm1_long.key


@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_the_probe_options_are_absent_from_every_profile_and_key_only_their_stage_and_later(scale):
    """level5_fade, gt_flow_warmup, easy_first and layers_first exist for probes (ablations/cpu_recipe.yaml,
    ablations/cpu_design.yaml): no profile sets them,
    so no key holds them; set, they key their own stage and, through the upstream keys, the later ones."""
    from demon_lab.pipeline.stages.schedule import stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        plain = compose("config", [f"scale={scale}"])
        fade = compose("config", [f"scale={scale}", "+schedule.stages.flow1.level5_fade=1.0"])
        warm = compose("config", [f"scale={scale}", "+schedule.stages.dm1.gt_flow_warmup=0.5"])
        easy = compose("config", [f"scale={scale}", "+schedule.stages.flow1.easy_first=[0.25,0.5]"])
        layers = compose("config", [f"scale={scale}", "+schedule.stages.flow1.layers_first=0.3"])
    for spec in plain.schedule.stages.values():
        assert not {"level5_fade", "gt_flow_warmup", "easy_first", "layers_first"} & set(spec)
    keys = {name: [d.key for d in stage_dirs(cfg)]
            for name, cfg in (("plain", plain), ("fade", fade), ("warm", warm), ("easy", easy), ("layers", layers))}
    for option in ("fade", "easy", "layers"):
        assert all(a != b for a, b in zip(keys["plain"], keys[option], strict=True))
    assert keys["warm"][0] == keys["plain"][0] and all(a != b for a, b in zip(keys["plain"][1:], keys["warm"][1:],
                                                                             strict=True))


# DeMoN's design at every scale (the cpu scale's profile has four priors: design=demon turns them off).
DEMON_DESIGN = ("design=demon",)
FOUR_PRIORS_OFF = ("model.flow1_prior=null", "model.dm1_prior=null", "model.flow2_prior=null", "model.dm2_prior=null")


@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_design_demon_is_demons_design_at_every_scale_with_the_keys_of_the_four_priors_off(scale):
    """design=demon composes DeMoN's design: at the smoke and paper scales the scale's own config, at the cpu
    scale the profile with its four priors off, each with the stage and run keys of those configs."""
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.identity import run_key
    from demon_lab.pipeline.stages.schedule import stage_dirs
    from demon_lab.pipeline.tracking import flatten
    from demon_lab.reporting.provenance import DEMON, departures, design_name

    with initialize_config_dir(CONF, version_base="1.3"):
        named = compose("config", [f"scale={scale}", "design=demon"])
        spelled = compose("config", [f"scale={scale}", *FOUR_PRIORS_OFF])
        own = compose("config", [f"scale={scale}"])
    assert run_key(named) == run_key(spelled)
    assert [d.key for d in stage_dirs(named)] == [d.key for d in stage_dirs(spelled)]
    assert design_name(departures(flatten(OmegaConf.to_container(named, resolve=True)))) == DEMON
    assert (run_key(named) == run_key(own)) == (scale != "cpu")


@pytest.mark.parametrize("option, key, built", [
    ("model.correlation=[8,2]", "correlation",
     lambda chain: chain.flow1.correlation == (8, 2) and chain.flow2.correlation == (8, 2)),
    ("model.flow1_prior=dis", "flow1_prior", lambda chain: chain.flow1.prior == "dis" and chain.flow2.prior is None),
], ids=["correlation", "flow1_prior"])
@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_a_flow_net_option_keys_every_stage_and_the_run_and_is_absent_by_default(option, key, built, scale):
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.identity import run_key, semantic_config
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        plain = compose("config", [f"scale={scale}", *DEMON_DESIGN])
        changed = compose("config", [f"scale={scale}", *DEMON_DESIGN, option])
    assert plain.model[key] is None and key not in semantic_config(plain)["model"]
    assert all(a.key != b.key for a, b in zip(stage_dirs(plain), stage_dirs(changed), strict=True))
    assert run_key(plain) != run_key(changed)
    if scale != "paper":  # (the paper-scale chain is 46 M parameters: the smaller ones show the same)
        assert built(build_chain(changed)) and not built(build_chain(plain))


@pytest.mark.parametrize(("option", "first"), [("dm1_prior=ransac", "dm1"), ("flow2_prior=previous", "flow2"),
                                               ("dm2_prior=previous", "dm2")])
def test_a_motion_prior_keys_the_stages_from_its_net_on_and_shares_those_before(option, first):
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.identity import run_key
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    key, value = option.split("=")
    with initialize_config_dir(CONF, version_base="1.3"):
        plain = compose("config", ["scale=cpu", *DEMON_DESIGN])
        prior = compose("config", ["scale=cpu", *DEMON_DESIGN, f"model.{option}"])
    assert plain.model[key] is None and run_key(plain) != run_key(prior)
    a, b = stage_dirs(plain), stage_dirs(prior)
    names = [d.name for d in a]
    assert names == [d.name for d in b] and first in names
    cut = names.index(first)
    assert all(x.key == y.key for x, y in zip(a[:cut], b[:cut], strict=True))
    assert all(x.key != y.key for x, y in zip(a[cut:], b[cut:], strict=True))
    assert getattr(build_chain(prior), key) == value and getattr(build_chain(plain), key) is None


def test_the_stages_train_the_chain_with_all_four_priors_and_under_the_depth_motion_oracle(tmp_path):
    """Every stage kind trains and evaluates with the four priors (flow2's correction of the previous
    flow in the flow2, dm2, iterative and refine stages), and flow2 trains with its prior under the
    depth-motion oracle, where it reads ground-truth depth and motion and corrects the bootstrap flow."""
    from demon_lab.app.job import run

    priors = ["model.flow1_prior=dis", "model.dm1_prior=ransac", "model.flow2_prior=previous",
              "model.dm2_prior=previous"]
    threads = torch.get_num_threads()
    try:
        chain = run(compose_config(smoke_overrides(tmp_path, "threads=1", *priors)))
        oracle = run(compose_config(smoke_overrides(tmp_path, "threads=1", "+experiment=gt_depth_motion_oracle",
                                                    "model.flow2_prior=previous")))
    finally:
        torch.set_num_threads(threads)
    assert chain["status"] == oracle["status"] == "finished"
    for name in ("synthetic_sun3d", "middlebury"):
        assert all(math.isfinite(chain["summary"][name][f"it{k}/epe"]) for k in range(4))
        assert math.isfinite(oracle["summary"][name]["it1/epe"])


def test_only_the_cpu_profile_departs_and_the_departures_study_turns_each_departure_off():
    """The cpu profile takes the four priors (dis_x2, ransac_prior, previous, previous) and the memo;
    smoke and paper keep DeMoN's design. Each row of the cpu_departures study at the cpu scale turns
    off exactly the prior its name says (without flow1's prior, dm1 reads RANSAC of flow1's own flow),
    row demon all four, and row profile is the cpu profile itself."""
    from demon_lab.pipeline.schema import PRIOR_KEYS
    from demon_lab.pipeline.stages.schedule import build_chain

    spec = yaml.safe_load((resources.STUDIES / "cpu_departures.yaml").read_text())
    four = {"flow1_prior": "dis_x2", "dm1_prior": "ransac_prior", "flow2_prior": "previous", "dm2_prior": "previous"}
    assert set(PRIOR_KEYS) == set(four)
    with initialize_config_dir(CONF, version_base="1.3"):
        for scale in ("smoke", "paper"):
            cfg = compose("config", [f"scale={scale}"])
            assert all(cfg.model[k] is None for k in four) and cfg.trainer.reuse_frozen is False
        cpu = compose("config", ["scale=cpu"])
        assert {k: cpu.model[k] for k in four} == four and cpu.trainer.reuse_frozen is True
        rows = {}
        for run in spec["runs"]:
            cfg = compose("config", ["scale=cpu", *(o for o in run if not o.startswith("seed="))])
            rows[cfg.row] = {k: cfg.model[k] for k in four}
            assert cfg.train is (cfg.row != "untrained")
    assert rows["profile"] == rows["untrained"] == four and rows["demon"] == dict.fromkeys(four)
    assert rows["no_flow1_prior"] == {**four, "flow1_prior": None, "dm1_prior": "ransac"}
    for key in ("dm1_prior", "flow2_prior", "dm2_prior"):
        assert rows[f"no_{key}"] == {**four, key: None}
    with initialize_config_dir(CONF, version_base="1.3"):
        chain = build_chain(compose("config", ["scale=cpu", *spec["runs"][0]]))
    assert (chain.flow1_prior, chain.dm1_prior, chain.flow2_prior, chain.dm2_prior) == tuple(four.values())


def test_train_stage_hands_the_probe_options_to_their_stages(tmp_path, monkeypatch):
    """A flow stage gets level5_fade, a depth-motion stage gt_flow_warmup, from the stage's config;
    a stage without them gets DeMoN's values (its module's defaults)."""
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Built(Exception):
        pass

    given = {}

    def capture(kind):
        def make(chain, weights, **kwargs):
            given[kind] = kwargs
            raise Built
        return make

    from demon_lab.pipeline.schema import STAGE_SPECS
    from demon_lab.pipeline.stages import modules
    from demon_lab.pipeline.stages.modules import DepthMotionStage, FlowStage

    for kind, spec in STAGE_SPECS.items():
        monkeypatch.setattr(modules, spec.module, capture(kind))
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}", "+schedule.stages.flow1.level5_fade=0.75",
                                 "+schedule.stages.dm1.gt_flow_warmup=0.4"])
        plain = compose("config", ["scale=smoke", f"cache_dir={tmp_path}"])
    default = lambda module, key: inspect.signature(module).parameters[key].default  # noqa: E731
    demon = {"flow": {"level5_fade": default(FlowStage, "level5_fade")},
             "depth_motion": {"gt_flow_warmup": default(DepthMotionStage, "gt_flow_warmup")}}
    assert demon == {"flow": {"level5_fade": 1 / 3}, "depth_motion": {"gt_flow_warmup": 0.0}}
    for config, expect in ((cfg, {"flow": {"level5_fade": 0.75}, "depth_motion": {"gt_flow_warmup": 0.4}}),
                           (plain, demon)):
        chain = build_chain(config)
        for stage in stage_dirs(config)[:2]:  # flow1, dm1
            with pytest.raises(Built):
                training.train_stage(config, chain, stage, logger=None, progress=False)
        assert {k: v for k, v in given["flow"].items() if k == "level5_fade"} == expect["flow"]
        assert {k: v for k, v in given["depth_motion"].items() if k == "gt_flow_warmup"} == expect["depth_motion"]


def test_train_stage_draws_its_samples_with_the_stage_curriculum(tmp_path, monkeypatch):
    """easy_first of a stage reaches its sampler, with each source ordered by flow_order; a stage
    without it draws with the plain sampler."""
    from demon_lab.data.mixture import flow_order
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Built(Exception):
        pass

    samplers = []

    def fit(trainer, module, train_dataloaders, ckpt_path=None):
        samplers.append(train_dataloaders.sampler)
        raise Built

    monkeypatch.setattr(training.L.Trainer, "fit", fit)
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}",
                                 "+schedule.stages.flow1.easy_first=[0.25,0.5]"])
    chain = build_chain(cfg)
    for stage in stage_dirs(cfg)[:2]:  # flow1 with the curriculum, dm1 without
        with pytest.raises(Built):
            training.train_stage(cfg, chain, stage, logger=None, progress=False)
    easy, plain = samplers
    assert easy.easy_first == (0.25, 0.5) and plain.easy_first is None
    datasets = training.build_datamodule(cfg, training.JobSettings.of(cfg), 2, 4).train_sources
    assert [list(o) for o in easy.order] == [list(flow_order(d)) for _, d in datasets]


def test_a_flow1_stage_starts_on_fresh_2d_layers_and_trains_on_them(tmp_path, monkeypatch):
    """layers_first of flow1 reaches its sampler as the lead of a 2-D layers source of the job's size
    and seed (weight 0: none after the lead); a flow1 step on a batch of layers has a finite loss that
    the flow net's every parameter gets a gradient from."""
    from demon_lab.data.datasets import LayersDataset
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.modules import FlowStage
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Built(Exception):
        pass

    loaders = []

    def fit(trainer, module, train_dataloaders, ckpt_path=None):
        loaders.append(train_dataloaders)
        raise Built

    monkeypatch.setattr(training.L.Trainer, "fit", fit)
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}", "seed=3",
                                 "+schedule.stages.flow1.layers_first=0.5"])
    chain = build_chain(cfg)
    for stage in stage_dirs(cfg)[:2]:  # flow1 with the layers, dm1 without
        with pytest.raises(Built):
            training.train_stage(cfg, chain, stage, logger=None, progress=False)
    layered, plain = (loader.sampler for loader in loaders)
    sources = loaders[0].dataset.datasets
    assert isinstance(sources[-1], LayersDataset) and sources[-1].size == tuple(cfg.data.size)
    assert sources[-1].seed == 3 and layered.lead_source == len(sources) - 1 and layered.p[-1] == 0
    steps, batch = int(cfg.schedule.stages.flow1.steps), int(cfg.data.batch_size)
    assert layered.lead_keys == round(0.5 * steps) * batch and plain.lead_keys == 0
    assert not any(isinstance(d, LayersDataset) for d in loaders[1].dataset.datasets)
    module = FlowStage(chain, weights=dict(cfg.loss), steps=10, lr=1e-4)
    pairs = torch.utils.data.default_collate([sources[-1][i] for i in range(2)])
    from demon_lab.core import losses

    loss, terms = module.stage_loss(pairs, losses.ground_truth(pairs))
    assert torch.isfinite(loss) and terms["flow2"] > 0
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in chain.flow1.parameters())


def test_restarts_screen_starts_of_flow1_and_the_stage_continues_from_the_best(tmp_path):
    """restarts=[1, 1] is the plain stage, to the last bit (start 0 is the chain's own initialisation and
    the stage continues from its checkpoint as a resumed stage does); restarts=[3, 1] trains three starts
    for one step, logs each one's held-apart EPE, continues from the lowest and keeps only its checkpoint."""
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Recorder:
        def __init__(self):
            self.logged = []

        def log_metrics(self, metrics, step=None):
            self.logged.append((dict(metrics), step))

    def trained(*extra, logger=None):
        with initialize_config_dir(CONF, version_base="1.3"):
            cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path / str(len(list(tmp_path.iterdir())))}",
                                     "schedule.stages.flow1.steps=3", *extra])
        torch.manual_seed(0)
        chain = build_chain(cfg)
        stage = stage_dirs(cfg)[0]
        training.train_stage(cfg, chain, stage, logger=None, progress=False) if logger is None else \
            _train_with(training, cfg, chain, stage, logger)
        return chain.flow1.state_dict(), stage

    plain, _ = trained()
    one, _ = trained("+schedule.stages.flow1.restarts=[1,1]")
    assert all(torch.equal(plain[k], one[k]) for k in plain)
    recorder = Recorder()
    three, stage = trained("+schedule.stages.flow1.restarts=[3,1]", logger=recorder)
    scores = [m["restart/val_epe"] for m, _ in recorder.logged if "restart/val_epe" in m]
    chosen = [m["restart/chosen"] for m, _ in recorder.logged if "restart/chosen" in m]
    assert len(scores) == 3 and len(set(scores)) == 3 and chosen == [float(np.argmin(scores))]
    assert [p.name for p in stage.path.glob("restart*.ckpt")] == [f"restart{int(chosen[0])}.ckpt"]
    assert any(not torch.equal(plain[k], three[k]) for k in plain) == (chosen[0] != 0)


def _train_with(training, cfg, chain, stage, logger):
    """train_stage with a logger that records the metrics logged outside Lightning's own logging."""
    original = training.L.Trainer.__init__

    def without_logger(self, *args, **kwargs):  # the stage's own curves need an MLflow run: not here
        kwargs["logger"] = False
        original(self, *args, **kwargs)

    import unittest.mock

    with unittest.mock.patch.object(training.L.Trainer, "__init__", without_logger):
        training.train_stage(cfg, chain, stage, logger=logger, progress=False)


def test_a_stage_key_holds_only_the_loss_weights_that_stage_reads():
    """The loss-weight study's presets share every stage whose loss they leave unchanged:
    no_normals and depth_sig_1000 change depth-motion weights only, so they share supplementary's
    flow1 and train their own dm1; no_confidence changes the flow weights, so its flow1 (and,
    through the upstream key, its dm1) is its own. no_sig changes the flow sig weights, which the
    cpu scale's flow1 never reads (sig_start 1), so there it shares supplementary's flow1 too; at
    the paper scale (sig terms from step 0) it does not."""
    from demon_lab.pipeline.stages.schedule import stage_dirs

    keys = {}
    with initialize_config_dir(CONF, version_base="1.3"):
        for loss in ("supplementary", "no_normals", "depth_sig_1000", "no_confidence", "no_sig"):
            cfg = compose("config", ["scale=cpu", "+experiment=loss_weights", f"loss={loss}"])
            keys[loss] = [d.key for d in stage_dirs(cfg)]
    flow1 = {loss: k[0] for loss, k in keys.items()}
    dm1 = {loss: k[1] for loss, k in keys.items()}
    assert flow1["no_normals"] == flow1["depth_sig_1000"] == flow1["supplementary"] != flow1["no_confidence"]
    assert flow1["no_sig"] == flow1["supplementary"]
    assert len(set(dm1.values())) == 5
    with initialize_config_dir(CONF, version_base="1.3"):
        paper = {loss: stage_dirs(compose("config", ["scale=paper", "+experiment=loss_weights", f"loss={loss}"]))[0].key
                 for loss in ("supplementary", "no_sig")}
    assert paper["no_sig"] != paper["supplementary"]


def test_times_resolver_takes_integers_only():
    from omegaconf import OmegaConf
    from omegaconf.errors import InterpolationResolutionError

    import demon_lab.pipeline.config  # noqa: F401  (registers the resolver)

    assert OmegaConf.create({"n": 3, "m": "${times:${n},4}"}).m == 12
    with pytest.raises(InterpolationResolutionError, match="times: expected two integers"):
        _ = OmegaConf.create({"n": "3; rm -rf", "m": "${times:${n},4}"}).m


@pytest.mark.slow
def test_killed_training_stage_resumes_from_its_checkpoint(tmp_path):
    """A real job is killed (SIGKILL) mid-stage; the same command resumes from the stage's last
    checkpoint instead of starting over."""
    args = smoke_overrides(tmp_path, "scale.steps.flow1=100", "schedule.until=flow1", "iterations=0",
                           "scale.checkpoint_every=5",
                           "eval.max_samples=1")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "demon_lab", *args], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoints = []
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        checkpoints = list((tmp_path / "cache" / "stages").glob("flow1-*/last.ckpt"))
        if checkpoints and any((p.parent / "weights.pt").exists() for p in checkpoints):
            break
        if checkpoints:
            time.sleep(1.0)  # let a few more steps pass
            break
        time.sleep(0.2)
    assert checkpoints, "no checkpoint was written before the deadline"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    import torch

    step_at_kill = torch.load(checkpoints[0], map_location="cpu", weights_only=False)["global_step"]
    assert 0 < step_at_kill < 100
    from demon_lab.app.job import run

    result = run(compose_config(args))
    assert result["status"] == "finished"
    assert (checkpoints[0].parent / "weights.pt").is_file()
    # the stage resumed from the checkpoint (at the kill step or a later one written just before
    # the kill) and ran only the remaining steps
    figures = result["figures"]["flow1"]
    assert step_at_kill <= figures["resumed_from_step"] < 100
    assert torch.load(checkpoints[0], map_location="cpu", weights_only=False)["global_step"] == 100
    c = client(tmp_path)
    statuses = [r.info.status for r in c.search_runs([c.get_experiment_by_name("default").experiment_id])]
    assert "FINISHED" in statuses


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
def test_each_job_is_composed_twice_and_handed_the_parent_run(sweep, tmp_path):
    """``python -m demon_lab`` with the job's work left out: a sweep's job is composed twice in all,
    with the same overrides (the sweeper's check before any launch, then its launcher), a single job
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
    times = 2 if sweep else 1
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


def test_keep_best_keeps_the_nets_of_the_lowest_held_apart_score_across_a_resume(tmp_path):
    """KeepBest scores every 2 steps and at the last: scripted translation scores 40, 30, 35 at steps
    2, 4, 6 keep step 4's nets; a stage resumed after step 4 (a new callback over the same file) keeps
    them against a worse score at step 6 and takes a better one at step 8; the restored nets are those
    of the best step, bit for bit, and only the stage's own nets are written."""
    from types import SimpleNamespace

    from demon_lab.pipeline.stages.validation import KeepBest

    scripted = {2: 40.0, 4: 30.0, 6: 35.0, 8: 20.0}

    class Scorer:
        last_seconds = 1.5  # what each step's scoring took (the option's cost counts it)

        def evaluate(self, trainer, module):
            score = scripted[trainer.global_step]
            return {"val/a/tran_deg": score, "val/b/tran_deg": score, "val/a/epe": -1.0}

    chain = SimpleNamespace(dm1=torch.nn.Linear(2, 2), flow1=torch.nn.Linear(2, 2))
    module = SimpleNamespace(chain=chain)
    states = {}

    def steps(keep, first, last, max_steps):
        for step in range(first, last + 1):
            with torch.no_grad():
                chain.dm1.weight.fill_(float(step))
            states[step] = {k: v.clone() for k, v in chain.dm1.state_dict().items()}
            keep.on_train_batch_end(SimpleNamespace(global_step=step, max_steps=max_steps), module, None, None, 0)

    path = tmp_path / "best.pt"
    keep = KeepBest(Scorer(), "tran_deg", 2, path, ["dm1"])
    steps(keep, 1, 4, max_steps=8)
    resumed = KeepBest(Scorer(), "tran_deg", 2, path, ["dm1"])
    assert (resumed.best_step, resumed.best) == (4, 30.0)
    steps(resumed, 5, 6, max_steps=8)
    assert resumed.best_step == 4
    figures = resumed.restore(chain)
    assert figures["keep_best_step"] == 4 and figures["keep_best_tran_deg"] == 30.0
    assert torch.equal(chain.dm1.weight, states[4]["weight"])
    assert set(torch.load(path, weights_only=True)["nets"]) == {"dm1"}
    steps(resumed, 7, 8, max_steps=8)
    assert resumed.restore(chain)["keep_best_step"] == 8 and torch.equal(chain.dm1.weight, states[8]["weight"])
    assert figures["keep_best_seconds"] >= 1.5  # step 6 scored in this process (steps 2 and 4 before the resume)


LEARNED_CHOICES = {  # the study's row -> what it turns off, as the row's overrides set it
    "no_correlation": {"model.correlation": None},
    "no_layers_first": {"schedule.stages.flow1.layers_first": None},
    "no_fresh_scenes": {"schedule.stages.flow1.fresh_scenes": 0, "schedule.stages.dm1.fresh_scenes": 0},
    "no_gt_flow_warmup": {"schedule.stages.dm1.gt_flow_warmup": 0},
    "no_keep_best": {f"schedule.stages.{s}.keep_best": 0 for s in ("flow1", "dm1", "iterative")},
    "profile_steps": {"scale.steps.flow1": 5000, "scale.steps.dm1": 2500,  # (and the stages that read them)
                      "schedule.stages.flow1.steps": 5000, "schedule.stages.dm1.steps": 2500},
    "no_previous": {"model.flow2_prior": None, "model.dm2_prior": None},
    "untrained": {"train": False},
}


def _leaves(node, prefix=""):
    if isinstance(node, dict):
        return {k: v for key, value in node.items() for k, v in _leaves(value, f"{prefix}{key}.").items()}
    return {prefix[:-1]: node}


def test_the_learned_design_has_no_classical_prior_and_its_study_turns_each_choice_off_alone():
    """design=learned: no DIS flow, no RANSAC motion, its choices set; the profile and DeMoN's design
    set none of its new options; each row of ablations/learned_design.yaml differs from row learned in
    exactly the keys its name turns off (and its row tag), and every row composes the design."""
    from demon_lab.pipeline.identity import semantic_config

    spec = yaml.safe_load((resources.STUDIES / "learned_design.yaml").read_text())
    with initialize_config_dir(CONF, version_base="1.3"):
        learned = compose("config", ["design=learned"])
        others = [compose("config", []), compose("config", ["+experiment=cpu_departures", *DEMON_DESIGN])]
        rows = {}
        for run in spec["runs"]:
            assert "seed=0,1,2" in run  # every row at 3 seeds (a sweep: composed here at seed 0)
            cfg = compose("config", [o for o in run if not o.startswith("seed=")])
            rows[cfg.row] = _leaves(OmegaConf.to_container(cfg, resolve=True))
    assert (learned.model.flow1_prior, learned.model.dm1_prior) == (None, None)
    assert learned.model.correlation == [8, 2] and learned.model.flow2_prior == "previous"
    stages = learned.schedule.stages
    assert stages.flow1.fresh_scenes > 0 and stages.dm1.fresh_scenes > 0 and stages.dm1.gt_flow_warmup > 0
    assert stages.flow1.keep_best > 0 and stages.dm1.keep_best > 0 and stages.flow1.layers_first > 0
    for cfg in others:
        for stage in cfg.schedule.stages.values():
            assert not {"fresh_scenes", "keep_best"} & set(stage)
    assert set(rows) == {"learned", *LEARNED_CHOICES}
    semantic = _leaves(semantic_config(learned))
    base = {k: v for k, v in rows["learned"].items() if k in semantic}
    for row, turned_off in LEARNED_CHOICES.items():
        changed = {k: v for k, v in rows[row].items() if k in semantic and base.get(k) != v}
        assert changed == turned_off, row


@pytest.mark.parametrize("option", ["schedule.stages.flow1.fresh_scenes=0.1", "schedule.stages.flow1.keep_best=100",
                                    "schedule.stages.dm1.fresh_scenes=0.1", "schedule.stages.dm1.keep_best=100"])
def test_fresh_scenes_and_keep_best_key_their_stage_and_the_later_ones_only(option):
    """Set on a stage, either option keys that stage and (through the upstream keys) the later ones;
    the earlier stages keep their keys. keep_best also keys the held-apart sets that choose."""
    from demon_lab.pipeline.stages.schedule import stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        plain = [d.key for d in stage_dirs(compose("config", ["scale=cpu"]))]
        changed = [d.key for d in stage_dirs(compose("config", ["scale=cpu", f"+{option}"]))]
        other_val = [d.key for d in stage_dirs(compose("config", ["scale=cpu", f"+{option}",
                                                                  "data.val=${data.test}"]))]
    first = 0 if ".flow1." in option else 1
    assert changed[:first] == plain[:first]
    assert all(a != b for a, b in zip(plain[first:], changed[first:], strict=True))
    assert (other_val == changed) == ("fresh_scenes" in option)


@pytest.mark.slow
def test_the_learned_design_trains_every_stage_keeping_its_best_nets_on_fresh_scenes(tmp_path):
    """design=learned end to end at the smoke scale (its own data loader worker): every stage run
    FINISHED, the stages with keep_best log which step they kept, and the fresh scenes that flow1
    and dm1 drew were rendered into the cache beyond the set's own scenes."""
    from demon_lab.app.job import run

    steps = [f"scale.steps.{s}={n}" for s, n in (("flow1", 8), ("dm1", 8), ("flow2", 2), ("dm2", 2), ("iterative", 2),
                                                 ("refine", 2))]
    cache = tmp_path / "scenes"
    overrides = [o for o in smoke_overrides(tmp_path) if not o.startswith("data.cache_dir=")]
    cfg = compose_config([*overrides, "design=learned", *steps, f"data.cache_dir={cache}", "threads=1",
                                         "schedule.stages.flow1.fresh_scenes=0.5", "schedule.stages.flow1.keep_best=4",
                                         "schedule.stages.dm1.keep_best=4", "schedule.stages.iterative.keep_best=1"])
    result = run(cfg)
    assert result["status"] == "finished"
    c = client(tmp_path)
    stages = c.search_runs([c.get_experiment_by_name("default").experiment_id],
                           filter_string=f"tags.`mlflow.parentRunId` = '{result['run_id']}'")
    by_stage = {r.data.tags["demon_lab.stage"]: r for r in stages}
    assert len(by_stage) == 6 and all(r.info.status == "FINISHED" for r in stages)
    figures = c.get_run(result["run_id"]).data.metrics
    for stage, metric in (("flow1", "epe"), ("dm1", "tran_deg"), ("iterative", "tran_deg")):
        assert figures[f"stage/{stage}/keep_best_step"] in ({4.0, 8.0} if stage != "iterative" else {1.0, 2.0})
        assert f"stage/{stage}/keep_best_{metric}" in figures and figures[f"stage/{stage}/keep_best_seconds"] >= 0
    assert "stage/refine/keep_best_step" not in figures
    assert result["figures"]["flow1"]["keep_best_step"] == figures["stage/flow1/keep_best_step"]
    rendered = {(p.parent.name, int(p.stem)) for p in cache.glob("synthetic/synthetic_*-*/[0-9]*.pt")}
    from demon_lab.data.datasets import SPLIT_SEEDS

    # training scenes past the sets' own
    fresh = [(name, i) for name, i in rendered if cfg.data.train_length <= i < SPLIT_SEEDS["val"]]
    # rendered ahead of the stage that first draws them
    ahead = figures["stage/flow1/fresh_scenes_rendered"] + figures.get("stage/dm1/fresh_scenes_rendered", 0)
    assert len(fresh) == ahead
    assert len(fresh) > 0


def test_the_profiles_priors_alone_are_scored_beside_the_chain_and_change_none_of_its_rows(tmp_path, monkeypatch):
    """With both bootstrap priors, the evaluation scores the priors alone (no net) as pass 'priors':
    the untrained chain's pass 0 reads the same motion (dm1's correction starts at none), so their
    motion errors agree; the chain's own rows are those of an evaluation without the priors row, digit
    for digit; a chain without the priors has no such row, nor does an oracle's."""
    from demon_lab.data.datasets import SyntheticDataset
    from demon_lab.nets.chain import DeMoN
    from demon_lab.pipeline.evaluate import evaluate_dataset, summarize
    from demon_lab.pipeline.stages.schedule import build_chain

    cfg = compose_config(smoke_overrides(tmp_path, "model.flow1_prior=dis_x2", "model.dm1_prior=ransac_prior"))
    chain = build_chain(cfg).eval()
    dataset = SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(64, 64), cache_dir=shared_renders())
    rows, _ = evaluate_dataset(chain, dataset, iterations=1)
    priors = [r for r in rows if r["it"] == "priors"]
    first = [r for r in rows if r["it"] == 0]
    assert len(priors) == 3 and [r["id"] for r in priors] == [r["id"] for r in first]
    for p, c in zip(priors, first, strict=True):
        assert p["rot_deg"] == pytest.approx(c["rot_deg"], abs=1e-3) and p["tran_deg"] == pytest.approx(c["tran_deg"],
                                                                                                          abs=1e-3)
        assert math.isfinite(p["epe"]) and math.isfinite(p["sc_inv"])
    summary = summarize(rows, 1)
    assert summary["priors/tran_deg"] == pytest.approx(sum(r["tran_deg"] for r in priors) / 3)
    monkeypatch.setattr(DeMoN, "priors_alone", lambda self, pair, intrinsics: None)
    without, _ = evaluate_dataset(chain, dataset, iterations=1)
    assert without == [r for r in rows if r["it"] != "priors"]
    monkeypatch.undo()
    assert not [r for r in evaluate_dataset(chain, dataset, iterations=0, oracle="flow")[0] if r["it"] == "priors"]
    plain = build_chain(compose_config(smoke_overrides(tmp_path))).eval()
    assert not [r for r in evaluate_dataset(plain, dataset, iterations=0)[0] if r["it"] == "priors"]


def test_a_profiled_stage_logs_its_loops_largest_parts_and_keeps_its_keys():
    """trainer.profile=true: the SimpleProfiler's actions become figures named as metrics, the largest first,
    with the time outside the batches and the loader; the option is in no key."""
    from demon_lab.pipeline import identity
    from demon_lab.pipeline.stages.training import LOOP_PARTS, loop_parts

    durations = {"run_training_epoch": [9.0], "run_training_batch": [0.5] * 10,
                 "[_TrainingEpochLoop].train_dataloader_next": [0.1] * 10,
                 "[Callback]KeepBest.on_train_batch_end": [0.0] * 9 + [1.5],
                 **{f"[LightningModule]FlowStage.hook{i}": [0.01 * i] for i in range(12)}}
    figures = loop_parts(durations, seconds=8.0)
    assert list(figures)[:3] == ["profile/run_training_batch_seconds",
                                 "profile/callback.KeepBest.on_train_batch_end_seconds",
                                 "profile/trainingepochloop.train_dataloader_next_seconds"]
    assert len(figures) == LOOP_PARTS + 1 and "profile/run_training_epoch_seconds" not in figures
    assert figures["profile/outside_seconds"] == pytest.approx(8.0 - 5.0 - 1.0)
    assert not identity.is_semantic("trainer.profile")
    assert identity.run_key(compose_config(["scale=smoke", "trainer.profile=true"])) == \
        identity.run_key(compose_config(["scale=smoke"]))
