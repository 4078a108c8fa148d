"""The LightningModule that trains a stage of DeMoN's schedule (`training/v2/training.py`;
docs/reference.md §5), of whatever kind (:mod:`demon_lab.pipeline.kinds`: the kind gives its
loss, the nets it trains and its options). It holds the whole chain as a plain submodule; only the
stage's own nets train, the upstream nets run frozen in eval mode, forward only.

Optimiser as in DeMoN's training code: Adam (beta 0.9/0.999, eps 1e-6), weight decay on kernels,
element-wise gradient clipping (the Trainer's ``gradient_clip_algorithm="value"``). Learning-rate schedules:
``released`` — constant for the first third, then quadratic decay to 1e-6 at the end (the
released code); ``supplementary`` — multistep, -20 % at each step (its Figure 1; the step
positions are not given, demon_lab puts them at 40, 60 and 80 % of the stage).
"""

from __future__ import annotations

from collections.abc import Mapping

import lightning as L
import torch

from demon_lab.core import execution, losses
from demon_lab.nets.chain import DeMoN, Prediction, downsample_image
from demon_lab.pipeline.kinds import StageSpec, pair_priors
from demon_lab.pipeline.schema import LR_SCHEDULES
from demon_lab.pipeline.stages.memo import FrozenMemo

MULTISTEP_MILESTONES = (0.4, 0.6, 0.8)
FINAL_LR = 1e-6


def learning_rate(step: int, steps: int, base: float, schedule: str, warmup_steps: int = 0) -> float:
    """The learning rate at ``step`` of a stage of ``steps`` steps; with ``warmup_steps`` it rises
    linearly from ``base / warmup_steps`` to the schedule's value over the first steps."""
    warm = min(1.0, (step + 1) / warmup_steps) if warmup_steps > 0 else 1.0
    if schedule == "released":
        tau = min(max((step - steps / 3) / (2 * steps / 3), 0.0), 1.0)
        return warm * (base + (FINAL_LR - base) * tau * tau)
    if schedule == "supplementary":
        return warm * base * 0.8 ** sum(step >= m * steps for m in MULTISTEP_MILESTONES)
    raise ValueError(f"schedule.lr_schedule: expected one of {LR_SCHEDULES}, got {schedule!r}")


class StageModule(L.LightningModule):
    """A stage's training: frozen upstream nets, optimiser, schedule, loss logging; its kind's loss.

    Args:
        chain: the DeMoN chain (upstream nets already trained and loaded).
        spec: the stage, an instance of its kind (its steps, rate, warm-up, the nets it trains, its loss).
        weights: a loss preset (:func:`demon_lab.core.losses.check_weights`).
        lr_schedule, weight_decay: the job's optimisation of every stage.
        channels_last: the batch's images in channels-last layout (the chain's nets already are:
            :func:`demon_lab.core.execution.prepare_nets`).
        reuse_frozen: what the frozen nets compute for a pair is computed once and read from a
            memo at the pair's next draws (:mod:`demon_lab.pipeline.stages.memo`).
    """

    def __init__(self, chain: DeMoN, spec: StageSpec, weights: Mapping[str, float], lr_schedule: str = "released",
                 weight_decay: float = 0.0, channels_last: bool = False, reuse_frozen: bool = False):
        super().__init__()
        self.chain, self.spec = chain, spec
        self.trained = list(spec.trained_nets())
        self.weights = losses.check_weights(weights)
        self.steps, self.base_lr, self.lr_schedule = int(spec.steps), float(spec.lr), lr_schedule
        self.weight_decay, self.warmup_steps = float(weight_decay), int(spec.warmup_steps)
        learning_rate(0, self.steps, self.base_lr, lr_schedule)  # validates the schedule name
        self.channels_last = bool(channels_last)
        self.memo = FrozenMemo() if reuse_frozen else None
        self.state: dict = {}
        """What the kind carries from step to step (the iterative kind's queue): saved with a checkpoint."""
        self.freeze_upstream()
        self.last_terms: dict[str, float] = {}

    def freeze_upstream(self) -> None:
        """Only the stage's own nets get gradients (stages share one chain: call before training)."""
        for name, net in self.nets():
            net.requires_grad_(name in self.trained)

    def on_fit_start(self) -> None:
        self.freeze_upstream()

    def nets(self):
        return [(n, getattr(self.chain, n)) for n in ("flow1", "dm1", "flow2", "dm2", "refine_net")]

    def train(self, mode: bool = True):
        super().train(mode)
        for name, net in self.nets():  # frozen nets always run in eval mode
            if name not in self.trained:
                net.eval()
        return self

    def configure_optimizers(self):
        decay, no_decay = [], []
        for name in self.trained:
            for pname, p in getattr(self.chain, name).named_parameters():
                (no_decay if pname.endswith("bias") else decay).append(p)
        optimizer = torch.optim.Adam(
            [{"params": decay, "weight_decay": self.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
            lr=self.base_lr, betas=(0.9, 0.999), eps=1e-6,
            foreach=True)  # multi-tensor Adam: the same update, bit for bit on the CPU, in less time
        # (docs/notes/2026-11-cpu-profile.md, "Time and memory": the exact speed-ups)
        scheduler = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: learning_rate(step, self.steps, self.base_lr, self.lr_schedule,
                                                  self.warmup_steps) / self.base_lr)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def on_after_batch_transfer(self, batch, dataloader_idx: int):
        return execution.channels_last_batch(batch, self.channels_last)

    def inputs(self, batch: Mapping[str, torch.Tensor]):
        pair = torch.cat([batch["image1"], batch["image2"]], 1)
        return pair, downsample_image(batch["image2"]), batch["intrinsics"]

    def stage_loss(self, batch: Mapping[str, torch.Tensor], gt: dict) -> tuple[torch.Tensor, dict]:
        """The kind's loss on ``batch`` and its terms (:meth:`demon_lab.pipeline.kinds.StageSpec.loss`)."""
        return self.spec.loss(self, batch, gt)

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        self.spec.save_state(self.state, checkpoint)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self.state = self.spec.load_state(checkpoint)

    def frozen(self, compute, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``compute(*inputs)``, a computation of the frozen nets alone that returns a tuple of batch
        tensors, without gradient (from the memo with ``reuse_frozen``)."""
        with torch.no_grad():
            return self.memo(compute, *inputs) if self.memo is not None else compute(*inputs)

    def bootstrap(self, pair: torch.Tensor, image2_2: torch.Tensor, intrinsics: torch.Tensor,
                  batch: Mapping[str, torch.Tensor]) -> Prediction:
        """The frozen bootstrap pass, without gradient, on the classical priors ``batch`` carries."""
        return Prediction(*self.frozen(self._bootstrap_fields, pair, image2_2, intrinsics, *pair_priors(batch)))

    def _bootstrap_fields(self, pair, image2_2, intrinsics, *priors) -> tuple[torch.Tensor, ...]:
        p = self.chain.bootstrap(pair, image2_2, intrinsics, None, None, *priors)
        return tuple(getattr(p, f) for f in Prediction.__dataclass_fields__)

    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        gt = losses.ground_truth(batch)
        loss, terms = self.stage_loss(batch, gt)
        if not torch.isfinite(loss):
            values = ", ".join(f"{k}={v.item():.4g}" for k, v in terms.items())
            raise FloatingPointError(f"non-finite loss at step {self.global_step}: {values}")
        self.last_terms = {k: float(v.detach()) for k, v in terms.items()}
        if self._logging_step():
            logged = {f"train/{k}": v.detach() for k, v in terms.items()}
            logged["train/loss"] = loss.detach()
            logged["train/lr"] = torch.tensor(self.optimizers().param_groups[0]["lr"])
            self.log_dict(logged, prog_bar=False, on_step=True, on_epoch=False, batch_size=batch["image1"].shape[0])
            self.log("loss", loss.detach(), prog_bar=True, on_step=True, on_epoch=False, logger=False,
                     batch_size=batch["image1"].shape[0])
        return loss

    def _logging_step(self) -> bool:
        """Whether Lightning writes this step's values to the logger (every ``log_every_n_steps``,
        by its own rule): only those steps collect the values, since the others would drop them
        (the cost: docs/notes/2026-11-cpu-profile.md, "Time and memory")."""
        trainer = self._trainer
        return trainer is None or bool(trainer._logger_connector.should_update_logs)

    def ramp(self, duration_fraction: float, start_fraction: float = 0.0) -> float:
        """ease_out_quad over ``duration_fraction`` of the stage (DeMoN's sig-weight ramps),
        starting after ``start_fraction`` of it (0 before)."""
        elapsed = max(self.global_step - start_fraction * self.steps, 0.0)
        return losses.ease_out_quad(elapsed, duration_fraction * self.steps)

    def level5(self, duration_fraction: float) -> float:
        return losses.ease_in_quad_down(self.global_step, duration_fraction * self.steps)

