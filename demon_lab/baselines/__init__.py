"""Classical baselines scored with DeMoN's protocol (``method=base_*`` in ``python -m demon_lab``).

:func:`evaluate_baseline` runs one method over a test set and returns per-sample rows like
``demon_lab.evaluate.evaluate_dataset`` (``it = "baseline"``); a sample the method cannot handle
(too few matches, no parallax) becomes a row with ``failed`` set to the reason, counted in the
summary as ``n_failed`` and excluded from the means.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from demon_lab import metrics
from demon_lab.baselines.methods import METHODS, BaselineConfig, base_ff, base_mat_f, base_oracle, base_sift
from demon_lab.baselines.twoview import BaselineFailure

__all__ = ["METHODS", "BaselineConfig", "BaselineFailure", "evaluate_baseline", "summarize_baseline"]


@torch.no_grad()
def evaluate_baseline(method: str, dataset, cfg: BaselineConfig, chain=None, iterations: int = 3,
                      hires_dataset=None, max_samples: int | None = None,
                      keep: int = 0, histogram: metrics.PixelHistogram | None = None
                      ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per-sample metric rows of ``method`` on ``dataset`` and the first ``keep`` predictions.

    ``chain`` (a trained DeMoN) is needed by ``base_mat_f``; ``hires_dataset`` (the same samples at
    a higher resolution) by ``base_oracle``. ``histogram`` collects per-pixel depth errors.
    """
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    n = len(dataset) if max_samples is None else min(len(dataset), int(max_samples))
    rows: list[dict[str, Any]] = []
    kept: list[dict[str, Any]] = []
    protocol = metrics.protocol(dataset)
    for i in range(n):
        sample = dataset[i]
        truth = metrics.ground_truth(sample, dataset)
        truth.pop("flow")  # the baselines predict no flow: EPE is not scored
        flow = None
        try:
            if method == "base_ff":
                pred = base_ff(sample, cfg)
            elif method == "base_sift":
                pred = base_sift(sample, cfg)
            elif method == "base_mat_f":
                out = chain(sample["image1"][None], sample["image2"][None], sample["intrinsics"][None],
                            iterations=iterations)
                flow = out.passes[-1].flow[0].cpu()
                pred = base_mat_f(sample, cfg, flow)
            else:
                pred = base_oracle(sample, cfg, hires_dataset[i])
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
                         "inv_depth": torch.as_tensor(np.asarray(pred["inv_depth"], dtype=np.float32)),
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
