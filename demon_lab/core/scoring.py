"""One test set scored with DeMoN's protocol, whatever predicted it: the one loop that turns a
method's predictions into per-sample metric rows, the pixel-error histogram of its final depth and
the samples kept for pictures (:func:`score`). The chain
(:func:`demon_lab.pipeline.evaluate.evaluate_dataset`) and the classical methods
(:func:`demon_lab.baselines.evaluate_baseline`) each only say what they predicted
(:class:`Prediction`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from demon_lab.core import metrics


@dataclass
class Prediction:
    """One test pair as a method predicted it.

    ``sample``: the pair with its ground truth (unbatched tensors and its ``id``); ``groups``: each
    row group (``it``: pass 0..N, ``refined``, ``priors``, ``baseline``) and its prediction
    (``inv_depth``, ``motion``, optionally ``flow``: scored where given), or the reason the method
    could not predict it (a row with ``failed`` set, left out of the means); ``final``: the group
    whose depth is the method's answer (the histogram, the pictures); ``flow``, ``normals``: what the
    pictures show beside it (zeros where None); ``reports_failures``: whether its rows carry a
    ``failed`` column (the classical methods', empty where they predicted)."""

    sample: dict[str, Any]
    groups: dict[Any, dict[str, Any] | str]
    final: Any
    flow: torch.Tensor | None = None
    normals: torch.Tensor | None = None
    reports_failures: bool = False


def picture(sample: dict[str, Any], inv_depth: Any, flow: torch.Tensor | None = None,
            normals: torch.Tensor | None = None) -> dict[str, Any]:
    """What the job keeps of a scored pair for its pictures: image 1, the ground truth, the predicted
    inverse depth (a classical method's, at any resolution, resized to the ground truth's nearest
    neighbour), flow and normals (zeros where the method predicts none)."""
    shape = tuple(sample["inv_depth"].shape[1:])
    if isinstance(inv_depth, np.ndarray):
        inv_depth = torch.as_tensor(metrics.resize_nearest(inv_depth, shape).astype(np.float32))
    return {"id": sample["id"], "image1": sample["image1"], "gt_inv_depth": sample["inv_depth"][0],
            "gt_motion": sample["motion"], "inv_depth": inv_depth,
            "flow": flow if flow is not None else torch.zeros(2, *shape),
            "normals": normals if normals is not None else torch.zeros(3, *shape),
            "intrinsics": sample["intrinsics"]}


def score(dataset: Any, predictions: Iterable[Prediction], keep: int = 0,
          histogram: metrics.PixelHistogram | None = None) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per-sample metric rows (one per pair and group, in the groups' order) of ``predictions`` on
    ``dataset``'s ground truth and protocol, and the pictures of the first ``keep`` pairs; the
    per-pixel errors of each pair's final depth go into ``histogram``."""
    protocol = metrics.protocol(dataset)
    rows: list[dict[str, Any]] = []
    kept: list[dict[str, Any]] = []
    for p in predictions:
        truth = metrics.ground_truth(p.sample, dataset)
        for group, pred in p.groups.items():
            row = {"id": p.sample["id"], "it": group}
            if isinstance(pred, str):
                rows.append({**row, "failed": pred})
                continue
            failed = {"failed": ""} if p.reports_failures else {}
            rows.append({**row, **failed, **metrics.evaluate_sample(pred, truth, **protocol)})
        final = p.groups[p.final]
        if isinstance(final, str):
            continue
        if histogram is not None:
            histogram.add(metrics.pixel_depth_errors({"inv_depth": final["inv_depth"]}, truth, **protocol))
        if len(kept) < keep:
            kept.append(picture(p.sample, final["inv_depth"], p.flow, p.normals))
    return rows, kept
