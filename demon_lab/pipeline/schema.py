"""The parts of a job's config the pipeline acts on, as typed values.

Hydra composes ``conf/`` into a DictConfig and :func:`demon_lab.pipeline.validate.validate`
checks it, one line per error. The pipeline then reads the chain's options and each training
stage through these frozen dataclasses rather than through the raw config:

- :class:`ModelSpec` (``model``): every key is in ``conf/model/demon.yaml``, so its defaults are
  written there and nowhere else;
- one :class:`StageSpec` subclass per stage kind (``schedule.stages.NAME``, told apart by its
  ``kind``): the options that every stage of a kind has come from ``conf/schedule/``; the options a
  stage may leave out (the departures and probes of the ``cpu`` scale) have their defaults here,
  and an option its kind does not take is an error. The class is everything a kind is: its options,
  its training module (``module``, a class of :mod:`demon_lab.pipeline.stages.modules`), the nets it
  trains, the ground-truth inputs it may train on, the loss weights it reads and its held-apart
  scores. A new kind is a subclass here, its module, and the YAML that schedules it.

A stage key hashes the stage's raw config node, not its spec, so an option's default written here
does not enter the key of a stage that leaves the option out (:mod:`demon_lab.pipeline.identity`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Any, ClassVar

from omegaconf import DictConfig, OmegaConf

from demon_lab.core.losses import DEPTH_MOTION_WEIGHTS, FLOW_SIG_WEIGHTS, FLOW_WEIGHTS, REFINE_WEIGHTS
from demon_lab.pipeline.config import (
    ConfigError,
    expect_choice,
    expect_flag,
    expect_fraction,
    expect_int,
    expect_positive,
)

LR_SCHEDULES = ("released", "supplementary")
"""``schedule.lr_schedule``: :func:`demon_lab.pipeline.stages.base.learning_rate` implements both."""
PRIOR_KEYS = ("flow1_prior", "dm1_prior", "flow2_prior", "dm2_prior")
"""The model options that give a net a prior (:mod:`demon_lab.nets.prior`)."""


@dataclass(frozen=True)
class ModelSpec:
    """``model``: the chain (:class:`demon_lab.nets.DeMoN`) and how its nets run."""

    variant: str
    width: float
    compat: str | None
    correlation: tuple[int, int] | None
    flow1_prior: str | None
    dm1_prior: str | None
    flow2_prior: str | None
    dm2_prior: str | None
    channels_last: bool
    compile: bool
    weights: str | None
    nets: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    """The slots given a net of one's own (``model.nets.SLOT``), each with its config (``_target_`` and
    its arguments): :mod:`demon_lab.nets.slots`."""

    @classmethod
    def of(cls, model: DictConfig) -> ModelSpec:
        """``model`` as a spec, or its first error as one ConfigError line: the chain's own rules
        (:func:`demon_lab.nets.chain.check_options`), the two switches and each slot's net
        (:func:`demon_lab.nets.slots.check_plugin`)."""
        from demon_lab.nets.chain import check_options
        from demon_lab.nets.slots import check_plugin

        values = OmegaConf.to_container(model, resolve=True)
        nets = values.get("nets") or {}
        try:
            check_options(values["variant"], values["width"], values["compat"], values["correlation"],
                          {k: values[k] for k in PRIOR_KEYS}, prefix="model.")
            if not isinstance(nets, dict):
                raise ValueError(f"model.nets: expected a mapping of slots to nets, got {nets!r}")
            for slot, node in nets.items():
                check_plugin(slot, node)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        for key in ("channels_last", "compile"):
            expect_flag(f"model.{key}", values[key])
        correlation = values["correlation"]
        return cls(**{**{f.name: values[f.name] for f in fields(cls) if f.name != "nets"},
                      "nets": {slot: node for slot, node in nets.items() if node is not None},
                      "width": float(values["width"]),
                      "correlation": tuple(correlation) if isinstance(correlation, list) else correlation})

    def priors(self) -> dict[str, str | None]:
        """The prior options as the chain takes them (keyword arguments)."""
        return {k: getattr(self, k) for k in PRIOR_KEYS}

    def plugins(self) -> dict[str, Any]:
        """The nets of one's own, built from their configs (``nets``), by slot: the class its
        ``_target_`` names (an ``nn.Module``, checked by :meth:`of`) called with its arguments, which
        the package's rule for targets holds to (:func:`demon_lab.pipeline.config.instantiate`)."""
        from demon_lab.nets.slots import plugin_class
        from demon_lab.pipeline.config import instantiate

        nets = {}
        for slot, node in self.nets.items():
            args = {k: v for k, v in node.items() if k != "_target_"}
            built = {k: instantiate(v) if isinstance(v, dict) and "_target_" in v else v for k, v in args.items()}
            try:
                nets[slot] = plugin_class(node["_target_"])(**built)
            except TypeError as e:  # (its arguments do not fit its constructor)
                raise ConfigError(f"model.nets.{slot}: {node['_target_']}({', '.join(args)}): {e}") from None
        return nets


@dataclass(frozen=True)
class StageSpec:
    """``schedule.stages.NAME``: what every kind of stage takes."""

    kind: ClassVar[str]
    module: ClassVar[str]
    """The stage's LightningModule: a class of :mod:`demon_lab.pipeline.stages.modules`, by name (the
    schema is read where Lightning is not imported)."""
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

    def module_options(self) -> dict[str, Any]:
        """The keyword arguments of the stage's module (its kind's ``module``) that its options set."""
        return {"steps": self.steps, "lr": self.lr, "warmup_steps": self.warmup_steps}

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
class FlowStageSpec(StageSpec):
    """A flow net's stage (``flow1``, or ``flow2`` on the frozen bootstrap net)."""

    kind: ClassVar[str] = "flow"
    module: ClassVar[str] = "FlowStage"
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

    def module_options(self) -> dict[str, Any]:
        return {**super().module_options(), "net": self.net, "oracle": self.oracle, "sig_start": self.sig_start,
                "level5_fade": self.level5_fade}

    def weight_keys(self) -> tuple[str, ...]:
        return _without_unstarted_sig(self.loss_weights, self.sig_start)

    def curriculum(self) -> dict[str, Any]:
        return {**super().curriculum(), "layers_first": self.layers_first}

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
class DepthMotionStageSpec(StageSpec):
    """A depth-motion net's stage (``dm1`` on the frozen ``flow1``, ``dm2`` on the frozen ``flow2``)."""

    kind: ClassVar[str] = "depth_motion"
    module: ClassVar[str] = "DepthMotionStage"
    oracles: ClassVar[tuple[str | None, ...]] = (None, "flow")
    loss_weights: ClassVar[tuple[str, ...]] = DEPTH_MOTION_WEIGHTS
    scores_motion: ClassVar[bool] = True
    best_metric: ClassVar[str] = "tran_deg"  # the motion the depth's scale and the next pass rest on
    net: str = "dm1"
    """The net the stage trains: ``dm1`` (bootstrap) or ``dm2`` (iterative)."""
    gt_flow_warmup: float = 0.0
    """The first fraction of the stage fed ground-truth flow (0: none, as DeMoN)."""

    def module_options(self) -> dict[str, Any]:
        return {**super().module_options(), "net": self.net, "oracle": self.oracle,
                "gt_flow_warmup": self.gt_flow_warmup}

    @classmethod
    def check(cls, name: str, values: dict[str, Any]) -> None:
        super().check(name, values)
        expect_fraction(f"schedule.stages.{name}.gt_flow_warmup", values["gt_flow_warmup"])


@dataclass(frozen=True)
class IterativeStageSpec(StageSpec):
    """``flow2`` and ``dm2`` trained together on DeMoN's queue of previous predictions."""

    kind: ClassVar[str] = "iterative"
    module: ClassVar[str] = "IterativeStage"
    loss_weights: ClassVar[tuple[str, ...]] = FLOW_WEIGHTS + DEPTH_MOTION_WEIGHTS
    scores_motion: ClassVar[bool] = True
    best_metric: ClassVar[str] = "tran_deg"
    queue_size: int = 24
    """Queued samples per step, beside the batch's new ones (DeMoN: 24)."""
    sig_start: float = 0.0
    """The fraction of the stage before its flow net's sig terms ramp in (0: DeMoN's; 1: never)."""

    def module_options(self) -> dict[str, Any]:
        return {**super().module_options(), "queue_size": self.queue_size, "sig_start": self.sig_start}

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


@dataclass(frozen=True)
class RefineStageSpec(StageSpec):
    """The refinement net on the frozen chain's depth after ``iterations`` passes."""

    kind: ClassVar[str] = "refine"
    module: ClassVar[str] = "RefineStage"
    loss_weights: ClassVar[tuple[str, ...]] = REFINE_WEIGHTS
    best_metric: ClassVar[str] = "l1_inv"  # of the refined depth
    iterations: int = 3
    """The passes of the frozen chain whose depth the refinement net refines (DeMoN: 3)."""

    def module_options(self) -> dict[str, Any]:
        return {**super().module_options(), "iterations": self.iterations}

    def trained_nets(self) -> tuple[str, ...]:
        return ("refine_net",)

    def validation_passes(self) -> int:
        return self.iterations


def _without_unstarted_sig(weights: tuple[str, ...], sig_start: float) -> tuple[str, ...]:
    """A flow net's weights without its sig terms' where they never start (``sig_start`` >= 1): a
    stage that never reads them shares its key with the stages of other sig weights."""
    return tuple(k for k in weights if k not in FLOW_SIG_WEIGHTS) if sig_start >= 1 else weights


FLOW1_ONLY = {"layers_first": "trains on 2-D layers", "restarts": "screens restarts"}
"""The options only the bootstrap flow net's stage takes, and what they do."""
OTHER_KINDS = {"level5_fade": "only flow stages have level-5 terms",
               "gt_flow_warmup": "only depth-motion stages are fed flow"}
"""Options of one kind, and why, for the line that refuses them on a stage of another."""

STAGE_SPECS: dict[str, type[StageSpec]] = {s.kind: s for s in (FlowStageSpec, DepthMotionStageSpec,
                                                              IterativeStageSpec, RefineStageSpec)}
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
