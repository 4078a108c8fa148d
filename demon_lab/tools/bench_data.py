"""The ``data`` section of ``python -m demon_lab.bench``: synthetic pairs rendered and served per
second, 2-D layer draws per second, and DeMoN's HDF5 files decoded on the training path against the
paper-scale training step."""

from __future__ import annotations

import datetime as dt
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from demon_lab.data.throughput import demon_h5_pair_ms, demon_h5_rates, worker_counts, write_demon_layout_file
from demon_lab.reporting.tables import markdown_table
from demon_lab.tools.benchmarking import machine_line


def _render_job(args: tuple[str, int, tuple[int, int]]) -> None:
    from demon_lab.data import synthetic

    preset, seed, size = args
    synthetic.render_pair(preset, seed, size)


def bench_data(repeats: int) -> str:
    """Synthetic pairs per second: rendering on one core and with worker processes, and cached."""
    import multiprocessing as mp
    import tempfile

    from demon_lab.data import synthetic
    from demon_lab.data.datasets import SyntheticDataset
    from demon_lab.data.textures import texture_bank

    texture_bank()  # built once per process; not part of a pair's cost
    presets = sorted(synthetic.PRESETS)
    workers = max(2, min(4, os.cpu_count() or 2))
    rows = []
    for size in ((96, 128), (192, 256)):
        n = max(3, repeats) * len(presets) if size[0] < 192 else max(1, repeats // 2) * len(presets)
        jobs = [(presets[i % len(presets)], 1000 + i, size) for i in range(n)]
        start = time.perf_counter()
        for job in jobs:
            _render_job(job)
        one = n / (time.perf_counter() - start)
        with mp.get_context("spawn").Pool(workers, initializer=texture_bank) as pool:
            pool.map(_render_job, jobs[:workers])  # warm the workers up
            start = time.perf_counter()
            pool.map(_render_job, jobs)
            many = n / (time.perf_counter() - start)
        rounds = max(1, repeats // 4)
        with tempfile.TemporaryDirectory() as cache:
            # the training path (translation normalised, augmented), read from the disk cache
            # every time or kept in memory after the first read
            rates = []
            for memory_mb in (0, 1024):
                ds = SyntheticDataset(presets[0], "train", length=8, size=size, cache_dir=cache, augment=True,
                                      memory_mb=memory_mb)
                for i in range(8):
                    ds[i]  # renders into the disk cache (and keeps it, with memory)
                start = time.perf_counter()
                for r in range(rounds):
                    for i in range(8):
                        ds[(i, 8 * r + i)]
                rates.append(8 * rounds / (time.perf_counter() - start))
            cached, memory = rates
        rows.append((f"{size[1]}x{size[0]}", n, f"{one:.1f}", f"{many:.1f}", f"{cached:.0f}", f"{memory:.0f}"))
    layers = layers_rates(max(3, repeats) * 8)
    lines = [
        "## data",
        "",
        f"`python -m demon_lab.bench data` — {dt.date.today().isoformat()}, {machine_line()}.",
        "Synthetic pairs rendered per second (the three presets in turn, 2x2 supersampling, exact "
        f"visibility), on one core and with {workers} worker processes; and pairs per second served "
        "as training serves them (translation normalised, augmented with DeMoN's rotation and mirror), "
        "read back from the disk cache every time or kept in memory after the first read (the default).",
        "",
        markdown_table(["resolution", "pairs timed", "render, 1 core", f"render, {workers} workers",
                        "training path from disk cache, 1 core", "from memory, 1 core"], rows, "lrrrrr"),
        "",
        "2-D layers under affine motion (`layers_first`; `demon_lab/data/layers.py`), generated as a training "
        "draw generates them, one core: " + ", ".join(f"{rate:.0f} pairs/s at {w}x{h}" for (h, w), rate in layers)
        + ".",
        "",
        *_demon_h5_section(repeats),
    ]
    return "\n".join(lines)


def layers_rates(pairs: int, sizes: Sequence[tuple[int, int]] = ((96, 128), (192, 256))) -> list[tuple]:
    """Pairs per second of :class:`demon_lab.data.datasets.LayersDataset` draws at each size (one process)."""
    from demon_lab.data.datasets import LayersDataset

    rates = []
    for size in sizes:
        layers = LayersDataset(size)
        layers[(0, 0)]  # the texture bank, built once per process
        start = time.perf_counter()
        for i in range(pairs):
            layers[(1 + i, i)]
        rates.append((size, pairs / (time.perf_counter() - start)))
    return rates


def paper_step_rate() -> tuple[float, str]:
    """Steps/s of ``flow1``'s bare training step at scale=paper (256x192, full width, batch 32) on
    this machine's device: float32 on the CPU, bf16-mixed with channels-last on a GPU."""
    from dataclasses import replace

    from demon_lab.tools.step_rate import PAPER, step_rate

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    precision, channels_last = ("bf16-mixed", True) if device.type == "cuda" else ("32-true", False)
    rate = step_rate(device, replace(PAPER, seconds=0.0), "flow1", precision, channels_last)
    return rate["steps_per_second"], f"{device.type}, {precision}{', channels-last' if channels_last else ''}"


def _demon_h5_section(repeats: int) -> list[str]:
    import tempfile

    size, batch = (192, 256), 32
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "demon_layout.h5"
        write_demon_layout_file(path, 24, size)
        mib = path.stat().st_size / 2**20
        rates = demon_h5_rates(path, worker_counts(), batch, batches=max(2, repeats // 4), size=size,
                               pin_memory=torch.cuda.is_available())
        draw_ms, eval_ms = demon_h5_pair_ms(path, size=size)
    step, where = paper_step_rate()
    return [
        f"DeMoN's HDF5 files, the training path (`DemonH5Dataset`, train phase: WebP and LZ4 decoded, "
        f"resized to {size[1]}x{size[0]}, DeMoN's augmentation, batches of {batch} collated) through a DataLoader, "
        f"from a {mib:.1f} MiB DeMoN-layout file of 24 rendered scenes (written by `write_demon_h5`; it sits in the "
        "page cache, as a file read over and over does). The goal: decoding at least 4x the training step rate. "
        f"The step: `flow1`'s bare training step at scale=paper (256x192, full width, batch {batch}) on this "
        f"machine ({where}), {step:.3f} steps/s; on a GPU, reports/device_check.md compares with every stage. "
        f"One pair on one core: {draw_ms:.1f} ms as a training draw, {eval_ms:.1f} ms as an evaluation sample "
        "(with the flow, normals and masks a draw does not compute).",
        "",
        h5_table(rates, batch, step),
        "",
    ]


def h5_table(rates: Mapping[int, float], batch: int, step: float) -> str:
    """The HDF5 table: per loader worker count, samples/s (``rates``), batches/s of ``batch``, the
    steps/s they feed with 4x headroom, and whether that reaches ``step`` (the training step's steps/s)."""
    return markdown_table(["loader workers", "samples/s", "batches/s", "steps/s fed with 4x headroom", "4x the step"],
                          [[str(w), f"{r:.0f}", f"{r / batch:.2f}", f"{r / batch / 4:.2f}",
                            "yes" if r / batch / 4 >= step else "no"] for w, r in rates.items()], "rrrrc")
