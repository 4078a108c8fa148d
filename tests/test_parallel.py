"""Parallel jobs and the tracking store: joblib sweeps on SQLite, concurrent writers, the local
tracking server and an unreachable one."""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import pytest

from tests.conftest import free_port
from tests.jobs import cli, client, smoke_overrides

WRITER = """
import sys, time
from pathlib import Path
from demon_lab.pipeline.tracking import Tracker
uri, worker, count, gate = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
while not gate.exists():  # every writer opens the fresh store at the same moment
    time.sleep(0.01)
tracker = Tracker(uri, "stress", Path(uri[len("sqlite:///"):]).parent / "artifacts")
run = tracker.start(f"writer-{worker}", {"demon_lab.kind": "stress"})
for step in range(count):
    tracker.log_metrics(run, {"value": float(worker * count + step)}, step=step)
tracker.finish(run)
"""


@pytest.mark.slow
def test_parallel_writers_on_a_fresh_sqlite_store_lose_nothing(tmp_path):
    """N processes open a store that does not exist yet at the same moment and log M metrics each
    through demon_lab's tracking layer: N x M values are stored, no process fails."""
    n, m = 4, 250
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    gate = tmp_path / "go"
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, uri, str(i), str(m), str(gate)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(n)]
    time.sleep(3.0)  # let every interpreter import and wait at the gate
    gate.touch()
    outputs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-1500:] for _, err in outputs]
    c = client(tmp_path)
    runs = c.search_runs([c.get_experiment_by_name("stress").experiment_id])
    assert len(runs) == n and all(r.info.status == "FINISHED" for r in runs)
    stored = {(int(r.info.run_name.split("-")[1]), h.step): h.value
              for r in runs for h in c.get_metric_history(r.info.run_id, "value")}
    assert len(stored) == n * m
    assert all(v == w * m + s for (w, s), v in stored.items())


@pytest.mark.slow
def test_joblib_sweep_on_the_default_sqlite_store(tmp_path):
    """Three jobs, three at a time, on a store created by the sweep: every run FINISHED with all
    its metrics, one parent run holding them."""
    args = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=3", *smoke_overrides(tmp_path),
            "seed=0,1,2", "schedule.until=flow1", "iterations=0", "eval.max_samples=1"]
    result = cli(*args, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "database is locked" not in result.stderr
    c = client(tmp_path)
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    (parent,) = [r for r in runs if r.data.tags.get("demon_lab.kind") == "sweep"]
    jobs = [r for r in runs if "demon_lab.run_key" in r.data.tags]
    assert sorted(r.data.tags["demon_lab.seed"] for r in jobs) == ["0", "1", "2"]
    assert all(r.info.status == "FINISHED" for r in runs)
    assert all(r.data.tags["mlflow.parentRunId"] == parent.info.run_id for r in jobs)
    counts = {len([k for k in r.data.metrics if k.startswith("test/")]) for r in jobs}
    assert len(counts) == 1 and counts.pop() > 20  # every job stored the same, complete set
    stages = [r for r in runs if r.data.tags.get("demon_lab.kind") == "stage"]
    assert len(stages) == 3 and all(c.get_metric_history(r.info.run_id, "train/loss") for r in stages)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.slow
@pytest.mark.parametrize("sweep", [[], ["-m", "hydra/launcher=joblib", "seed=0,1"]], ids=["job", "joblib_sweep"])
def test_local_server_serves_the_command_on_loopback_and_stops(tmp_path, sweep):
    """One server per command: a job starts its own; a sweep's process starts one and its jobs (in
    joblib's processes) log through it."""
    port = free_port()
    args = [*sweep, *smoke_overrides(tmp_path), "tracking=local_server", f"tracking.server.port={port}",
            f"tracking.server.backend_store_uri=sqlite:///{tmp_path}/mlflow.db",
            "schedule.until=flow1", "iterations=0", "eval.max_samples=1"]
    result = cli(*args, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count(f"MLflow server on http://127.0.0.1:{port}") == 1
    assert not _listening(port)  # stopped with the command
    c = client(tmp_path)  # the runs are in the SQLite store behind the server, readable without it
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    jobs = [r for r in runs if "demon_lab.run_key" in r.data.tags]
    assert len(jobs) == (2 if sweep else 1) and all(r.info.status == "FINISHED" for r in jobs)
    assert all(any(a.path == "config.yaml" for a in c.list_artifacts(r.info.run_id)) for r in jobs)


@pytest.mark.slow
def test_an_unreachable_tracking_server_fails_before_any_work(tmp_path):
    port = free_port()  # nothing listens there
    result = cli(*smoke_overrides(tmp_path), f"tracking.uri=http://127.0.0.1:{port}", "schedule.until=flow1",
                 "iterations=0", cwd=tmp_path)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr[-3000:]
    assert "tracking server does not answer" in lines[0] and str(port) in lines[0]
    assert "training stage" not in result.stdout and not (tmp_path / "cache").exists()


def test_launcher_workers_get_no_store_client():
    """The sweep callback travels to joblib/submitit workers pickled, without its client, and hands
    the parent run to the job there (on_job_start, in the job's process) until the job ends."""
    import pickle

    from demon_lab.app import job
    from demon_lab.app.callbacks import MultirunTracking

    callback = MultirunTracking()
    callback.tracker, callback.parent = object(), "abc"
    callback.server, callback.served = object(), "http://127.0.0.1:5055"
    copy = pickle.loads(pickle.dumps(callback))
    assert copy.tracker is None and copy.server is None and copy.parent == "abc"
    assert job._parent_run() is None and job.SWEEP_SERVER.get() is None
    copy.on_job_start(config=None, task_function=job.main_task)
    assert job._parent_run() == "abc" and job.SWEEP_SERVER.get() == "http://127.0.0.1:5055"
    copy.on_job_end(config=None, job_return=None)
    assert job._parent_run() is None and job.SWEEP_SERVER.get() is None



@pytest.mark.slow
def test_two_process_ddp_on_the_cpu_trains_like_one_process(tmp_path):
    """``trainer.devices=2`` on the CPU (gloo): Lightning starts the second process by re-running
    the command; rank 1 only trains, rank 0 tracks, saves and evaluates. Each process takes half of
    every batch and gradients are averaged, so the stage's weights equal a one-process run's.

    One step: Adam's first update is ``lr * g / (|g| + eps)``, so an element whose gradient sits at
    float32's rounding floor (level 5's at this size: conv over a batch of 1 or of 2 rounds
    differently, by CPU) moves by a fraction of ``lr``, and over more steps those elements diverge as
    a chaotic system does. Training on half the batch (one sample instead of two) moves about half of
    all elements by more than ``lr / 10`` in this one step; the rounding moves at most a few by more
    than 1e-5."""
    import torch

    lr = 2.5e-4  # flow1's rate in the released schedule that the smoke scale takes
    common = ["schedule.until=flow1", "iterations=0", "eval.max_samples=1", "trainer.accelerator=cpu",
              "scale.steps.flow1=1", f"schedule.stages.flow1.lr={lr}"]
    weights = {}
    for devices in (1, 2):
        tmp = tmp_path / f"devices{devices}"
        tmp.mkdir()
        result = cli(*smoke_overrides(tmp), *common, f"trainer.devices={devices}", cwd=tmp)
        assert result.returncode == 0, result.stderr[-3000:]
        assert result.stdout.count("[demon_lab] results") == 1  # rank 0 alone evaluates and reports
        c = client(tmp)
        runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
        jobs = [r for r in runs if "demon_lab.run_key" in r.data.tags]
        assert len(jobs) == 1 and all(r.info.status == "FINISHED" for r in runs)
        (saved,) = (tmp / "cache" / "stages").glob("flow1-*/weights.pt")
        weights[devices] = torch.load(saved, weights_only=True)["flow1"]
    assert weights[1].keys() == weights[2].keys()
    differences = torch.cat([(weights[2][name] - value).abs().flatten() for name, value in weights[1].items()])
    print(f"DDP against one process after one step: largest difference {float(differences.max()):.2e}, "
          f"{int((differences > 1e-5).sum())} of {differences.numel()} elements beyond 1e-5")
    assert float(differences.max()) < lr / 10
    assert int((differences > 1e-5).sum()) <= differences.numel() // 1000


def test_a_local_sweep_refuses_several_devices_per_job(tmp_path):
    """Lightning's launcher would re-run the whole sweep in each extra process: refused before any work."""
    result = cli("-m", *smoke_overrides(tmp_path), "seed=0,1", "trainer.devices=2", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "error: trainer.devices x trainer.num_nodes = 2 in a sweep with hydra/launcher=basic: use "
        "hydra/launcher=slurm_ddp (or torchrun), or one device per job"]
    assert not (tmp_path / "mlflow.db").exists()
