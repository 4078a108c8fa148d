"""Held-apart metrics on a stage's training curves: every ``tracking.val_every_n_steps`` steps
(and at the stage's last step) the chain runs on the data's validation sets (``data.val``: the
synthetic_sun3d validation scenes in the default mix) and the stage's MLflow run gets

- ``val/<set>/epe``: end-point error of the flow of the pass the stage trains (level 2,
  normalised units, against the ground truth the loss uses; ``val/<set>/zero_flow_epe`` is the
  error of predicting no flow, once);
- ``val/<set>/rot_deg``, ``val/<set>/tran_deg``: DeMoN's motion errors of that pass, when the stage
  trains a depth-motion net (its kind's ``scores_motion``: dm1, dm2, iterative);
- ``val/<set>/l1_inv``: L1 of the inverse depth at level 2 (refine: the refined depth at level 0).

The same scores choose a stage's kept nets with the stage option ``keep_best`` (:class:`KeepBest`).

It reads the chain in eval mode without gradients and puts the trained nets back in training
mode: training itself is unchanged (bit for bit; ``tests/test_pipeline.py``). The held-apart pairs are
loaded once per stage, with the chain's classical priors of each pair where it reads any (the
``cpu`` profile's DIS flow and its RANSAC motion: functions of the pair alone,
:class:`demon_lab.pipeline.stages.priors.PairPriors`), so a scoring runs the nets only. The pass scored is
the one the stage trains: the bootstrap pass for flow1 and dm1, the first iterative pass for
flow2, dm2 and iterative, and for refine the refinement of the pass its training uses.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from typing import Any

import lightning as L
import torch

from demon_lab.core import losses, metrics
from demon_lab.pipeline.evaluate import run_chain
from demon_lab.pipeline.kinds import StageSpec


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return sum(finite) / len(finite) if finite else math.nan


class StageValidation(L.Callback):
    """Logs the held-apart metrics of one stage (see the module docstring)."""

    def __init__(self, spec: StageSpec, datasets: Sequence, every_n_steps: int, iterations: int | None = None,
                 batch_size: int = 8):
        """``spec``: the stage scored (its kind says what: :class:`demon_lab.pipeline.kinds.StageSpec`);
        ``iterations``: the passes the chain runs (None: the stage's own, ``spec.validation_passes()``)."""
        self.spec, self.datasets = spec, list(datasets)
        self.iterations = spec.validation_passes() if iterations is None else int(iterations)
        self.every, self.batch_size = int(every_n_steps), int(batch_size)
        self._zero_logged = False
        self._last: tuple[int, dict[str, float]] | None = None
        self._batches: dict[int, list[dict[str, Any]]] = {}  # each set's batches, with their priors
        self.last_seconds = 0.0  # what scoring the last scored step took (whichever callback asked first)

    def due(self, trainer) -> bool:
        """Whether this step is one to score: every ``every_n_steps`` and the stage's last."""
        step = trainer.global_step
        return bool(self.datasets) and self.every > 0 and (step % self.every == 0 or step >= trainer.max_steps)

    def evaluate(self, trainer, module) -> dict[str, float]:
        """``val/<set>/<metric>`` of the chain as it is now; the nets go back to their modes. Scored
        once per step (the curves and :class:`KeepBest` share a step's scores)."""
        if self._last is not None and self._last[0] == trainer.global_step:
            return dict(self._last[1])
        start = time.perf_counter()
        chain = module.chain
        was_training = {name: net.training for name, net in module.nets()}
        chain_training = chain.training
        chain.eval()
        try:
            values = {}
            for which, dataset in enumerate(self.datasets):
                scores = self._scores(chain, self.batches(chain, which), getattr(module, "channels_last", False),
                                      trainer.precision_plugin.precision)
                values.update({f"val/{dataset.name}/{k}": v for k, v in scores.items()})
        finally:
            chain.training = chain_training  # the container's own flag, then each net's
            for name, net in module.nets():
                net.train(was_training[name])
        self._last = (trainer.global_step, values)
        self.last_seconds = time.perf_counter() - start
        return dict(values)

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        if trainer.logger is None or not self.due(trainer):
            return
        values = self.evaluate(trainer, module)
        step = trainer.global_step
        if not self._zero_logged:
            self._zero_logged = True
        else:
            values = {k: v for k, v in values.items() if not k.endswith("zero_flow_epe")}
        trainer.logger.log_metrics({k: v for k, v in values.items() if math.isfinite(v)}, step=step)

    def batches(self, chain, which: int) -> list[dict[str, Any]]:
        """Held-apart set ``which`` in batches, loaded at its first scoring, each with the pairs' classical
        priors where ``chain`` reads them (:class:`PairPriors`: the values the chain would compute)."""
        if which not in self._batches:
            from demon_lab.pipeline.stages.priors import PairPriors

            priors = PairPriors.of(chain)
            loader = torch.utils.data.DataLoader(self.datasets[which], batch_size=self.batch_size, shuffle=False)
            self._batches[which] = []
            for batch in loader:
                if priors is not None:
                    pairs = [{k: batch[k][i] for k in ("image1", "image2", "intrinsics")}
                             for i in range(batch["image1"].shape[0])]
                    fields = priors.compute(pairs)
                    batch.update({k: torch.stack([f[k] for f in fields]) for k in fields[0]})
                self._batches[which].append(batch)
        return self._batches[which]

    def _scores(self, chain, batches, channels_last: bool = False, precision: Any = 32) -> dict[str, float]:
        """The module docstring's metrics on ``batches`` (:meth:`batches`), the chain's nets in
        ``precision`` (the stage's)."""
        rows: dict[str, list[float]] = {"epe": [], "zero_flow_epe": [], "rot_deg": [], "tran_deg": [], "l1_inv": []}
        for _, b, out in run_chain(chain, batches, self.iterations, precision=precision, channels_last=channels_last,
                                   refine=self.spec.kind == "refine"):
            p = out.passes[-1]
            gt = losses.ground_truth(b)
            error = (p.flow - gt["flow2"]).norm(dim=1)
            zero = gt["flow2"].norm(dim=1)
            for i in range(p.flow.shape[0]):
                rows["epe"].append(float(error[i][torch.isfinite(error[i])].mean()))
                rows["zero_flow_epe"].append(float(zero[i][torch.isfinite(zero[i])].mean()))
                if self.spec.scores_motion:
                    motion = metrics.motion_errors(p.motion[i].cpu(), b["motion"][i].cpu())
                    rows["rot_deg"].append(motion["rot_deg"])
                    rows["tran_deg"].append(motion["tran_deg"])
            if self.spec.kind == "refine":
                depth, target = out.refined, gt["inv_depth0"]
            elif self.spec.scores_motion:
                depth, target = p.inv_depth, gt["inv_depth2"]
            else:
                continue
            diff = (depth[:, :1] - target).abs()
            for i in range(p.flow.shape[0]):
                rows["l1_inv"].append(float(diff[i][torch.isfinite(diff[i])].mean()))
        return {k: _mean(v) for k, v in rows.items() if v}


class KeepBest(L.Callback):
    """The stage option ``keep_best``: every ``every`` steps and at the stage's last, the stage's
    ``metric`` (the stage kind's ``best_metric``: the flow of the pass a flow stage trains, the
    translation of a depth-motion net, the refined depth of the refinement net; lower is better)
    averaged over the held-apart sets; the trained nets of the lowest score so far
    are written to ``path`` (with the step and the score, so a resumed stage keeps its best), and
    :meth:`restore` puts them back into the chain when the stage ends. ``seconds`` is what scoring
    and saving the best nets cost this process (the stage logs it: the option's price), the scoring
    counted in full where the held-apart curves scored the same step first."""

    def __init__(self, scorer: StageValidation, metric: str, every: int, path, nets: Sequence[str]):
        self.scorer, self.metric, self.every = scorer, metric, int(every)
        self.path, self.nets, self.seconds = path, list(nets), 0.0
        saved = torch.load(path, weights_only=True) if path.is_file() else None
        self.best_step, self.best = (saved["step"], saved["score"]) if saved else (-1, math.inf)

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        step = trainer.global_step
        if step % self.every and step < trainer.max_steps:
            return
        values = self.scorer.evaluate(trainer, module)
        self.seconds += self.scorer.last_seconds  # (counted here too where the curves scored this step first)
        start = time.perf_counter()
        score = _mean([v for k, v in values.items() if k.endswith(f"/{self.metric}")])
        if score < self.best:
            self.best, self.best_step = score, step
            state = {"step": step, "score": score,
                     "nets": {n: {k: v.detach().cpu().clone() for k, v in getattr(module.chain, n).state_dict().items()}
                              for n in self.nets}}
            tmp = self.path.with_suffix(".tmp")
            torch.save(state, tmp)
            os.replace(tmp, self.path)  # atomic: a kill never leaves half a file
        self.seconds += time.perf_counter() - start

    def restore(self, chain) -> dict[str, float]:
        """Load the best nets into ``chain``; returns the stage's figures of the option."""
        if not self.path.is_file():
            return {"keep_best_seconds": self.seconds}
        saved = torch.load(self.path, weights_only=True)
        for name, state in saved["nets"].items():
            getattr(chain, name).load_state_dict(state)
        return {"keep_best_step": float(saved["step"]), f"keep_best_{self.metric}": float(saved["score"]),
                "keep_best_seconds": self.seconds}
