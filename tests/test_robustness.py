"""Checkpoints survive kills, bad checkpoints are one-line errors, runs never stay RUNNING."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from demon_lab.pipeline.stages.cache import CheckpointError, atomic_torch_save, load_checkpoint
from demon_lab.pipeline.tracking import version_tags
from tests.jobs import cli, client, compose_config, settings, smoke_overrides

WRITER = """
import sys, torch
from demon_lab.pipeline.stages.cache import atomic_torch_save
path, i = sys.argv[1], 0
while True:
    i += 1
    atomic_torch_save({"step": i, "weights": torch.full((4_000_000,), float(i))}, path)
    print(i, flush=True)
"""


@pytest.mark.slow
def test_a_kill_during_a_save_never_leaves_a_torn_checkpoint(tmp_path):
    """A real process saving 16 MB checkpoints in a loop is SIGKILLed at 8 moments; each time the
    file on disk loads and is one complete save."""
    path = tmp_path / "last.ckpt"
    for delay in (0.35, 0.5, 0.65, 0.8, 0.95, 1.1, 1.25, 1.4):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout is not None
        proc.stdout.readline()  # at least one complete save exists
        time.sleep(delay - 0.3)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        state = load_checkpoint(path)
        assert torch.equal(state["weights"], torch.full((4_000_000,), float(state["step"])))


def test_truncated_and_foreign_checkpoints_are_one_line_errors(tmp_path):
    path = tmp_path / "weights.pt"
    atomic_torch_save({"flow1": {"w": torch.ones(3)}}, path)
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_checkpoint(path)
    path.write_bytes(b"import os; os.system('echo pwned')")  # not a checkpoint at all
    with pytest.raises(CheckpointError, match="cannot be read"):
        load_checkpoint(path)


def _stage_weights(tmp: Path, *extra: str) -> list[Path]:
    from demon_lab.pipeline.stages.schedule import stage_dirs

    return [d.weights for d in stage_dirs(settings(compose_config(smoke_overrides(tmp, *extra))))]


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "other_architecture"])
def test_a_bad_cached_stage_fails_the_job_in_one_line(tmp_path, damage):
    first = cli(*smoke_overrides(tmp_path, "schedule.until=dm1", "iterations=0"), cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    weights = _stage_weights(tmp_path, "schedule.until=dm1", "iterations=0")[-1]
    if damage == "truncated":
        weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    else:  # the dm1 weights of a wider chain
        from demon_lab.nets.chain import DeMoN

        atomic_torch_save({"dm1": DeMoN("v1", 0.125, (64, 64)).dm1.state_dict()}, weights)
    again = cli(*smoke_overrides(tmp_path, "schedule.until=dm1", "iterations=0", "force=true"), cwd=tmp_path)
    lines = again.stderr.strip().splitlines()
    assert again.returncode == 2 and len(lines) == 1, again.stderr[-2000:]
    assert ("cannot be read" if damage == "truncated" else "does not fit") in lines[0]
    statuses = [r.info.status for r in client(tmp_path).search_runs(
        [client(tmp_path).get_experiment_by_name("default").experiment_id])]
    assert "RUNNING" not in statuses and statuses.count("FAILED") == 1


def _metrics(tmp: Path) -> tuple[str, str, dict[str, float]]:
    c = client(tmp)
    runs = [r for r in c.search_runs([c.get_experiment_by_name("default").experiment_id])
            if r.data.tags.get("demon_lab.kind") != "stage"]
    assert len(runs) == 1, [r.info.status for r in runs]
    return runs[0].info.run_id, runs[0].info.status, {k: v for k, v in runs[0].data.metrics.items()
                                                      if k.startswith("test/")}


KILL_POINTS = {
    # name: (overrides, what to wait for: a checkpoint glob or a line the job prints)
    "flow1 training": (["scale.steps.flow1=60", "schedule.until=flow1", "iterations=0"], "flow1-*/last.ckpt"),
    "iterative training": (["scale.steps.iterative=40", "schedule.until=iterative"], "iterative-*/last.ckpt"),
    "evaluation": (["schedule.until=flow1", "iterations=0"], "[demon_lab] evaluating on synthetic_sun3d"),
    # between the test metrics and the artifacts (_HOLD_AFTER_METRICS holds the job there)
    "final logging": (["schedule.until=flow1", "iterations=0"], "[demon_lab] paused at metrics_logged"),
}

_HOLD_AFTER_METRICS = """
import time
import demon_lab.reporting.tables

def _held(*args, **kwargs):  # the job's first call after logging its test metrics
    print("[demon_lab] paused at metrics_logged", flush=True)
    time.sleep(3600)

demon_lab.reporting.tables.results_table = _held
"""
"""A ``sitecustomize`` module for the job's process: it holds the job between its test metrics and its
artifacts, where the job builds its results table, without a hook in demon_lab itself."""


def _kill_when(args: list[str], cwd: Path, trigger: str) -> None:
    """Start the job and SIGKILL it when ``trigger`` (a checkpoint glob under the stage cache, or
    text in a line of its output) appears."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if trigger.endswith("paused at metrics_logged"):
        hook = cwd / "hold_after_metrics"
        hook.mkdir(exist_ok=True)
        (hook / "sitecustomize.py").write_text(_HOLD_AFTER_METRICS)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(hook), env.get("PYTHONPATH")) if p)
    proc = subprocess.Popen([sys.executable, "-m", "demon_lab", *args], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert proc.stdout is not None
    if not trigger.endswith(".ckpt"):
        for line in proc.stdout:
            if trigger in line:
                break
    else:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            if list((cwd / "cache" / "stages").glob(trigger)):
                time.sleep(0.5)
                break
            time.sleep(0.1)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stdout.close()


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The uninterrupted run of a job, once per set of overrides (kill points share them)."""
    done: dict[tuple[str, ...], Path] = {}

    def get(extra: list[str]) -> Path:
        if tuple(extra) not in done:
            root = tmp_path_factory.mktemp("uninterrupted")
            clean = cli(*smoke_overrides(root, *extra), cwd=root)
            assert clean.returncode == 0, clean.stderr[-2000:]
            done[tuple(extra)] = root
        return done[tuple(extra)]

    return get


@pytest.mark.slow
@pytest.mark.parametrize("point", list(KILL_POINTS))
def test_a_killed_job_resumes_into_its_run_with_the_uninterrupted_result(tmp_path, point, uninterrupted):
    """SIGKILL at a point of the job (a stage's training, evaluation, the final logging), the same
    command again: the job resumes (a stage from its last checkpoint, with the same batches and
    the same iterative-net queue) into the same MLflow run, which ends FINISHED with exactly the
    metrics and weights of an uninterrupted run."""
    overrides, trigger = KILL_POINTS[point]
    extra = [*overrides, "scale.checkpoint_every=5", "eval.max_samples=1"]
    clean = uninterrupted(extra)
    (tmp_path / "b").mkdir()
    args = smoke_overrides(tmp_path / "b", *extra)
    _kill_when(args, tmp_path / "b", trigger)
    killed_id, status, _ = _metrics(tmp_path / "b")
    assert status == "RUNNING"  # what a kill leaves behind
    # As if the killed attempt ran older code: the resumed run is tagged with the code that finishes it.
    client(tmp_path / "b").delete_tag(killed_id, "demon_lab.generator_version")
    client(tmp_path / "b").set_tag(killed_id, "mlflow.source.git.commit", "an-older-commit")

    again = cli(*args, cwd=tmp_path / "b")
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"resuming the interrupted run {killed_id}" in again.stdout
    stage = trigger.split("-")[0] if trigger.endswith(".ckpt") else None
    if stage:
        assert f"resuming stage {stage} from step" in again.stdout
    run_id, status, resumed = _metrics(tmp_path / "b")
    _, _, reference = _metrics(clean)
    assert run_id == killed_id and status == "FINISHED"
    assert resumed == reference and len(reference) > 10
    tags = client(tmp_path / "b").get_run(run_id).data.tags
    assert all(tags.get(k) == v for k, v in version_tags().items())
    assert tags.get("mlflow.source.git.commit") == _commit_of_the_job_command()

    def weights(root: Path) -> dict:
        stages = (root / "cache" / "stages").glob("*/weights.pt")
        return {p.parent.name.split("-")[0]: load_checkpoint(p) for p in stages}

    a, b = weights(clean), weights(tmp_path / "b")
    assert a.keys() == b.keys()
    assert all(torch.equal(a[s][net][k], b[s][net][k]) for s in a for net in a[s] for k in a[s][net])


SWEEP = ["schedule.until=flow1", "iterations=0", "eval.max_samples=1"]


def _jobs_and_parents(tmp: Path):
    c = client(tmp)
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    return ([r for r in runs if "demon_lab.run_key" in r.data.tags],
            [r for r in runs if r.data.tags.get("demon_lab.kind") == "sweep"])


@pytest.mark.slow
def test_a_failing_job_does_not_stop_the_sweep(tmp_path):
    """A job whose loss turns NaN (learning rate 1e30): one line naming the stage, step and terms,
    its run FAILED with the error and traceback, the other job still runs; the sweep exits
    non-zero, names the failed job and its parent run is FAILED."""
    args = ["-m", *smoke_overrides(tmp_path, *SWEEP), "scale.steps.flow1=4", "schedule.stages.flow1.lr=1e30,2.5e-4"]
    result = cli(*args, cwd=tmp_path)
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 2 and "Traceback" not in result.stderr, result.stderr[-3000:]
    assert "stage flow1: non-finite loss at step" in errors[0] and "flow2=nan" in errors[0]
    assert "1 job(s) of the sweep failed" in errors[1] and "lr=1e+30" in errors[1]
    rows = result.stdout.split("the sweep's jobs on ")[1].splitlines()[3:5]
    assert [row.split()[:2] for row in rows] == [["1e+30", "FAILED"], ["0.00025", "finished"]]
    jobs, (parent,) = _jobs_and_parents(tmp_path)
    by_status = {r.info.status: r for r in jobs}
    assert sorted(by_status) == ["FAILED", "FINISHED"] and len(jobs) == 2
    failed = by_status["FAILED"]
    assert "non-finite loss" in failed.data.tags["demon_lab.error"]
    assert failed.data.params["schedule.stages.flow1.lr"] == "1e+30"
    text = Path(client(tmp_path).download_artifacts(failed.info.run_id, "error.txt")).read_text()
    assert "Traceback" in text and "TrainingDiverged" in text
    assert parent.info.status == "FAILED"
    assert all(r.data.tags["mlflow.parentRunId"] == parent.info.run_id for r in jobs)


@pytest.mark.slow
def test_a_killed_sweep_reissued_completes_only_the_missing_jobs(tmp_path):
    """SIGKILL a three-job sweep after its first job finished, issue it again: the finished job is
    skipped, the interrupted one resumes into its run, the third runs; three job runs in all, all
    FINISHED and all children of the one parent run."""
    # (one thread in both: the count the nets compute with is in the run keys, and the library's
    # default differs between machines)
    args = ["-m", *smoke_overrides(tmp_path, *SWEEP), "seed=0,1,2", "threads=1"]
    _kill_when(args, tmp_path, "[HYDRA] \t#1 : ")  # the first job is FINISHED, the second starts
    jobs, parents = _jobs_and_parents(tmp_path)
    assert len(parents) == 1 and [r.info.status for r in jobs].count("FINISHED") <= 1

    again = cli(*args, "data.num_workers=0", cwd=tmp_path)  # another loader setting: still the same sweep
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"continuing the sweep run {parents[0].info.run_id}" in again.stdout
    assert again.stdout.count("skipped: run key") == 1
    jobs, (parent,) = _jobs_and_parents(tmp_path)
    assert sorted(r.data.tags["demon_lab.seed"] for r in jobs) == ["0", "1", "2"]
    assert all(r.info.status == "FINISHED" for r in jobs) and parent.info.status == "FINISHED"
    assert all(r.data.tags["mlflow.parentRunId"] == parent.info.run_id for r in jobs)


def test_sweep_verdict_does_not_count_failed_attempts_of_jobs_that_finished_since(tmp_path, caplog):
    """A job's first attempt FAILED (a crash, a SIGTERM), a later attempt FINISHED: the sweep's
    closing line counts one finished job and no failed one, and names the earlier attempt."""
    from omegaconf import OmegaConf

    from demon_lab.app.callbacks import MultirunTracking
    from demon_lab.pipeline.tracking import TAG, Tracker

    tracker = Tracker(f"sqlite:///{tmp_path}/mlflow.db", "default", str(tmp_path / "artifacts"))
    parent = tracker.start("sweep", {f"{TAG}kind": "sweep"})
    first = tracker.start("job", {f"{TAG}run_key": "k0"}, parent_id=parent)
    tracker.fail(first, RuntimeError("SIGTERMException"))
    tracker.finish(tracker.start("job", {f"{TAG}run_key": "k0"}, parent_id=parent), "FINISHED")
    tracker.fail(tracker.start("job", {f"{TAG}run_key": "k1"}, parent_id=parent), RuntimeError("bad data"))
    callback = MultirunTracking()
    callback.tracker, callback.parent = tracker, parent
    with caplog.at_level(logging.INFO, logger="demon_lab"):
        callback.on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path / "sweep")}}}))
    line = caplog.messages[-1]
    assert line.endswith("1 job runs FINISHED, 1 FAILED (1 earlier FAILED attempt(s) of jobs that have since FINISHED)")


def test_the_sweep_verdict_reads_its_own_jobs_records_not_an_earlier_sweeps(tmp_path, monkeypatch, capsys):
    """Each job leaves its outcome in its sweep's own folder of records (``on_job_end``, in the job's
    process, whatever the launcher), one file per job, even where two jobs share an output folder; the
    sweep's end reads its own: an error.txt or a FAILED record that an earlier sweep left is not a
    failure of this one, a job that returned FAILED is, listed by its folder, and so is a job Hydra
    ended FAILED; the table of its jobs is in launch order; the parent run ends FAILED and the sweep
    exits 1."""
    from hydra.core.utils import JobReturn, JobStatus
    from omegaconf import OmegaConf

    from demon_lab.app.callbacks import MultirunTracking
    from demon_lab.app.sweep import records_dir
    from demon_lab.pipeline.tracking import TAG, Tracker

    monkeypatch.chdir(tmp_path)
    sweep = tmp_path / "multirun" / "default"

    def returned(num: int, status: str | None, folder: str = "", hydra_status=JobStatus.COMPLETED) -> JobReturn:
        output = sweep / (folder or f"seed={num}")
        hydra_cfg = OmegaConf.create({"hydra": {"runtime": {"output_dir": str(output)}, "job": {"num": num}}})
        job = JobReturn(overrides=[f"seed={num}"], hydra_cfg=hydra_cfg, status=hydra_status,
                        cfg=OmegaConf.create({"method": "demon", "iterations": 0,
                                              "trainer": {"devices": 1, "num_nodes": 1}}))
        job._return_value = {"status": status, "run_id": None}
        return job

    earlier = MultirunTracking()  # an earlier sweep in the same folder: its seed=2 failed
    earlier.records = records_dir("multirun/default", "earlier")
    earlier.on_job_end(None, returned(2, "FAILED"))
    (sweep / "seed=2").mkdir(parents=True, exist_ok=True)
    (sweep / "seed=2" / "error.txt").write_text("Traceback (an earlier sweep's)\n")
    tracker = Tracker(f"sqlite:///{tmp_path}/mlflow.db", "default", str(tmp_path / "artifacts"))
    callback = MultirunTracking()
    callback.tracker, callback.parent = tracker, tracker.start("sweep", {f"{TAG}kind": "sweep"})
    callback.records = records_dir("multirun/default", "this")
    # (a parallel launcher ends them in any order; jobs 3 and 4 share a folder, as a sweep over threads does)
    for job in (returned(2, None), returned(0, None), returned(1, "FAILED"), returned(4, None, "threads"),
                returned(3, None, "threads", hydra_status=JobStatus.FAILED)):
        callback.on_job_end(None, job)
    config = OmegaConf.create({"experiment": "no_study", "hydra": {"sweep": {"dir": "multirun/default"}}})
    with pytest.raises(SystemExit) as exited:
        callback.on_multirun_end(config)
    assert exited.value.code == 1
    assert not callback.records.exists() and earlier.records.is_dir()  # its own records read and cleared
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == [
        "error: 2 job(s) of the sweep failed (each folder has error.txt): multirun/default/seed=1; "
        "multirun/default/threads"]
    table = captured.out.split("the sweep's jobs on ")[1].splitlines()
    assert table[1].split()[:2] == ["seed", "status"]
    assert [line.split()[:2] for line in table[3:8]] == [["0", "-"], ["1", "FAILED"], ["2", "-"], ["3", "FAILED"],
                                                         ["4", "-"]]
    parent = tracker.client.get_run(callback.parent)
    assert parent.info.status == "FAILED" and parent.data.tags[f"{TAG}jobs_failed_now"] == "2"


def _commit_of_the_job_command() -> str | None:
    """The commit a ``python -m demon_lab`` run is tagged with: that of the checkout holding demon_lab's
    code (None outside a checkout)."""
    from mlflow.utils.git_utils import get_git_commit

    import demon_lab

    return get_git_commit(str(Path(demon_lab.__file__).with_name("__main__.py")))


def test_runs_carry_mlflow_source_tags_and_a_resumed_run_is_re_tagged(tmp_path):
    """Every run gets MLflow's context tags, as mlflow.start_run gives them (the caller's tags win);
    resuming re-tags the run with the source that finishes it and drops git tags it no longer has."""
    from demon_lab.pipeline.tracking import TAG, Tracker, source_tags

    tracker = Tracker(f"sqlite:///{tmp_path}/mlflow.db", "default", str(tmp_path / "artifacts"))
    run_id = tracker.start("job", {f"{TAG}run_key": "k0", "mlflow.user": "someone"})
    tags = tracker.client.get_run(run_id).data.tags
    assert tags["mlflow.source.name"] == source_tags()["mlflow.source.name"] and tags["mlflow.user"] == "someone"
    tracker.set_tags(run_id, {"mlflow.source.git.commit": "an-older-commit", "mlflow.source.git.branch": "old",
                              f"{TAG}git_commit": "an-older-commit"})  # the tag demon_lab wrote before
    tracker.resume(run_id)
    tags = tracker.client.get_run(run_id).data.tags
    source = source_tags()
    assert tags[f"{TAG}resumed"] == "1" and tags["mlflow.user"] == source["mlflow.user"]
    for key in ("mlflow.source.git.commit", "mlflow.source.git.branch"):
        assert tags.get(key) == source.get(key)
    assert f"{TAG}git_commit" not in tags



def test_a_resumed_run_keeps_its_first_parameters_and_tags_the_values_that_changed(tmp_path):
    """MLflow refuses to change a logged parameter; a job resumed from another install (package data
    at another path, outside the run key) keeps the first values, tags the new ones, adds new keys."""
    from demon_lab.pipeline.tracking import TAG, Tracker

    tracker = Tracker(f"sqlite:///{tmp_path}/mlflow.db", "default", str(tmp_path / "artifacts"))
    run_id = tracker.start("job", {f"{TAG}run_key": "k0"})
    tracker.log_params(run_id, {"data.real_pair": "/old/site-packages/pair", "seed": "0"})
    tracker.resume(run_id)
    tracker.log_params(run_id, {"data.real_pair": "/new/site-packages/pair", "seed": "0", "threads": "2"})
    data = tracker.client.get_run(run_id).data
    assert data.params == {"data.real_pair": "/old/site-packages/pair", "seed": "0", "threads": "2"}
    assert data.tags[f"{TAG}resumed_param.data.real_pair"] == "/new/site-packages/pair"
    assert f"{TAG}resumed_param.seed" not in data.tags

def _pair_folder(tmp: Path, damage: str) -> Path:
    """A copy of the shipped SUN3D pair with one defect."""
    import shutil

    import numpy as np

    from tests.conftest import SUN3D_PAIR

    folder = tmp / f"pair_{damage}"
    shutil.copytree(SUN3D_PAIR, folder)
    if damage == "corrupt_image":
        (folder / "0000.jpg").write_bytes(b"\xff\xd8 this is not a JPEG")
    elif damage == "nan_depth":
        depth = np.load(folder / "0000.npy")
        np.save(folder / "0000.npy", np.full_like(depth, np.nan))
    elif damage == "zero_baseline":
        poses = (folder / "poses.txt").read_text().strip().splitlines()
        (folder / "poses.txt").write_text("\n".join([poses[0], poses[0]]) + "\n")
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("damage, message", [
    ("missing", "no such file or directory"),
    ("corrupt_image", "not a readable image"),
    ("nan_depth", "has no valid pixel"),
    ("zero_baseline", "zero baseline"),
    ("corrupt_hdf5", "not a readable HDF5 file"),
    ("tracking_typo", "tracking.uri"),
])
def test_bad_input_is_one_line_and_leaves_no_running_run(tmp_path, damage, message):
    if damage == "corrupt_hdf5":
        bad = tmp_path / "scenes.h5"
        bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 64)  # an HDF5 signature and nothing else
        data = ["data=demon_h5", f"data.path={bad}"]
    elif damage == "missing":
        data = ["data=pair_folder", f"data.path={tmp_path / 'no_such_folder'}"]
    elif damage == "tracking_typo":
        data = []
    else:
        data = ["data=pair_folder", f"data.path={_pair_folder(tmp_path, damage)}"]
    args = [*smoke_overrides(tmp_path, *data), "data.size=[64,64]", "schedule.until=flow1", "iterations=0"]
    if damage == "tracking_typo":
        args.append("tracking.uri=sqlit:///mlflow.db")
    result = cli(*args, cwd=tmp_path)
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1 and message in lines[0], result.stderr[-3000:]
    assert lines[0].startswith("error: ")
    if (tmp_path / "mlflow.db").exists():
        c = client(tmp_path)
        runs = [r for e in c.search_experiments() for r in c.search_runs([e.experiment_id])]
        assert all(r.info.status != "RUNNING" for r in runs)


@pytest.mark.slow
def test_the_same_config_and_seed_give_identical_metrics_on_cpu(tmp_path):
    """Two independent runs (own caches and stores) of the same job: every final metric equal."""
    extra = ["schedule.until=dm1", "iterations=0", "eval.max_samples=2"]
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        result = cli(*smoke_overrides(tmp_path / name, *extra), cwd=tmp_path / name)
        assert result.returncode == 0, result.stderr[-2000:]
    _, _, a = _metrics(tmp_path / "a")
    _, _, b = _metrics(tmp_path / "b")
    assert len(a) > 20 and a == b


def test_sweep_key_follows_what_the_jobs_compute_and_the_versions(monkeypatch):

    from demon_lab.data import synthetic
    from demon_lab.pipeline.identity import sweep_key

    def key(*overrides: str) -> str:
        return sweep_key("study", list(overrides))

    base = key("seed=0,1", "+experiment=study")
    assert key("seed=0,1", "+experiment=study", "threads=1", "tracking=local_server") == base
    assert key("seed=0,1,2", "+experiment=study") != base
    monkeypatch.setattr(synthetic, "generator_version", lambda: synthetic.GENERATOR_VERSION + 1)
    assert key("seed=0,1", "+experiment=study") != base  # new scenes: a new parent run


@pytest.mark.slow
def test_a_stage_that_diverges_fails_its_own_run_not_the_finished_stages_before_it(tmp_path):
    """flow1 trains and is cached, dm1's loss turns NaN: the job and dm1's stage run are FAILED with
    the error, flow1's stage run stays FINISHED (Lightning's logger ended it so)."""
    result = cli(*smoke_overrides(tmp_path), "scale.steps.dm1=4", "schedule.stages.dm1.lr=1e30", cwd=tmp_path)
    assert result.returncode == 2 and "stage dm1: non-finite loss" in result.stderr, result.stderr[-2000:]
    c = client(tmp_path)
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    stages = {r.data.tags["demon_lab.stage"]: r for r in runs if r.data.tags.get("demon_lab.kind") == "stage"}
    assert set(stages) == {"flow1", "dm1"}
    assert stages["flow1"].info.status == "FINISHED" and "demon_lab.error" not in stages["flow1"].data.tags
    assert stages["dm1"].info.status == "FAILED" and "non-finite loss" in stages["dm1"].data.tags["demon_lab.error"]
    (job,) = [r for r in runs if "demon_lab.run_key" in r.data.tags]
    assert job.info.status == "FAILED"


def test_a_bad_config_is_refused_before_lightning_or_mlflow_is_imported(tmp_path):
    """A job whose config fails its checks exits with its one line having loaded neither Lightning nor MLflow
    (the job's imports of training and tracking come after the checks)."""
    import subprocess
    import sys

    probe = ("import atexit, runpy, sys\n"
             "atexit.register(lambda: print('LOADED', sorted({m.split('.')[0] for m in sys.modules} & "
             "{'lightning', 'mlflow'})))\n"
             "sys.argv = ['demon_lab', 'scale=smoke', 'model.width=-1']\n"
             "runpy.run_module('demon_lab', run_name='__main__')\n")
    done = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == "error: model.width: expected a positive number, got -1"
    assert "LOADED []" in done.stdout
