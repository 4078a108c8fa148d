"""Checkpoints survive kills, bad checkpoints are one-line errors, runs never stay RUNNING."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from demon_lab.stages.cache import CheckpointError, atomic_torch_save, load_checkpoint
from tests.test_pipeline import cli, client, compose_config, smoke_overrides

WRITER = """
import sys, torch
from demon_lab.stages.cache import atomic_torch_save
path, i = sys.argv[1], 0
while True:
    i += 1
    atomic_torch_save({"step": i, "weights": torch.full((4_000_000,), float(i))}, path)
    print(i, flush=True)
"""


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
    from demon_lab.train import stage_dirs

    return [d.weights for d in stage_dirs(compose_config(smoke_overrides(tmp, *extra)))]


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
