"""Shared fixtures: the real SUN3D pair that ships with demon_lab, and small random scenes."""

from __future__ import annotations

import math
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from demon_lab.resources import DATA

SUN3D_PAIR = DATA / "sun3d_train_0.1m_to_0.2m_00000"


def pytest_configure(config):
    """Under pytest-xdist each worker, and every job it starts, gets an equal share of the cores.

    Workers that each open a thread pool as wide as the machine oversubscribe it: torch's OpenMP
    threads spin while they wait for each other, and a training test runs several times slower.
    The share reaches the jobs a test starts through the variables torch and OpenCV read at start-up
    (a variable the user set wins); a job's ``threads`` override still wins over both.
    """
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if not workers:
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    share = str(max(1, cores // int(workers)))
    for variable in ("OMP_NUM_THREADS", "OPENCV_FOR_THREADS_NUM"):
        os.environ.setdefault(variable, share)
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))

CUDA = pytest.param("cuda", id="cuda", marks=[pytest.mark.cuda, pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device on this machine: the cuda cases run on a GPU "
    "(scripts/device_check.sh runs them there)")])
DEVICES = ["cpu", CUDA]
"""Device parametrisation: the cpu case everywhere, the cuda case (marker ``cuda``) where a GPU is."""


def shared_renders() -> Path:
    """The render cache that every job the tests run shares (in the test process or a child; one per
    test process, so one per xdist worker): the smoke scenes are rendered once and read by the jobs
    after. Where scenes are cached is in no key (``demon_lab.pipeline.identity.without_render_cache``)."""
    return Path(tempfile.gettempdir()) / f"demon_lab-tests-{os.getpid()}" / "renders"


@pytest.fixture(autouse=True)
def _no_scenes_in_memory():
    """Each test starts without scenes in the process's memory (demon_lab.data.datasets.MEMORY, shared
    by every set of one render key): a test that checks what reaches its disk cache renders it there."""
    from demon_lab.data.datasets import MEMORY

    MEMORY.clear()
    yield
    MEMORY.clear()


@pytest.fixture(scope="session", autouse=True)
def _remove_shared_renders():
    yield
    shutil.rmtree(shared_renders().parent, ignore_errors=True)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def table_rows(text: str) -> list[list[str]]:
    """The lines of every Markdown (pipe) table in ``text``, header lines included, each as its cells'
    text (padding stripped, ``\\|`` unescaped); the separator lines (``|:---|--:|``) left out."""
    rows = []
    for line in text.splitlines():
        if line.startswith("|") and not re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", line.strip()):
            cells = re.split(r"(?<!\\)\|", line.strip()[1:-1])
            rows.append([c.strip().replace("\\|", "|") for c in cells])
    return rows


def table_alignment(text: str) -> list[list[str]]:
    """Each separator line's column alignment in ``text``: ``l``, ``r``, ``c`` (``:---``, ``---:``,
    ``:---:``) or ``-`` (``---``, shown left)."""
    found = []
    for line in text.splitlines():
        if line.startswith("|") and re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", line.strip()):
            marks = [m.strip() for m in line.strip()[1:-1].split("|")]
            found.append(["c" if m.startswith(":") and m.endswith(":") else "l" if m.startswith(":")
                          else "r" if m.endswith(":") else "-" for m in marks])
    return found


def relative_motion(pose1: np.ndarray, pose2: np.ndarray) -> np.ndarray:
    """World-to-camera 3x4 poses -> (4, 4) transform X2 = R12 X1 + t12 (docs/reference.md §2)."""
    r1, t1, r2, t2 = pose1[:, :3], pose1[:, 3], pose2[:, :3], pose2[:, 3]
    r12 = r2 @ r1.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r12, t2 - r12 @ t1
    return out


@pytest.fixture(scope="session")
def sun3d_pair() -> dict:
    """The real SUN3D pair: depths (480, 640) in metres (0 = invalid), K, relative pose."""
    if not SUN3D_PAIR.is_dir():
        pytest.fail(f"the real SUN3D pair is missing: {SUN3D_PAIR}")
    poses = np.loadtxt(SUN3D_PAIR / "poses.txt").reshape(-1, 3, 4)
    return {
        "depth1": np.load(SUN3D_PAIR / "0000.npy"),
        "depth2": np.load(SUN3D_PAIR / "0001.npy"),
        "K": np.loadtxt(SUN3D_PAIR / "cam.txt"),
        "T12": relative_motion(poses[0], poses[1]),
    }


def random_scene(batch: int, height: int, width: int, dtype=torch.float64, seed: int = 0):
    """A smooth random inverse-depth field (depth 1.5-6) and a well-conditioned motion."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(batch, 1, 4, 5, generator=g, dtype=torch.float64)
    inv = 1 / (1.5 + 4.5 * torch.nn.functional.interpolate(
        coarse, size=(height, width), mode="bilinear", align_corners=False))
    r = (torch.rand(batch, 3, generator=g, dtype=torch.float64) - 0.5) * 0.2
    t = torch.randn(batch, 3, generator=g, dtype=torch.float64)
    t[:, 0] += 2 * torch.sign(t[:, 0])  # mostly sideways: large triangulation angles
    t = t / t.norm(dim=1, keepdim=True) * 0.5
    intrinsics = torch.tensor([[0.89115971, 1.18821287, 0.5, 0.5]] * batch, dtype=torch.float64)
    return inv.to(dtype), torch.cat([r, t], 1).to(dtype), intrinsics.to(dtype)


def rotation_about(axis, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    return axis / np.linalg.norm(axis) * math.radians(degrees)


@pytest.fixture(scope="module")
def rendered():
    """A synthetic sample with its scene and cameras (for exact checks against the renderer), rendered once per
    test module that asks for it."""
    from data_helpers import SIZE

    from demon_lab.data import synthetic

    return synthetic.render_pair("synthetic_sun3d", 7, SIZE, supersample=1, return_scene=True)
