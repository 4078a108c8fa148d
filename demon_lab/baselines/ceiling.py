"""How much camera motion a flow field carries, and how much each way of reading it loses.

For a pair's flow field (a net's flow at level 2, or the ground truth), in pixels of the flow's own
grid with view 2's end points in view 1's camera, its distances from the truth measured in pixels of
the input image (``image_px`` of them to a pixel of the flow's grid: 4 at level 2):

- :func:`precision`: the share of its vectors within 1, 2 and 4 pixels of the ground truth
  (:data:`PIXELS`; over the vectors whose truth is finite), and their median distance;
- :func:`read_motion`: the camera motion read from it by one of :data:`READERS`:

  - ``ransac``: Nister's 5-point algorithm in RANSAC on all its vectors, as Base-Mat-F reads the
    chain's flow (:func:`demon_lab.baselines.twoview.ransac_essential`);
  - ``lmeds``: the essential matrix by least median of squares on all its vectors (OpenCV's
    ``findEssentialMat`` with ``LMEDS``): no threshold, the fit for an error spread evenly rather
    than held in outliers;
  - ``pick1``, ``pick2``: the same fit on an oracle's pick, the vectors within 1 (2) pixels of the
    truth: what the flow's precise vectors carry, were a reader to find them.

:func:`ceiling` gives both for one sample, scored against its ground-truth motion with DeMoN's
motion errors (:func:`demon_lab.core.metrics.motion_errors`). A reader that finds no motion (too
few vectors, no essential matrix) gives NaN errors and counts as failed (``READER/n_failed``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from demon_lab.baselines.twoview import (
    BaselineFailure,
    pixel_intrinsics,
    pose_from_essential,
    ransac_essential,
    scaled_threshold,
    view1_pixels,
)
from demon_lab.core.metrics import motion_errors

PIXELS = (1, 2, 4)
"""The distances from the truth, in pixels of the flow's grid, whose shares :func:`precision` gives."""
READERS = ("ransac", "lmeds", "pick1", "pick2")
"""The ways :func:`read_motion` reads a motion from a flow field."""
MIN_VECTORS = 8
"""The fewest vectors a reader fits a motion to."""


def pixel_flow(flow: np.ndarray, sample: Mapping[str, Any]) -> np.ndarray:
    """A (2, h, w) flow in normalised units (DeMoN's: x by the width, y by the height) as (h, w, 2)
    pixels of its grid, its end points in view 1's camera (a sample with one camera: the flow as it is)."""
    f = np.asarray(flow, dtype=np.float64)
    _, h, w = f.shape
    px = np.stack([f[0] * w, f[1] * h], -1)
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
    end = grid + px
    moved = view1_pixels(end, sample["intrinsics"], sample.get("intrinsics2", sample["intrinsics"]), h, w)
    return px if moved is end else moved - grid


def precision(flow_px: np.ndarray, truth_px: np.ndarray, pixels: tuple[int, ...] = PIXELS,
              image_px: float = 1.0) -> dict[str, float]:
    """``within_Npx``: the share of the vectors with a finite truth whose end point lies within N pixels
    of the truth's, for each N of ``pixels``, and ``median_px``: the median of their distances (a vector
    the flow does not give is infinitely far; NaN where no vector has a finite truth); distances in
    pixels of the input, ``image_px`` to one of the flow's grid."""
    error = np.linalg.norm(flow_px - truth_px, axis=-1) * image_px
    known = np.isfinite(truth_px).all(-1)
    error = np.where(np.isfinite(error), error, np.inf)[known]
    if not error.size:
        return {**{f"within_{n}px": float("nan") for n in pixels}, "median_px": float("nan")}
    return {**{f"within_{n}px": float((error <= n).mean()) for n in pixels}, "median_px": float(np.median(error))}


def read_motion(flow_px: np.ndarray, K: np.ndarray, reader: str, truth_px: np.ndarray | None = None,
                threshold: float = 1.0, seed: int = 0, image_px: float = 1.0) -> np.ndarray:
    """The motion ``[r, t]`` (6,), unit t, that ``reader`` (:data:`READERS`) reads from ``flow_px``
    ((h, w, 2) pixels of its grid) with pixel intrinsics ``K``; ``truth_px`` (the ground-truth flow)
    for the oracle's picks, whose distances count in pixels of the input (``image_px`` to one of the
    grid); ``threshold``: the RANSAC threshold in pixels of the grid. Raises
    :class:`~demon_lab.baselines.twoview.BaselineFailure` where it finds none."""
    if reader not in READERS:
        raise ValueError(f"reader: expected one of {', '.join(READERS)}, got {reader!r}")
    h, w = flow_px.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
    use = np.isfinite(flow_px).all(-1)
    if reader.startswith("pick"):
        if truth_px is None:
            raise ValueError(f"reader {reader}: needs the ground-truth flow")
        error = np.linalg.norm(flow_px - truth_px, axis=-1) * image_px
        use &= np.isfinite(error) & (error <= int(reader.removeprefix("pick")))
    if use.sum() < MIN_VECTORS:
        raise BaselineFailure(f"{int(use.sum())} vectors to read the motion from (needs {MIN_VECTORS})")
    x1 = grid[use]
    x2 = x1 + flow_px[use]
    method = cv2.RANSAC if reader == "ransac" else cv2.LMEDS  # (each retried where OpenCV's solver aborts)
    E, inliers = ransac_essential(x1, x2, K, threshold, MIN_VECTORS, seed, method=method)
    return pose_from_essential(E, x1, x2, K, inliers)


def ceiling(flow: np.ndarray, truth: np.ndarray, sample: Mapping[str, Any], seed: int = 0,
            ransac_threshold_px: float = 1.0, image_width: int | None = None) -> dict[str, float]:
    """For one sample: the precision of ``flow`` against ``truth`` (both (2, h, w), normalised, on one
    grid) and, per reader, the rotation and translation errors of the motion it reads from ``flow``
    (``READER/rot_deg``, ``READER/tran_deg``; NaN, and ``READER/n_failed`` 1, where it reads none).
    ``ransac_threshold_px``: at 256 pixels of width, scaled to the flow's (as the baselines' is);
    ``image_width``: the input's width, whose pixels the distances from the truth count in (None: the
    flow's own grid)."""
    flow_px, truth_px = pixel_flow(flow, sample), pixel_flow(truth, sample)
    h, w = flow_px.shape[:2]
    image_px = 1.0 if image_width is None else image_width / w
    K = pixel_intrinsics(sample["intrinsics"], h, w)
    out = precision(flow_px, truth_px, image_px=image_px)
    for reader in READERS:
        try:
            motion = read_motion(flow_px, K, reader, truth_px, scaled_threshold(ransac_threshold_px, w), seed,
                                 image_px)
            errors, failed = motion_errors(motion, np.asarray(sample["motion"], dtype=np.float64)), 0.0
        except BaselineFailure:
            errors, failed = {"rot_deg": float("nan"), "tran_deg": float("nan")}, 1.0
        out.update({f"{reader}/rot_deg": errors["rot_deg"], f"{reader}/tran_deg": errors["tran_deg"],
                    f"{reader}/n_failed": failed})
    return out
