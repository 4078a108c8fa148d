"""What every kind of training stage takes: :class:`StageSpec`, and the classical priors a batch carries."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from demon_lab.core.losses import FLOW_SIG_WEIGHTS
from demon_lab.nets.chain import Prediction
from demon_lab.pipeline.config import ConfigError, expect_choice, expect_int, expect_positive

PRIOR_FIELDS = ("prior_flow", "prior_motion")
"""The classical priors a training batch may carry, in :meth:`demon_lab.nets.chain.DeMoN.bootstrap`'s
order (computed once per pair: :mod:`demon_lab.pipeline.stages.priors`)."""


def pair_priors(batch: Mapping[str, torch.Tensor]) -> list[torch.Tensor]:
    """The classical priors ``batch`` carries (:data:`PRIOR_FIELDS`, the leading ones it has)."""
    given = []
    for key in PRIOR_FIELDS:
        if key not in batch:
            break
        given.append(batch[key])
    return given


@dataclass(frozen=True)
class StageSpec:
    """``schedule.stages.NAME``: what every kind of stage takes."""

    kind: ClassVar[str]
    oracles: ClassVar[tuple[str | None, ...]] = (None,)
    """The ground-truth inputs (``oracle``) the kind may train on; None: the chain's own."""
    loss_weights: ClassVar[tuple[str, ...]]
    """The loss weights (``loss.*``) the kind's loss reads."""
    scores_motion: ClassVar[bool] = False
    """Its held-apart scores include the motion and the depth of its pass."""
    best_metric: ClassVar[str]
    """The held-apart score ``keep_best`` keeps the best nets by (lower is better)."""
    name: str
    steps: int
    """Training steps (0: the stage trains nothing; its nets stay as they are)."""
    lr: float
    """The base learning rate (``schedule.lr_schedule`` decays it)."""
    warmup_steps: int = 0
    """Linear learning-rate warm-up (0: none, as DeMoN)."""
    batch_size: int | None = None
    """The stage's own batch (None: ``data.batch_size``)."""
    oracle: str | None = None
    """Ground-truth inputs in training ('flow' for depth-motion stages, 'depth_motion' for flow2)."""
    easy_first: tuple[float, float] | None = None
    """A curriculum: the easiest fraction of samples first, widening to all (None: none)."""
    fresh_scenes: float = 0.0
    """New synthetic scenes per training draw of a synthetic source, rendered into the scene cache
    before the stage trains (0: the source's fixed set, as DeMoN's fixed training files)."""
    keep_best: int = 0
    """Score the held-apart sets (``data.val``) every this many steps and at the end, and keep the
    trained nets of the best score (0: the last step's nets, as DeMoN)."""

    def weight_keys(self) -> tuple[str, ...]:
        """The loss weights the stage reads (and so the ones in its stage key)."""
        return self.loss_weights

    def trained_nets(self) -> tuple[str, ...]:
        """The chain's nets (attributes of :class:`demon_lab.nets.DeMoN`) the stage trains and stores."""
        return (self.net,)

    def validation_passes(self) -> int:
        """The iterative passes the chain runs when the stage's nets are scored on the held-apart sets."""
        return int(self.net in ("flow2", "dm2"))

    def curriculum(self) -> dict[str, Any]:
        """The keyword arguments of the stage's training data (:func:`demon_lab.data.datamodule.build_datamodule`)
        that the stage's options set."""
        return {"easy_first": self.easy_first, "fresh_scenes": self.fresh_scenes}

    def loss(self, stage: Any, batch: Mapping[str, torch.Tensor],
             gt: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The stage's loss on a training ``batch`` and its terms by name: ``stage`` is the
        LightningModule that trains it (:class:`demon_lab.pipeline.stages.base.StageModule`: its
        chain, its frozen computations, its step and ramps)."""
        raise NotImplementedError

    def save_state(self, state: dict, checkpoint: dict) -> None:
        """What the kind carries from step to step (``state``, the module's) into a checkpoint: a
        resumed stage continues with it. None by default."""

    def load_state(self, checkpoint: dict) -> dict:
        """The state :meth:`save_state` wrote into ``checkpoint`` (empty where it wrote none)."""
        return {}

    @classmethod
    def check(cls, name: str, values: dict[str, Any]) -> None:
        """The rules of the kind's own options, on the stage's values as the config gives them, its
        defaults filled in (a
        ConfigError line naming ``schedule.stages.NAME.OPTION``); the rules across the config
        (``data``, the devices, the stages before it) are :func:`demon_lab.pipeline.validate.validate`'s."""
        key = f"schedule.stages.{name}."
        expect_int(key + "steps", values["steps"], 0)
        expect_positive(key + "lr", values["lr"])
        expect_choice(key + "oracle", values["oracle"], cls.oracles)
        expect_int(key + "warmup_steps", values["warmup_steps"], 0)
        easy = values["easy_first"]
        if easy is not None:
            numbers = isinstance(easy, list) and len(easy) == 2 and all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in easy)
            if not numbers or not (0 < easy[0] <= 1 and 0 < easy[1] <= 1):
                raise ConfigError(f"{key}easy_first: expected [start, until]: the easiest fraction start in (0, 1] "
                                  f"widening to all samples at the fraction until in (0, 1] of the stage, got {easy!r}")
        rate = values["fresh_scenes"]
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not 0 <= rate <= 1:
            raise ConfigError(f"{key}fresh_scenes: expected new scenes per training draw in [0, 1], got {rate!r}")
        if rate and easy is not None:
            raise ConfigError(f"{key}fresh_scenes: the easy_first order is of a fixed set of scenes; "
                              f"leave easy_first unset")
        expect_int(key + "keep_best", values["keep_best"], 0)


def prediction_fields(p: Prediction) -> tuple[torch.Tensor, ...]:
    """A prediction's fields, in order."""
    return tuple(getattr(p, f) for f in Prediction.__dataclass_fields__)


def prediction_row(p: Prediction, i: int) -> Prediction:
    """Sample ``i`` of a batched prediction."""
    return Prediction(*(getattr(p, f)[i] for f in Prediction.__dataclass_fields__))


def stacked_predictions(ps: list[Prediction]) -> Prediction:
    """Predictions of single samples as one batched prediction."""
    return Prediction(*(torch.stack([getattr(p, f) for p in ps]) for f in Prediction.__dataclass_fields__))


def without_unstarted_sig(weights: tuple[str, ...], sig_start: float) -> tuple[str, ...]:
    """A flow net's weights without its sig terms' where they never start (``sig_start`` >= 1): a
    stage that never reads them shares its key with the stages of other sig weights."""
    return tuple(k for k in weights if k not in FLOW_SIG_WEIGHTS) if sig_start >= 1 else weights
