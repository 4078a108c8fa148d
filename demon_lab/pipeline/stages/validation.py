"""Held-apart metrics on a stage's training curves: every ``tracking.val_every_n_steps`` steps
(and at the stage's last step) the chain runs on the data's validation sets (``data.val``: the
synthetic_sun3d validation scenes in the default mix) and the stage's MLflow run gets

- ``val/<set>/epe``: end-point error of the flow of the pass the stage trains (level 2,
  normalised units, against the ground truth the loss uses; ``val/<set>/zero_flow_epe`` is the
  error of predicting no flow, once);
- ``val/<set>/rot_deg``, ``val/<set>/tran_deg``: DeMoN's motion errors of that pass, when the stage
  trains a depth-motion net (dm1, dm2, iterative);
- ``val/<set>/l1_inv``: L1 of the inverse depth at level 2 (refine: the refined depth at level 0).

It reads the chain in eval mode without gradients and puts the trained nets back in training
mode: training itself is unchanged (bit for bit; ``tests/test_pipeline.py``). The pass scored is
the one the stage trains: the bootstrap pass for flow1 and dm1, the first iterative pass for
flow2, dm2 and iterative, and for refine the refinement of the pass its training uses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import lightning as L
import torch

from demon_lab.core import losses, metrics
from demon_lab.pipeline.evaluate import run_chain

MOTION_STAGES = ("dm1", "dm2", "iterative")


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return sum(finite) / len(finite) if finite else math.nan


class StageValidation(L.Callback):
    """Logs the held-apart metrics of one stage (see the module docstring)."""

    def __init__(self, stage: str, datasets: Sequence, every_n_steps: int, iterations: int, batch_size: int = 8):
        self.stage, self.datasets, self.iterations = stage, list(datasets), int(iterations)
        self.every, self.batch_size = int(every_n_steps), int(batch_size)
        self._zero_logged = False

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if trainer.logger is None or not self.datasets or self.every <= 0:
            return
        if step % self.every and step < trainer.max_steps:
            return
        chain = module.chain
        was_training = {name: net.training for name, net in module.nets()}
        chain_training = chain.training
        chain.eval()
        try:
            values = {}
            for dataset in self.datasets:
                scores = self._scores(chain, dataset, getattr(module, "channels_last", False),
                                      trainer.precision_plugin.precision)
                values.update({f"val/{dataset.name}/{k}": v for k, v in scores.items()})
        finally:
            chain.training = chain_training  # the container's own flag, then each net's
            for name, net in module.nets():
                net.train(was_training[name])
        if not self._zero_logged:
            self._zero_logged = True
        else:
            values = {k: v for k, v in values.items() if not k.endswith("zero_flow_epe")}
        trainer.logger.log_metrics({k: v for k, v in values.items() if math.isfinite(v)}, step=step)

    def _scores(self, chain, dataset, channels_last: bool = False, precision: Any = 32) -> dict[str, float]:
        """The module docstring's metrics on ``dataset``, the chain's nets in ``precision`` (the stage's)."""
        rows: dict[str, list[float]] = {"epe": [], "zero_flow_epe": [], "rot_deg": [], "tran_deg": [], "l1_inv": []}
        loader = torch.utils.data.DataLoader(dataset, batch_size=self.batch_size, shuffle=False)
        for _, b, out in run_chain(chain, loader, self.iterations, precision=precision, channels_last=channels_last,
                                   refine=self.stage == "refine"):
            p = out.passes[-1]
            gt = losses.ground_truth(b)
            error = (p.flow - gt["flow2"]).norm(dim=1)
            zero = gt["flow2"].norm(dim=1)
            for i in range(p.flow.shape[0]):
                rows["epe"].append(float(error[i][torch.isfinite(error[i])].mean()))
                rows["zero_flow_epe"].append(float(zero[i][torch.isfinite(zero[i])].mean()))
                if self.stage in MOTION_STAGES:
                    motion = metrics.motion_errors(p.motion[i].cpu(), b["motion"][i].cpu())
                    rows["rot_deg"].append(motion["rot_deg"])
                    rows["tran_deg"].append(motion["tran_deg"])
            if self.stage == "refine":
                depth, target = out.refined, gt["inv_depth0"]
            elif self.stage in MOTION_STAGES:
                depth, target = p.inv_depth, gt["inv_depth2"]
            else:
                continue
            diff = (depth[:, :1] - target).abs()
            for i in range(p.flow.shape[0]):
                rows["l1_inv"].append(float(diff[i][torch.isfinite(diff[i])].mean()))
        return {k: _mean(v) for k, v in rows.items() if v}
