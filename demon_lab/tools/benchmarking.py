"""Timing helpers of the benchmark sections (:mod:`demon_lab.tools.bench`): the median time of a
call, and the line that names the machine a table was measured on."""

from __future__ import annotations

import os
import platform
from collections.abc import Callable

import torch

BLOCK_S = 0.05
"""Seconds of timing per unit of ``--repeats`` in :func:`measure` (the geometry section's)."""


def measure(fn: Callable[[], object], repeats: int = 20, block_s: float = BLOCK_S) -> float:
    """Median seconds per call of ``fn``: ``torch.utils.benchmark.Timer.blocked_autorange`` on this
    process's torch threads, timing for at least ``repeats`` x ``block_s`` seconds (the timer picks
    the calls per block so that its own overhead is negligible, after a warm-up call)."""
    from torch.utils import benchmark

    timer = benchmark.Timer("fn()", globals={"fn": fn}, num_threads=torch.get_num_threads())
    return timer.blocked_autorange(min_run_time=repeats * block_s).median


def machine_line() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (f"{cpu}; {os.cpu_count()} cores, torch {torch.__version__} with "
            f"{torch.get_num_threads()} threads")
