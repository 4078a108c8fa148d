"""The DPSNet/DeepSFM folder layout of DeMoN's data: one folder per image sequence.

``0000.jpg, 0001.jpg, ...`` RGB images; ``0000.npy, ...`` float32 (H, W) camera-z depth in metres
(0 = invalid); ``cam.txt`` the 3x3 pixel K; ``poses.txt`` one line per view with the 12 numbers
of the row-major 3x4 world-to-camera ``[R|t]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from demon_lab.data.readers.common import inverse, normalised_intrinsics, read_rgb, relative_motion
from demon_lab.data.sample import DataError, Sample, make_sample


def find_pair_folders(root: str | Path) -> list[Path]:
    """``root`` itself if it is a pair folder (has ``cam.txt``), else its pair-folder children."""
    root = Path(root)
    if not root.exists():
        raise DataError(f"{root}: no such file or directory")
    if (root / "cam.txt").is_file():
        return [root]
    folders = sorted(p for p in root.iterdir() if (p / "cam.txt").is_file())
    if not folders:
        raise DataError(f"{root}: no pair folder (a folder with cam.txt, poses.txt, 0000.jpg, ...)")
    return folders


def _load_txt(path: Path, shape: tuple[int, ...] | None = None) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        a = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise DataError(f"{path}: not a table of numbers ({e})") from None
    if shape is not None and a.shape != shape:
        raise DataError(f"{path}: expected {shape[0]}x{shape[1]} numbers, got {a.shape[0]}x{a.shape[1]}")
    if not np.isfinite(a).all():
        raise DataError(f"{path}: contains non-finite numbers")
    return a


def _load_depth(path: Path, shape: tuple[int, int]) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        depth = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise DataError(f"{path}: not a readable .npy depth map ({e})") from None
    if depth.shape != shape:
        raise DataError(f"{path}: depth has shape {depth.shape}, the image {shape}")
    return depth


def read_pair_folder(path: str | Path, pair: tuple[int, int] = (0, 1)) -> Sample:
    """The sample of views ``pair`` of one folder, at the images' native resolution."""
    path = Path(path)
    a, b = pair
    K = _load_txt(path / "cam.txt", (3, 3))
    poses = _load_txt(path / "poses.txt")
    if poses.shape[1] != 12 or poses.shape[0] <= max(a, b):
        raise DataError(f"{path / 'poses.txt'}: expected a line of 12 numbers per view, "
                        f"got shape {poses.shape}")
    images = [read_rgb(path / f"{k:04d}.jpg") for k in (a, b)]
    if images[0].shape != images[1].shape:
        raise DataError(f"{path}: {a:04d}.jpg and {b:04d}.jpg differ in size")
    height, width = images[0].shape[:2]
    depths = [_load_depth(path / f"{k:04d}.npy", (height, width)) for k in (a, b)]
    (R1, t1), (R2, t2) = ((poses[k].reshape(3, 4)[:, :3], poses[k].reshape(3, 4)[:, 3]) for k in (a, b))
    k = normalised_intrinsics(K, width, height)
    return make_sample(f"{path.name}/{a:04d}-{b:04d}", images[0], images[1], k, inverse(depths[0]),
                       relative_motion(R1, t1, R2, t2), inv_depth2=inverse(depths[1]))
