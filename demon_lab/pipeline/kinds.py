"""The kinds of training stage, one class each: flow net, depth-motion net, iterative pair, refinement net.

A stage of the schedule (``schedule.stages.NAME``, told apart by its ``kind``) is an instance of
its kind's class, and the class is everything the kind is: its options with their defaults and
rules (the options every stage of a kind has come from ``conf/schedule/``; those a stage may leave
out, the departures and probes of the ``cpu`` scale, have their defaults here, and an option its
kind does not take is an error), the loss it trains on (:meth:`StageSpec.loss`, run by the one
LightningModule of every kind, :class:`demon_lab.pipeline.stages.base.StageModule`), the nets it
trains, the ground-truth inputs it may train on, the loss weights it reads, its held-apart scores
and the state it carries from step to step. A new kind is a subclass here and the YAML that
schedules it.

The schedule (``conf/schedule/``) composes them in the released code's order: flow1 and dm1
(bootstrap), flow2 and dm2 (iterative nets trained one after the other), iterative (flow2 + dm2
jointly, with DeMoN's queue of previous predictions) and refine (`training/v2/training.py`;
docs/reference.md §5).

Nothing here imports Lightning: a config is checked, and refused, before it is. A stage key hashes
the stage's raw config node, not its instance, so an option's default written here does not enter
the key of a stage that leaves the option out (:mod:`demon_lab.pipeline.identity`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig, OmegaConf

from demon_lab.core import losses
from demon_lab.core.losses import DEPTH_MOTION_WEIGHTS, FLOW_SIG_WEIGHTS, FLOW_WEIGHTS, REFINE_WEIGHTS
from demon_lab.nets.chain import DeMoN, Prediction, ground_truth_inputs
from demon_lab.pipeline.config import (
    ConfigError,
    expect_choice,
    expect_fraction,
    expect_int,
    expect_positive,
)

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


@dataclass(frozen=True)
class FlowStage(StageSpec):
    """A flow net's stage: ``flow1`` (bootstrap) or ``flow2`` (iterative, its inputs from the frozen
    bootstrap net, or from ground truth with ``oracle='depth_motion'``). Sig weights ramp in over the
    first third; the level-5 losses fade out over it (DeMoN's `training/v2/training.py`;
    docs/reference.md §4).

    ``sig_start`` (a fraction of the stage, default 0 as DeMoN; 1: never) holds the sig weights at 0
    until then and starts their ramp there: a stage far shorter than DeMoN's lets the net find
    correspondence with the flow term alone first, since near zero flow, where an untrained net starts,
    the sig terms' gradient outweighs the flow term's (the ratios: docs/notes/2026-11-cpu-profile.md,
    "The flow stages train without their sig terms").

    ``level5_fade`` (a fraction of the stage, default DeMoN's 1/3) is how long the level-5 terms take
    to fade out: an option for probes of a short schedule (its probe: docs/notes/2026-11-cpu-profile.md,
    "What limits learning: probes of the recipe").
    """

    kind: ClassVar[str] = "flow"
    oracles: ClassVar[tuple[str | None, ...]] = (None, "depth_motion")
    loss_weights: ClassVar[tuple[str, ...]] = FLOW_WEIGHTS
    best_metric: ClassVar[str] = "epe"
    net: str = "flow1"
    """The net the stage trains: ``flow1`` (bootstrap) or ``flow2`` (iterative)."""
    sig_start: float = 0.0
    """The fraction of the stage before its sig terms ramp in (0: DeMoN's; 1: never)."""
    level5_fade: float = 1 / 3
    """The fraction of the stage over which the level-5 terms fade out (DeMoN's third)."""
    layers_first: float | None = None
    """``flow1``: the first fraction of the stage on 2-D layers under affine motion (None: none)."""
    restarts: tuple[int, int] | None = None
    """``flow1``: ``[k, steps]`` starts screened on the held-apart sets (None: one start)."""

    def weight_keys(self) -> tuple[str, ...]:
        return _without_unstarted_sig(self.loss_weights, self.sig_start)

    def curriculum(self) -> dict[str, Any]:
        return {**super().curriculum(), "layers_first": self.layers_first}

    def loss(self, stage, batch, gt):
        chain = stage.chain
        pair, image2_2, K = stage.inputs(batch)
        if self.net == "flow1":
            prior2 = batch.get("prior_flow")  # computed once per pair where the data carries it
            if chain.flow1_prior and prior2 is None:
                prior2, = stage.frozen(lambda p: (chain.prior_flow(p),), pair)
            flow5, flow2 = chain.flow1(pair, prior2=prior2)
        else:
            oracle = self.oracle == "depth_motion"
            prev = stage.bootstrap(pair, image2_2, K, batch) if not oracle or chain.flow2_prior else None
            with torch.no_grad():
                src = ground_truth_inputs(batch, K) if oracle else prev
            flow5, flow2 = chain.flow_net2(pair, image2_2, K, src, prev)
        return losses.flow_loss(flow5, flow2, gt, stage.weights, ramp=stage.ramp(1 / 3, self.sig_start),
                                level5=stage.level5(self.level5_fade))

    @classmethod
    def check(cls, name: str, values: dict[str, Any]) -> None:
        super().check(name, values)
        key = f"schedule.stages.{name}."
        expect_fraction(key + "sig_start", values["sig_start"], note=" (1: never)")
        expect_positive(key + "level5_fade", values["level5_fade"])
        net = values["net"]
        for option, what in FLOW1_ONLY.items():
            if values.get(option) is not None and net != "flow1":
                raise ConfigError(f"{key}{option}: only the bootstrap flow net's stage (flow1) {what} "
                                  f"(this stage: {cls.kind}, {net})")
        if values["layers_first"] is not None:
            expect_fraction(key + "layers_first", values["layers_first"], low_open=True)
            if values["easy_first"] is not None:
                raise ConfigError(f"{key}layers_first: one curriculum at a time; leave easy_first unset")
        restarts = values["restarts"]
        if restarts is not None:
            pair = isinstance(restarts, list) and len(restarts) == 2 and all(
                isinstance(v, int) and not isinstance(v, bool) for v in restarts)
            if not pair or not (restarts[0] >= 1 and 1 <= restarts[1] < values["steps"]):
                raise ConfigError(f"{key}restarts: expected [starts, steps]: starts >= 1, each trained 1 <= steps "
                                  f"< the stage's {values['steps']} steps, got {restarts!r}")


@dataclass(frozen=True)
class DepthMotionStage(StageSpec):
    """A depth-motion net's stage: ``dm1`` (fed by the frozen flow1) or ``dm2`` (fed by the frozen
    flow2 on top of the bootstrap net, and the bootstrap motion). With ``oracle='flow'`` it is fed
    ground-truth flow. The depth-sig weight ramps over twice the stage for dm1 (DeMoN's 2M-step ramp in
    a 1M-step stage) and over the stage for dm2.

    ``gt_flow_warmup`` (a fraction of the stage, default 0 as DeMoN) feeds ground-truth flow, as the
    oracle does, for that first part of the stage, and the flow net's from then on: the net learns to
    read motion from a flow that shows it before it meets the flow it will be given.
    """

    kind: ClassVar[str] = "depth_motion"
    oracles: ClassVar[tuple[str | None, ...]] = (None, "flow")
    loss_weights: ClassVar[tuple[str, ...]] = DEPTH_MOTION_WEIGHTS
    scores_motion: ClassVar[bool] = True
    best_metric: ClassVar[str] = "tran_deg"  # the motion the depth's scale and the next pass rest on
    net: str = "dm1"
    """The net the stage trains: ``dm1`` (bootstrap) or ``dm2`` (iterative)."""
    gt_flow_warmup: float = 0.0
    """The first fraction of the stage fed ground-truth flow (0: none, as DeMoN)."""

    @classmethod
    def check(cls, name: str, values: dict[str, Any]) -> None:
        super().check(name, values)
        expect_fraction(f"schedule.stages.{name}.gt_flow_warmup", values["gt_flow_warmup"])

    def loss(self, stage, batch, gt):
        chain = stage.chain
        pair, image2_2, K = stage.inputs(batch)
        given = self.oracle == "flow" or stage.global_step < self.gt_flow_warmup * self.steps
        prior = None  # dm1's prior motion where the memo has it
        if self.net == "dm1" and not given:
            flow, conf, *prior = stage.frozen(functools.partial(_bootstrap_flow, chain), pair, K, *pair_priors(batch))
            prior = prior[0] if prior else None
        elif self.net == "dm2":
            *fields, flow, conf = stage.frozen(functools.partial(_iterative_flow, chain), pair, image2_2, K,
                                               *pair_priors(batch))
            prev = Prediction(*fields)
        if given:
            with torch.no_grad():
                flow = ground_truth_inputs(batch, K).flow
                conf = torch.isfinite(flow).to(flow.dtype)
        if self.net == "dm1":
            dm = chain.depth_motion1(pair, image2_2, flow, conf, K, prior)
        else:  # (the inputs are built without gradient)
            dm = chain.depth_motion2(pair, image2_2, flow, conf, prev.motion, K)
        ramp = stage.ramp(2.0 if self.net == "dm1" else 1.0)
        return losses.depth_motion_loss(dm.inv_depth, dm.normals, dm.motion, gt, stage.weights, ramp=ramp)


def _bootstrap_flow(chain: DeMoN, pair, K, prior_flow=None, prior_motion=None):
    """``flow1``'s flow and confidence, and with ``dm1_prior`` the RANSAC motion of that flow (or of its
    prior flow); ``prior_flow``, ``prior_motion`` where the batch carries them (``ransac_prior``'s motion
    is the prior flow's: :mod:`demon_lab.pipeline.stages.priors`)."""
    _, flowconf, prior_flow = chain.flow_net1(pair, prior_flow)
    flow, conf = _flow_and_conf(flowconf)
    given = prior_motion is not None and chain.dm1_prior == "ransac_prior"
    prior = prior_motion if given else chain.prior_motion(flow, K, prior_flow)
    return (flow, conf) if prior is None else (flow, conf, prior)


def _iterative_flow(chain: DeMoN, pair, image2_2, K, *priors):
    """The bootstrap pass's fields, then the iterative flow net's flow and confidence on it."""
    prev = chain.bootstrap(pair, image2_2, K, None, None, *priors)
    return (*_fields(prev), *_flow_and_conf(chain.flow_net2(pair, image2_2, K, prev, prev)[1]))


def _flow_and_conf(flowconf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return flowconf[:, :2], flowconf[:, 2:]


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
        return _without_unstarted_sig(self.loss_weights, self.sig_start)

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
                    _index(prev, i)) for i in range(pair.shape[0])]
        combined = samples + queue[: self.queue_size]
        queue = queue[self.queue_size:]
        merged = {k: torch.stack([s[k] for s, _ in combined]) for k in combined[0][0]}
        prev_all = _stack([p for _, p in combined])
        gt_all = losses.ground_truth(merged)
        pair, image2_2, K = stage.inputs(merged)
        out = stage.chain.iterate(pair, image2_2, K, prev_all)
        flow_sig = float(stage.global_step >= self.sig_start * self.steps)
        flow_total, flow_terms = losses.flow_loss(torch.cat([out.flow5, out.conf5], 1),
                                                  torch.cat([out.flow, out.conf], 1), gt_all,
                                                  stage.weights, ramp=flow_sig, level5=0.0)
        dm_total, dm_terms = losses.depth_motion_loss(out.inv_depth, out.normals, out.motion, gt_all,
                                                      stage.weights, ramp=1.0)
        detached = Prediction(*(t.detach() for t in (out.flow, out.conf, out.flow5, out.conf5,
                                                       out.inv_depth, out.normals, out.motion)))
        stage.state["queue"] = queue + [(combined[i][0], _index(detached, i))
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
        preds = _stack([Prediction(**{f: v[i] for f, v in saved["predictions"].items()}) for i in range(n)])
        return {"queue": [({k: v[i] for k, v in saved["samples"].items()}, _index(preds, i)) for i in range(n)]}


def _fields(p: Prediction) -> tuple[torch.Tensor, ...]:
    return tuple(getattr(p, f) for f in Prediction.__dataclass_fields__)


def _index(p: Prediction, i: int) -> Prediction:
    return Prediction(*(getattr(p, f)[i] for f in Prediction.__dataclass_fields__))


def _stack(ps: list[Prediction]) -> Prediction:
    return Prediction(*(torch.stack([getattr(p, f) for p in ps]) for f in Prediction.__dataclass_fields__))


@dataclass(frozen=True)
class RefineStage(StageSpec):
    """The refinement net on the depth of the frozen chain after ``iterations`` iterative passes; its
    depth-sig weight ramps in over the stage."""

    kind: ClassVar[str] = "refine"
    loss_weights: ClassVar[tuple[str, ...]] = REFINE_WEIGHTS
    best_metric: ClassVar[str] = "l1_inv"  # of the refined depth
    iterations: int = 3
    """The passes of the frozen chain whose depth the refinement net refines (DeMoN: 3)."""

    def trained_nets(self) -> tuple[str, ...]:
        return ("refine_net",)

    def validation_passes(self) -> int:
        return self.iterations

    def loss(self, stage, batch, gt):
        pair, image2_2, K = stage.inputs(batch)
        inv_depth, = stage.frozen(functools.partial(_passes, stage.chain, self.iterations), pair, image2_2, K,
                                  *pair_priors(batch))
        refined = stage.chain.refine(batch["image1"], inv_depth)
        return losses.refine_loss(refined, gt, stage.weights, ramp=stage.ramp(1.0))


def _passes(chain: DeMoN, iterations: int, pair, image2_2, K, *priors):
    """The inverse depth of the frozen chain's last pass."""
    p = chain.bootstrap(pair, image2_2, K, None, None, *priors)
    for _ in range(iterations):
        p = chain.iterate(pair, image2_2, K, p)
    return (p.inv_depth,)


def _without_unstarted_sig(weights: tuple[str, ...], sig_start: float) -> tuple[str, ...]:
    """A flow net's weights without its sig terms' where they never start (``sig_start`` >= 1): a
    stage that never reads them shares its key with the stages of other sig weights."""
    return tuple(k for k in weights if k not in FLOW_SIG_WEIGHTS) if sig_start >= 1 else weights


FLOW1_ONLY = {"layers_first": "trains on 2-D layers", "restarts": "screens restarts"}
"""The options only the bootstrap flow net's stage takes, and what they do."""
OTHER_KINDS = {"level5_fade": "only flow stages have level-5 terms",
               "gt_flow_warmup": "only depth-motion stages are fed flow"}
"""Options of one kind, and why, for the line that refuses them on a stage of another."""

STAGE_SPECS: dict[str, type[StageSpec]] = {s.kind: s for s in (FlowStage, DepthMotionStage,
                                                              IterativeStage, RefineStage)}
"""The kinds of training stage (``schedule.stages.NAME.kind``) and their options."""
STAGE_KIND_NAMES = tuple(STAGE_SPECS)


def options_of(kind: str) -> tuple[str, ...]:
    """The options a stage of ``kind`` takes (``kind`` itself included)."""
    return ("kind", *(f.name for f in fields(STAGE_SPECS[kind]) if f.name != "name"))


def stage_spec(cfg: DictConfig, name: str) -> StageSpec:
    """``schedule.stages.NAME`` as its kind's spec; an option left out, or null where its default is
    not, takes the default; an option the kind does not take is a ConfigError."""
    values = OmegaConf.to_container(cfg.schedule.stages[name], resolve=True)
    kind = values.pop("kind", None)
    expect_choice(f"schedule.stages.{name}.kind", kind, STAGE_KIND_NAMES)
    spec = STAGE_SPECS[kind]
    unknown = sorted(set(values) - set(options_of(kind)))
    for option in unknown:  # another kind's option, set here: why it is that kind's
        if option in FLOW1_ONLY and values[option] is not None:
            raise ConfigError(f"schedule.stages.{name}.{option}: only the bootstrap flow net's stage (flow1) "
                              f"{FLOW1_ONLY[option]} (this stage: {kind}, {values.get('net')})")
        if option in OTHER_KINDS and values[option] is not None:
            raise ConfigError(f"schedule.stages.{name}.{option}: {OTHER_KINDS[option]} (this stage's kind: {kind})")
    if unknown:
        raise ConfigError(f"schedule.stages.{name}.{unknown[0]}: not an option of a {kind} stage (its options: "
                          f"{', '.join(options_of(kind))})")
    defaults = {f.name: f.default for f in fields(spec) if f.default is not dataclasses.MISSING}
    values = {**defaults, **{k: v for k, v in values.items() if v is not None or defaults.get(k) is None}}
    spec.check(name, values)
    for key in ("easy_first", "restarts"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    return spec(name=name, **values)
