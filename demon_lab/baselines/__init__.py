"""Classical baselines scored with DeMoN's protocol (``method=base_*`` in ``python -m demon_lab``).

:func:`evaluate_baseline` runs one method over a test set and returns per-sample rows like
``demon_lab.pipeline.evaluate.evaluate_dataset`` (``it = "baseline"``); a sample the method cannot handle
(too few matches, no parallax) becomes a row with ``failed`` set to the reason, counted in the
summary as ``n_failed`` and excluded from the means.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from demon_lab.baselines.methods import (
    METHODS,
    BaselineConfig,
    base_5pt,
    base_ff,
    base_mat_f,
    base_oracle,
    base_sift,
)
from demon_lab.baselines.twoview import BaselineFailure
from demon_lab.core import metrics

__all__ = ["METHODS", "BaselineConfig", "BaselineFailure", "evaluate_baseline", "summarize_baseline"]


@torch.no_grad()
def evaluate_baseline(method: str, dataset, cfg: BaselineConfig, chain=None, iterations: int = 3,
                      inputs=None, max_samples: int | None = None,
                      keep: int = 0, histogram: metrics.PixelHistogram | None = None
                      ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per-sample metric rows of ``method`` on ``dataset`` and the first ``keep`` predictions.

    ``inputs``: the same pairs at the resolution the method reads them at (default ``dataset``;
    ``demon_lab.pipeline.evaluate.baseline_inputs``); every prediction is scored on ``dataset``'s ground truth.
    ``chain`` (a trained DeMoN) is needed by ``base_mat_f``, which reads its flow on ``dataset``'s
    pairs. ``histogram`` collects per-pixel depth errors.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    n = len(dataset) if max_samples is None else min(len(dataset), int(max_samples))
    rows: list[dict[str, Any]] = []
    kept: list[dict[str, Any]] = []
    protocol = metrics.protocol(dataset)
    inputs = dataset if inputs is None else inputs
    if len(inputs) != len(dataset):
        raise ValueError(f"inputs: expected the {len(dataset)} pairs of the test set, got {len(inputs)}")
    for i in range(n):
        sample = dataset[i]
        pair = sample if inputs is dataset else inputs[i]
        truth = metrics.ground_truth(sample, dataset)
        truth.pop("flow")  # the baselines predict no flow: EPE is not scored
        flow = None
        try:
            if method == "base_ff":
                pred = base_ff(pair, cfg)
            elif method == "base_sift":
                pred = base_sift(pair, cfg)
            elif method == "base_5pt":
                pred = base_5pt(pair, cfg)
            elif method == "base_mat_f":
                out = chain(sample["image1"][None], sample["image2"][None], sample["intrinsics"][None],
                            iterations=iterations)
                flow = out.passes[-1].flow[0].cpu()
                pred = base_mat_f(sample, cfg, flow)
            else:
                pred = base_oracle(pair, cfg)
        except BaselineFailure as e:
            rows.append({"id": sample["id"], "it": "baseline", "failed": str(e)})
            continue
        scores = metrics.evaluate_sample({"inv_depth": pred["inv_depth"], "motion": pred["motion"]}, truth, **protocol)
        rows.append({"id": sample["id"], "it": "baseline", "failed": "", **scores})
        if histogram is not None:
            histogram.add(metrics.pixel_depth_errors({"inv_depth": pred["inv_depth"]}, truth, **protocol))
        if len(kept) < keep:
            kept.append({"id": sample["id"], "image1": sample["image1"], "gt_inv_depth": sample["inv_depth"][0],
                         "gt_motion": sample["motion"],
                         "inv_depth": torch.as_tensor(metrics.resize_nearest(  # shown beside image 1
                             pred["inv_depth"], tuple(sample["inv_depth"].shape[1:])).astype(np.float32)),
                         "flow": flow if flow is not None else torch.zeros(2, *sample["inv_depth"].shape[1:]),
                         "normals": torch.zeros(3, *sample["inv_depth"].shape[1:]),
                         "intrinsics": sample["intrinsics"]})
    return rows, kept


def summarize_baseline(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Means over the samples the method handled, plus ``n_failed`` and ``n_samples``."""
    ok = [{k: v for k, v in r.items() if k not in ("it", "failed", "id")} for r in rows if not r["failed"]]
    out = {k: v for k, v in metrics.summarize(ok).items() if not k.startswith("n_failed")} if ok else {}
    out["n_failed"] = float(sum(1 for r in rows if r["failed"]))
    out["n_samples"] = float(len(rows))
    return out
