"""The accelerator check (scripts/device_check.sh): its dry run, as CI runs it on a CPU, exercises
every part and writes one table; a short budget skips what does not fit, with the reason."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
PARTS = ("1 tests", "2 inference", "3 train steps", "4 DeMoN HDF5 data", "5 job loop", "6 cpu profile",
         "7 torch.compile")


def _script(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable}
    return subprocess.run(["bash", str(ROOT / "scripts" / "device_check.sh"), *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _rows(text: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines()
            if re.match(r"^\| [1-7] ", line)]


@pytest.mark.slow
def test_the_dry_run_exercises_every_part_and_writes_one_table(tmp_path):
    out = tmp_path / "device_check.md"
    proc = _script("--dry-run", "--out", str(out))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    rows = _rows(out.read_text())
    assert {r[0] for r in rows} == {*PARTS, "3 full schedule"}
    assert not [r for r in rows if r[2].startswith(("failed", "skipped"))], rows
    assert {r[1] for r in rows if r[0] == "3 full schedule"} == {"32-true", "bf16-mixed, channels-last"}
    results = {(r[0], r[1]): r[2] for r in rows}
    assert re.match(r"\d+ passed", results[("1 tests", "tests/test_devices.py -m 'not cuda' on cpu")])
    stages = {r[1].split(",")[0] for r in rows if r[0] == "3 train steps"}
    assert stages == {"flow1", "dm1", "flow2", "dm2", "iterative", "refine"}
    assert all(float(r[2].split()[0]) > 0 for r in rows if r[0] in ("2 inference", "3 train steps"))
    profile = [r for r in rows if r[0] == "6 cpu profile"]
    assert profile[-1][2].startswith("6 of 6 stages")
    assert "dry run" in out.read_text()


def test_a_short_budget_skips_the_parts_that_do_not_fit(tmp_path):
    out = tmp_path / "device_check.md"
    proc = _script("--dry-run", "--budget", "1", "--out", str(out), timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = _rows(out.read_text())
    assert {r[0] for r in rows} == set(PARTS)
    skipped = [r for r in rows if r[2].startswith("skipped")]
    assert {r[0] for r in skipped} >= {"1 tests", "2 inference", "3 train steps", "4 DeMoN HDF5 data"}
    assert all("budget left" in r[2] for r in skipped if r[0] in ("1 tests", "2 inference"))


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is here: the check would run")
def test_without_a_gpu_the_real_check_refuses_in_one_line(tmp_path):
    proc = _script("--out", str(tmp_path / "x.md"), timeout=300)
    assert proc.returncode == 2 and not (tmp_path / "x.md").exists()
    assert proc.stderr.strip() == "[device_check] no CUDA device here: run it on a GPU, or pass --dry-run"
