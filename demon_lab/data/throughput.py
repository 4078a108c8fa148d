"""Throughput of the data path: DeMoN-layout HDF5 files written from synthetic scenes, and the
samples per second their training path serves per loader worker count (``python -m demon_lab.bench
data`` and the device check's data part report them)."""

from __future__ import annotations

import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from demon_lab.core import geometry as geo


def write_demon_layout_file(path: Path, scenes: int, size: tuple[int, int] = (192, 256), seed: int = 0) -> None:
    """A DeMoN-layout HDF5 file (WebP images, LZ4 float16 depth; ``write_demon_h5``) of ``scenes``
    rendered synthetic pairs at ``size``: what DeMoN's training files hold, with content that
    compresses like photographs rather than like noise."""
    from demon_lab.data import synthetic
    from demon_lab.data.readers.demon_h5 import write_demon_h5

    height, width = size
    fx, fy, cx, cy = geo.DEMON_INTRINSICS
    K = np.array([[fx * width, 0, cx * width], [0, fy * height, cy * height], [0, 0, 1.0]])
    presets = sorted(synthetic.PRESETS)
    out = []
    for i in range(scenes):
        s = synthetic.render_pair(presets[i % len(presets)], seed + i, size)
        motion = np.asarray(s["motion"], dtype=np.float64)
        R2 = geo.angle_axis_to_matrix(torch.as_tensor(motion[None, :3]))[0].numpy()
        views = []
        for image, inv, R, t in ((s["image1"], s["inv_depth"], np.eye(3), np.zeros(3)),
                                 (s["image2"], s["inv_depth2"], R2, motion[3:])):
            rgb = np.floor((np.asarray(image).transpose(1, 2, 0) + 0.5) * 255 + 0.5).clip(0, 255).astype(np.uint8)
            inv = np.asarray(inv, dtype=np.float64).reshape(height, width)
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = np.where(np.isfinite(inv) & (inv > 1e-3), 1 / inv, 0.0)  # (float16 depth: <= 1000)
            views.append({"image": rgb, "depth": depth, "K": K, "R": R, "t": t})
        out.append({"name": f"scene{i:04d}", "views": views})
    write_demon_h5(path, out)


def demon_h5_rates(path: Path, workers: Sequence[int], batch_size: int = 32, batches: int = 8,
                   size: tuple[int, int] = (192, 256), pin_memory: bool = False) -> dict[int, float]:
    """Samples per second that the training path of DeMoN's files serves (``DemonH5Dataset``:
    decode WebP and LZ4, resize, DeMoN's augmentation, collate) through a DataLoader with each
    number of ``workers`` (0: the main process), in the steady state: the first ``2 x workers + 1``
    batches (the loader's prefetch, decoded while the workers start) are not timed, then at least
    ``max(batches, 4 x workers)`` are. Keys are training draws ``(index, draw)``, as the job's sampler
    deals them."""
    from torch.utils.data import DataLoader

    from demon_lab.data.datasets import DemonH5Dataset

    dataset = DemonH5Dataset(path, test_phase=False, size=size, augment=True, seed=0)
    rng = np.random.default_rng(0)
    rates = {}
    for w in workers:
        warm, timed = 2 * w + 1, max(batches, 4 * w)
        indices = rng.integers(0, len(dataset), batch_size * (warm + timed))
        sampler = [(int(i), draw) for draw, i in enumerate(indices)]
        loader = DataLoader(dataset, batch_size=batch_size, sampler=sampler, num_workers=w, pin_memory=pin_memory,
                            prefetch_factor=2 if w else None)
        it = iter(loader)
        for _ in range(warm):  # workers started, the file opened in each, their prefetched batches drained
            next(it)
        start = time.perf_counter()
        n = sum(next(it)["image1"].shape[0] for _ in range(timed))
        rates[w] = n / (time.perf_counter() - start)
        del it, loader
    return rates


def demon_h5_pair_ms(path: Path, pairs: int = 48, size: tuple[int, int] = (192, 256)) -> tuple[float, float]:
    """Milliseconds per pair on one core: a training draw (``(index, draw)``: decoded, augmented,
    without the flow, normals and masks it drops) and an evaluation sample (``index``: all of them)."""
    from demon_lab.data.datasets import DemonH5Dataset

    dataset = DemonH5Dataset(path, test_phase=False, size=size, augment=True, seed=0)
    dataset[(0, 0)]  # the file opened
    times = []
    for key in (lambda i: (i % len(dataset), i), lambda i: i % len(dataset)):
        start = time.perf_counter()
        for i in range(pairs):
            dataset[key(i)]
        times.append(1e3 * (time.perf_counter() - start) / pairs)
    return times[0], times[1]


def worker_counts() -> list[int]:
    """0 (the main process), then 1, 2, 4, ... up to this machine's cores."""
    cores = os.cpu_count() or 1
    return [0] + [w for w in (1, 2, 4, 8, 16, 32) if w <= cores]
