"""TUM RGB-D sequences (Sturm et al., IROS 2012): ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``.

``rgb.txt`` / ``depth.txt``: ``timestamp path`` per line; depth PNGs are 16-bit, metres x 5000,
0 = invalid. ``groundtruth.txt``: ``timestamp tx ty tz qx qy qz qw``, the camera-to-world pose.
Frames are associated by nearest timestamp (within ``max_dt`` seconds, like TUM's
``associate.py``); pairs are sampled in order: for every ``stride``-th frame the first later
frame whose baseline lies in ``[min_baseline, max_baseline]`` metres.

Intrinsics: pass ``intrinsics=(fx, fy, cx, cy)`` in pixels, or they are taken from the
sequence's name (``freiburg1/2/3``) with TUM's published values, else ROS's default. TUM's (and
ROS's) principal points count pixel centres at integers; DeMoN's at +0.5, so 0.5 is added.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from demon_lab.core import geometry as geo
from demon_lab.data.readers.common import inverse, read_rgb, relative_motion
from demon_lab.data.sample import DataError, Sample, make_sample

TUM_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
ROS_DEFAULT = (525.0, 525.0, 319.5, 239.5)
DEPTH_SCALE = 5000.0


def _read_list(path: Path, columns: int) -> list[list[str]]:
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) < columns:
            raise DataError(f"{path}:{n}: expected {columns} columns, got {len(parts)}")
        rows.append(parts)
    if not rows:
        raise DataError(f"{path}: no entries")
    return rows


def _nearest(times: np.ndarray, t: float, max_dt: float) -> int | None:
    i = int(np.searchsorted(times, t))
    best = min((j for j in (i - 1, i) if 0 <= j < len(times)), key=lambda j: abs(times[j] - t))
    return best if abs(times[best] - t) <= max_dt else None


def _pose(values: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """TUM camera-to-world (t, q) -> world-to-camera (R, t)."""
    c = np.asarray(values[:3], dtype=np.float64)
    qx, qy, qz, qw = (float(v) for v in values[3:7])
    n = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not n > 0:
        raise DataError(f"groundtruth: zero quaternion {values}")
    qx, qy, qz, qw = qx / n, qy / n, qz / n, qw / n
    R_cw = np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])
    return R_cw.T, -R_cw.T @ c


def _intrinsics(root: Path, intrinsics: Sequence[float] | None) -> tuple[float, float, float, float]:
    if intrinsics is not None:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        return fx, fy, cx, cy
    for key, value in TUM_INTRINSICS.items():
        if key in str(root.resolve()):
            return value
    return ROS_DEFAULT


def read_tum_pairs(
    root: str | Path,
    min_baseline: float = 0.05,
    max_baseline: float = 0.5,
    stride: int = 10,
    max_gap: int = 60,
    max_dt: float = 0.02,
) -> list[tuple[dict, dict]]:
    """Associated frames paired by baseline: a list of (frame_a, frame_b) dicts with ``rgb``,
    ``depth`` (paths), ``R``, ``t`` (world-to-camera) and ``time``."""
    root = Path(root)
    rgb = _read_list(root / "rgb.txt", 2)
    depth = _read_list(root / "depth.txt", 2)
    gt = _read_list(root / "groundtruth.txt", 8)
    depth_t = np.array([float(r[0]) for r in depth])
    gt_t = np.array([float(r[0]) for r in gt])
    order_d, order_g = np.argsort(depth_t), np.argsort(gt_t)
    depth_t, gt_t = depth_t[order_d], gt_t[order_g]
    frames = []
    for row in rgb:
        t = float(row[0])
        jd, jg = _nearest(depth_t, t, max_dt), _nearest(gt_t, t, max_dt)
        if jd is None or jg is None:
            continue
        R, tr = _pose([float(v) for v in gt[order_g[jg]][1:8]])
        frames.append({"time": t, "rgb": root / row[1], "depth": root / depth[order_d[jd]][1],
                       "R": R, "t": tr, "center": -R.T @ tr})
    if len(frames) < 2:
        raise DataError(f"{root}: fewer than 2 frames with RGB, depth and pose within {max_dt} s")
    pairs = []
    for i in range(0, len(frames), max(1, stride)):
        for j in range(i + 1, min(len(frames), i + 1 + max_gap)):
            baseline = float(np.linalg.norm(frames[j]["center"] - frames[i]["center"]))
            if min_baseline <= baseline <= max_baseline:
                pairs.append((frames[i], frames[j]))
                break
    return pairs


def _read_depth_png(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2 or raw.dtype != np.uint16:
        raise DataError(f"{path}: not a 16-bit single-channel depth PNG")
    return raw.astype(np.float64) / DEPTH_SCALE


def load_tum_pair(root: str | Path, frames: tuple[dict, dict],
                  intrinsics: Sequence[float] | None = None) -> Sample:
    a, b = frames
    images = [read_rgb(f["rgb"]) for f in (a, b)]
    depths = [_read_depth_png(f["depth"]) for f in (a, b)]
    height, width = images[0].shape[:2]
    for f, d in zip((a, b), depths):
        if d.shape != (height, width):
            raise DataError(f"{f['depth']}: depth is {d.shape[1]}x{d.shape[0]}, the image {width}x{height}")
    fx, fy, cx, cy = _intrinsics(Path(root), intrinsics)
    k = np.array([fx / width, fy / height, (cx + 0.5) / width, (cy + 0.5) / height])
    return make_sample(f"{Path(root).name}/{a['time']:.6f}-{b['time']:.6f}", images[0], images[1], k,
                       inverse(depths[0]), relative_motion(a["R"], a["t"], b["R"], b["t"]),
                       inv_depth2=inverse(depths[1]))


def write_tum_sequence(root: str | Path, frames: Sequence[dict], start: float = 1305031102.0,
                       rate: float = 30.0) -> None:
    """Write frames in the TUM layout (for tests and for converting data).

    Each frame: ``image`` (H, W, 3) uint8 RGB, ``depth`` (H, W) metres (0 invalid), ``R``, ``t``
    world-to-camera.
    """
    root = Path(root)
    (root / "rgb").mkdir(parents=True, exist_ok=True)
    (root / "depth").mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines, gt_lines = ["# color images"], ["# depth maps"], ["# ground truth"]
    for k, f in enumerate(frames):
        t = start + k / rate
        name = f"{t:.6f}.png"
        cv2.imwrite(str(root / "rgb" / name), cv2.cvtColor(f["image"], cv2.COLOR_RGB2BGR))
        depth = np.clip(np.round(np.asarray(f["depth"]) * DEPTH_SCALE), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(root / "depth" / name), depth)
        rgb_lines.append(f"{t:.6f} rgb/{name}")
        depth_lines.append(f"{t + 0.003:.6f} depth/{name}")  # TUM's streams are not synchronous
        R, tr = np.asarray(f["R"], dtype=np.float64), np.asarray(f["t"], dtype=np.float64)
        center = -R.T @ tr
        w, x, y, z = geo.matrix_to_quaternion(torch.from_numpy(R.T)[None])[0].tolist()
        gt_lines.append(f"{t + 0.001:.6f} " + " ".join(f"{v:.9f}" for v in (*center, x, y, z, w)))
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines), ("groundtruth.txt", gt_lines)):
        (root / name).write_text("\n".join(lines) + "\n")
