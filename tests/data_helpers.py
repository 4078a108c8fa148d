"""Helpers of the data tests: the size they render at, a sample's flow, its photometric error, a view of a scene."""

from __future__ import annotations

import numpy as np
import torch

from demon_lab.core import geometry as geo
from demon_lab.core import warping
from demon_lab.data import synthetic

SIZE = (48, 64)


def _flow_of(sample: dict) -> torch.Tensor:
    return geo.flow_from_depth_motion(sample["inv_depth"][None], sample["motion"][None],
                                      sample["intrinsics"][None], sample["intrinsics2"][None])[0]


def _photometric_error(sample: dict) -> tuple[float, float]:
    """Mean |image1 - warp(image2, GT flow)| on visible pixels, and without the warp."""
    flow = torch.nan_to_num(sample["flow"], nan=0.0)[None]
    warped = warping.warp_image(sample["image2"][None], flow)[0]
    seen = sample["visible"][0] & (warped.abs().sum(0) > 0)
    err = (warped - sample["image1"]).abs().mean(0)[seen].mean().item()
    base = (sample["image2"] - sample["image1"]).abs().mean(0)[seen].mean().item()
    return err, base


def _view_of(scene, camera, size):
    image, depth, _ = synthetic.render_view(scene, camera, size, supersample=1)
    rgb = np.floor(np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    return rgb, np.where(np.isfinite(depth), depth, 0.0)


def _pixel_K(size):
    H, W = size
    fx, fy, cx, cy = synthetic.INTRINSICS
    return np.array([[fx * W, 0, cx * W], [0, fy * H, cy * H], [0, 0, 1.0]])
