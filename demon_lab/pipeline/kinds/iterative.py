"""The iterative pair's stage kind (``flow2`` and ``dm2`` on DeMoN's queue)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from demon_lab.core import losses
from demon_lab.core.losses import DEPTH_MOTION_WEIGHTS, FLOW_WEIGHTS
from demon_lab.nets.chain import Prediction
from demon_lab.pipeline.config import expect_fraction, expect_int
from demon_lab.pipeline.kinds.base import (
    PRIOR_FIELDS,
    StageSpec,
    prediction_row,
    stacked_predictions,
    without_unstarted_sig,
)


@dataclass(frozen=True)
class IterativeStage(StageSpec):
    """``flow2`` and ``dm2`` trained together on DeMoN's queue of previous predictions
    (``_simulated_iterations`` of DeMoN's `training/v2/training.py`; docs/reference.md §5).

    Each step takes the batch's ``B`` new samples (their previous prediction from the frozen
    bootstrap net) plus up to ``queue_size`` samples from a FIFO queue (their previous prediction is
    their own last dm2 output); after the step the first ``queue_size`` of these, with their new dm2
    outputs, are queued. So every sample passes the iterative net several times without
    back-propagation between passes. DeMoN: 8 new + 24 queued = 32, i.e. 4 passes per sample.

    The stage starts where DeMoN's ramps have ended: every weight at full value. ``sig_start`` (a
    fraction of the stage, default 0; 1: never) holds the flow loss's sig weights at 0 until then, as
    for :class:`FlowStage`; the depth-sig weight is not affected.
    """

    kind: ClassVar[str] = "iterative"
    loss_weights: ClassVar[tuple[str, ...]] = FLOW_WEIGHTS + DEPTH_MOTION_WEIGHTS
    scores_motion: ClassVar[bool] = True
    best_metric: ClassVar[str] = "tran_deg"
    queue_size: int = 24
    """Queued samples per step, beside the batch's new ones (DeMoN: 24)."""
    sig_start: float = 0.0
    """The fraction of the stage before its flow net's sig terms ramp in (0: DeMoN's; 1: never)."""

    def weight_keys(self) -> tuple[str, ...]:
        return without_unstarted_sig(self.loss_weights, self.sig_start)

    @classmethod
    def check(cls, name: str, values: dict[str, Any]) -> None:
        super().check(name, values)
        expect_fraction(f"schedule.stages.{name}.sig_start", values["sig_start"], note=" (1: never)")
        expect_int(f"schedule.stages.{name}.queue_size", values["queue_size"], 0)

    def trained_nets(self) -> tuple[str, ...]:
        return ("flow2", "dm2")

    def validation_passes(self) -> int:
        return 1

    def loss(self, stage, batch, gt):
        pair, image2_2, K = stage.inputs(batch)
        prev = stage.bootstrap(pair, image2_2, K, batch)
        queue = stage.state.get("queue", [])
        # (a queued sample's previous prediction is its own: it needs no priors)
        samples = [({k: v[i] for k, v in batch.items() if isinstance(v, torch.Tensor) and k not in PRIOR_FIELDS},
                    prediction_row(prev, i)) for i in range(pair.shape[0])]
        combined = samples + queue[: self.queue_size]
        queue = queue[self.queue_size:]
        merged = {k: torch.stack([s[k] for s, _ in combined]) for k in combined[0][0]}
        prev_all = stacked_predictions([p for _, p in combined])
        gt_all = losses.ground_truth(merged)
        pair, image2_2, K = stage.inputs(merged)
        out = stage.chain.iterate(pair, image2_2, K, prev_all)
        flow_sig = float(stage.global_step >= self.sig_start * self.steps)
        flow_total, flow_terms = losses.flow_loss(torch.cat([out.flow5, out.conf5], 1),
                                                  torch.cat([out.flow, out.conf], 1), gt_all,
                                                  stage.weights, ramp=flow_sig, level5=0.0)
        dm_total, dm_terms = losses.depth_motion_loss(out.inv_depth, out.normals, out.motion, gt_all,
                                                      stage.weights, ramp=1.0, intrinsics=K)
        detached = Prediction(*(t.detach() for t in (out.flow, out.conf, out.flow5, out.conf5,
                                                       out.inv_depth, out.normals, out.motion)))
        stage.state["queue"] = queue + [(combined[i][0], prediction_row(detached, i))
                                        for i in range(min(self.queue_size, len(combined)))]
        return flow_total + dm_total, {**flow_terms, **dm_terms}

    def save_state(self, state: dict, checkpoint: dict) -> None:
        """The queue is training state: a resumed stage continues with the same queued samples."""
        queue = state.get("queue")
        if queue:
            keys = list(queue[0][0])
            checkpoint["demon_lab_queue"] = {
                "samples": {k: torch.stack([s[k] for s, _ in queue]) for k in keys},
                "predictions": {f: torch.stack([getattr(p, f) for _, p in queue])
                                for f in Prediction.__dataclass_fields__}}

    def load_state(self, checkpoint: dict) -> dict:
        saved = checkpoint.get("demon_lab_queue")
        if not saved:
            return {}
        n = next(iter(saved["samples"].values())).shape[0]
        rows = [Prediction(**{f: v[i] for f, v in saved["predictions"].items()}) for i in range(n)]
        preds = stacked_predictions(rows)
        return {"queue": [({k: v[i] for k, v in saved["samples"].items()}, prediction_row(preds, i)) for i in range(n)]}
