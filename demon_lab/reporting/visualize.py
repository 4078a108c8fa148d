"""Pictures of evaluated samples, saved as run artifacts: titled panels and coloured point clouds.

Each kept sample (``demon_lab.pipeline.evaluate``) becomes one PNG of six panels: image 1, the ground-truth
inverse depth, the prediction (both for a unit-length translation, as the network predicts and
the metrics score it; one colour scale with its bar), the absolute inverse-depth error (the
per-pixel L1-inv), the flow (hue: direction, brightness: length) and the normals. Point clouds are
ASCII PLY files of the predicted depth, coloured by image 1.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch


def safe_name(text: str) -> str:
    """A file name from a test-set name or sample id (letters, digits, ``-`` and ``_``)."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in text)


def _rgb(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) image in [-0.5, 0.5] -> (H, W, 3) uint8."""
    return ((image.permute(1, 2, 0).numpy() + 0.5) * 255).clip(0, 255).astype(np.uint8)


def _resize_nearest(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    return cv2.resize(x, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)


def flow_colours(flow: np.ndarray) -> np.ndarray:
    """(2, H, W) normalised flow -> (H, W, 3) uint8 RGB: hue the direction, value the length
    (relative to the longest vector); a non-finite vector is black."""
    import cv2

    flow = np.nan_to_num(flow)
    h, w = flow.shape[1:]
    mag, ang = cv2.cartToPolar(flow[0] * w, flow[1] * h)
    hsv = np.zeros((h, w, 3), np.uint8)
    hsv[..., 0], hsv[..., 1] = (ang * 90 / np.pi).astype(np.uint8), 255
    hsv[..., 2] = (mag / max(float(mag.max()), 1e-6) * 255).astype(np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)


def sample_figure(sample: Mapping[str, Any], title: str, out: Path) -> Path:
    """One sample's six panels (module docstring) as a PNG at ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = sample["gt_inv_depth"].numpy().astype(np.float64)
    baseline = float(torch.linalg.vector_norm(sample["gt_motion"][3:]))
    gt_unit = gt * baseline  # inverse depth for a unit-length translation, as predicted
    shape = gt.shape
    pred = _resize_nearest(sample["inv_depth"].numpy().astype(np.float32), shape).astype(np.float64)
    error = np.abs(pred - gt_unit)
    valid = np.isfinite(gt_unit) & (gt_unit > 0)
    lo, hi = (np.nanpercentile(gt_unit[valid], [1, 99]) if valid.any() else (0.0, 1.0))
    normals = _resize_nearest(((np.nan_to_num(sample["normals"].numpy().transpose(1, 2, 0)) + 1) * 127.5)
                              .clip(0, 255).astype(np.uint8), shape)
    flow = _resize_nearest(flow_colours(sample["flow"].numpy()), shape)

    fig, axes = plt.subplots(1, 6, figsize=(18, 3.1))
    panels: Sequence[tuple[str, Any, dict]] = (
        ("image 1", _rgb(sample["image1"]), {}),
        ("GT inverse depth", np.where(valid, gt_unit, np.nan), {"cmap": "magma", "vmin": lo, "vmax": hi}),
        ("predicted inverse depth", pred, {"cmap": "magma", "vmin": lo, "vmax": hi}),
        ("|error| (L1-inv)", np.where(valid, error, np.nan), {"cmap": "viridis", "vmin": 0.0,
                                                             "vmax": float(np.nanpercentile(error[valid], 99))
                                                             if valid.any() else 1.0}),
        ("flow (hue: direction, brightness: length)", flow, {}),
        ("normals (x, y, z as RGB)", normals, {}),
    )
    for ax, (name, data, style) in zip(axes, panels):
        shown = ax.imshow(data, **style)
        ax.set_title(name, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        if style:
            bar = fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
            bar.ax.tick_params(labelsize=6)
            bar.set_label("|difference| of 1 / depth" if name.startswith("|error|") else "1 / depth (unit baseline)",
                          fontsize=6)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def point_cloud(sample: Mapping[str, Any], out: Path) -> Path:
    """The predicted depth of ``sample`` as an ASCII PLY point cloud (camera 1 coordinates, unit
    baseline), coloured by image 1; pixels without positive finite inverse depth are left out."""
    import cv2

    from demon_lab.core import geometry as geo

    inv = sample["inv_depth"][None, None].double()
    h, w = inv.shape[2:]
    rays = geo._rays(h, w, sample["intrinsics"][None].double())[0]
    valid = (inv[0, 0] > 0) & torch.isfinite(inv[0, 0])
    points = (rays / inv[0]).permute(1, 2, 0)[valid].numpy()
    colours = cv2.resize(_rgb(sample["image1"]), (w, h), interpolation=cv2.INTER_AREA)[valid.numpy()]
    lines = [f"{x:.5f} {y:.5f} {z:.5f} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(points, colours)]
    header = ["ply", "format ascii 1.0", f"element vertex {len(lines)}", "property float x", "property float y",
              "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(header + lines) + "\n")
    return out


def save_visuals(root: Path, dataset: str, kept: Sequence[Mapping[str, Any]], n_images: int, n_clouds: int,
                 what: str = "") -> None:
    """``root/images/<set>_<i>_<id>.png`` for the first ``n_images`` kept samples and
    ``root/point_clouds/<set>_<i>_<id>.ply`` for the first ``n_clouds``; ``what`` (e.g. the pass
    and method) goes into each picture's title."""
    names = [safe_name(f"{dataset}_{i}_{s['id']}") for i, s in enumerate(kept)]
    for name, s in zip(names[:n_images], kept):
        sample_figure(s, f"{dataset}, sample {s['id']}" + (f": {what}" if what else ""),
                      root / "images" / f"{name}.png")
    for name, s in zip(names[:n_clouds], kept):
        point_cloud(s, root / "point_clouds" / f"{name}.ply")
