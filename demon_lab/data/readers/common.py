"""Pieces shared by the readers: pixel intrinsics to normalised ones, relative motion, images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from demon_lab.core import geometry as geo
from demon_lab.data.sample import DataError


def normalised_intrinsics(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """3x3 pixel K (pixel centres at +0.5, as DeMoN) -> (fx/W, fy/H, cx/W, cy/H)."""
    return np.array([K[0, 0] / width, K[1, 1] / height, K[0, 2] / width, K[1, 2] / height])


def relative_motion(R1: np.ndarray, t1: np.ndarray, R2: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """World-to-camera poses -> (6,) [r, t] with X2 = R X1 + t: R = R2 R1^T, t = t2 - R t1."""
    R = R2 @ R1.T
    t = t2 - R @ t1
    r = geo.matrix_to_angle_axis(torch.from_numpy(R.astype(np.float64))[None])[0].numpy()
    return np.concatenate([r, t])


def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB; a one-line DataError for a missing or undecodable file."""
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    image = cv2.imdecode(np.fromfile(str(path), dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise DataError(f"{path}: not a readable image (corrupt or unsupported format)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def inverse(depth: np.ndarray) -> np.ndarray:
    """Absolute depth (0/NaN/negative = invalid) -> inverse depth with NaN for invalid."""
    depth = depth.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.isfinite(depth) & (depth > 0), 1.0 / depth, np.nan).astype(np.float32)
