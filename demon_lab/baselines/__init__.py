"""Classical baselines scored with DeMoN's protocol (``method=base_*`` in ``python -m demon_lab``).

:func:`evaluate_baseline` runs one method over a test set and returns per-sample rows like
``demon_lab.pipeline.evaluate.evaluate_dataset`` (``it = "baseline"``); a sample the method cannot handle
(too few matches, no parallax) becomes a row with ``failed`` set to the reason, counted in the
summary as ``n_failed`` and excluded from the means.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

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
from demon_lab.core import metrics, scoring

__all__ = ["METHODS", "BaselineConfig", "BaselineFailure", "evaluate_baseline", "get_method", "summarize_baseline"]


def get_method(name: str) -> Callable[..., tuple[dict[str, Any], torch.Tensor | None]]:
    """The classical method ``name`` as one call: ``predict(pair, sample, cfg, chain, iterations)`` returns
    its prediction (``inv_depth``, ``motion``) and the flow it read, if any (``base_mat_f``: the chain's,
    on ``sample``), or raises :class:`BaselineFailure`; ``pair`` is the sample at the resolution the
    method reads (``sample`` itself by default)."""
    if name not in PREDICTORS:
        raise ValueError(f"method: expected one of {METHODS}, got {name!r}")
    return PREDICTORS[name]


def _with_chain_flow(sample, cfg: BaselineConfig, chain, iterations: int):
    out = chain(sample["image1"][None], sample["image2"][None], sample["intrinsics"][None], iterations=iterations)
    flow = out.passes[-1].flow[0].cpu()
    return base_mat_f(sample, cfg, flow), flow


PREDICTORS: dict[str, Callable[..., tuple[dict[str, Any], torch.Tensor | None]]] = {
    "base_ff": lambda pair, sample, cfg, chain, iterations: (base_ff(pair, cfg), None),
    "base_sift": lambda pair, sample, cfg, chain, iterations: (base_sift(pair, cfg), None),
    "base_5pt": lambda pair, sample, cfg, chain, iterations: (base_5pt(pair, cfg), None),
    "base_mat_f": lambda pair, sample, cfg, chain, iterations: _with_chain_flow(sample, cfg, chain, iterations),
    "base_oracle": lambda pair, sample, cfg, chain, iterations: (base_oracle(pair, cfg), None),
}
"""The classical methods by name (:data:`METHODS`), each as :func:`get_method` hands it out."""


@torch.no_grad()
def evaluate_baseline(method: str, dataset, cfg: BaselineConfig, chain=None, iterations: int = 3,
                      inputs=None, max_samples: int | None = None,
                      keep: int = 0, histogram: metrics.PixelHistogram | None = None
                      ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per-sample metric rows of ``method`` on ``dataset`` and the first ``keep`` predictions, scored by
    :func:`demon_lab.core.scoring.score`.

    ``inputs``: the same pairs at the resolution the method reads them at (default ``dataset``;
    ``demon_lab.pipeline.evaluate.baseline_inputs``); every prediction is scored on ``dataset``'s ground truth.
    ``chain`` (a trained DeMoN) is needed by ``base_mat_f``, which reads its flow on ``dataset``'s
    pairs. ``histogram`` collects per-pixel depth errors.
    """
    predict = get_method(method)
    n = len(dataset) if max_samples is None else min(len(dataset), int(max_samples))
    inputs = dataset if inputs is None else inputs
    if len(inputs) != len(dataset):
        raise ValueError(f"inputs: expected the {len(dataset)} pairs of the test set, got {len(inputs)}")

    def predictions() -> Iterator[scoring.Prediction]:
        for i in range(n):
            sample = dataset[i]
            pair = sample if inputs is dataset else inputs[i]
            try:
                pred, flow = predict(pair, sample, cfg, chain, iterations)
            except BaselineFailure as e:
                yield scoring.Prediction(sample, {"baseline": str(e)}, "baseline", reports_failures=True)
                continue
            yield scoring.Prediction(sample, {"baseline": {"inv_depth": pred["inv_depth"], "motion": pred["motion"]}},
                                     "baseline", flow=flow, reports_failures=True)

    return scoring.score(dataset, predictions(), keep, histogram)


def summarize_baseline(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Means over the samples the method handled, plus ``n_failed`` and ``n_samples``."""
    ok = [{k: v for k, v in r.items() if k not in ("it", "failed", "id")} for r in rows if not r["failed"]]
    out = {k: v for k, v in metrics.summarize(ok).items() if not k.startswith("n_failed")} if ok else {}
    out["n_failed"] = float(sum(1 for r in rows if r["failed"]))
    out["n_samples"] = float(len(rows))
    return out
