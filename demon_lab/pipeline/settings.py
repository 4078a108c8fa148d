"""The job's config as typed settings: one frozen dataclass per section, each key's type and range
written once, in its field's check, and each rule across keys in its section's ``__post_init__``.

Hydra composes ``conf/`` into a DictConfig (the YAML files set every value); :meth:`JobSettings.of`
reads it into these objects, one :class:`~demon_lab.pipeline.config.ConfigError` line per error
(``iterations: expected an integer >= 0, got -2``), and the pipeline reads the typed values. What no
type can say stays in :func:`demon_lab.pipeline.validate.validate`: files that must exist, what the
machine's devices can run, and the nets a stage of 0 steps keeps.

A section's fields have no defaults where every config sets the key; a field with a default is a
key a config may leave out (``tracking.server``, ``data.val``). The model (:class:`ModelSpec`) and the
training stages (:class:`~demon_lab.pipeline.kinds.StageSpec`, by kind) in
:mod:`demon_lab.pipeline.schema` and :mod:`demon_lab.pipeline.kinds`; the baselines' parameters by
:class:`demon_lab.baselines.methods.BaselineConfig`; the loss weights by
:func:`demon_lab.core.losses.check_weights`. Why not Hydra's structured configs: their errors span
several lines with the config's key path and object type, and they check types, not ranges or rules
across keys; these checks write the one line a user needs. ``docs/config.md`` lists every field's
check (:func:`allowed`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from demon_lab.baselines.methods import BaselineConfig
from demon_lab.core.losses import check_weights
from demon_lab.nets.chain import ORACLES
from demon_lab.pipeline.config import ConfigError, expect_choice, expect_flag, expect_int, expect_positive
from demon_lab.pipeline.kinds import StageSpec, stage_spec
from demon_lab.pipeline.methods import METHODS, method
from demon_lab.pipeline.schema import LR_SCHEDULES, ModelSpec

ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps")
TRACKING_SCHEMES = ("sqlite", "http", "https", "postgresql", "mysql", "mssql", "file", "databricks")
SYNTHETIC_SOURCE = "demon_lab.data.datasets.SyntheticDataset"
"""The training source whose scenes ``fresh_scenes`` renders (a generator makes new ones)."""


# --- checks: each turns a config value into a typed one, or raises the key's one line --------------

@dataclass(frozen=True)
class Int:
    minimum: int | None = None
    optional: bool = False

    def __call__(self, key: str, value: Any) -> int | None:
        return None if value is None and self.optional else expect_int(key, value, self.minimum)

    def allowed(self) -> str:
        return ("null or " if self.optional else "") + ("an integer" if self.minimum is None
                                                        else f"an integer >= {self.minimum}")


@dataclass(frozen=True)
class Number:
    allow_zero: bool = False
    optional: bool = False

    def __call__(self, key: str, value: Any) -> float | None:
        return None if value is None and self.optional else expect_positive(key, value, self.allow_zero)

    def allowed(self) -> str:
        return ("null or " if self.optional else "") + ("a non-negative number" if self.allow_zero
                                                        else "a positive number")


@dataclass(frozen=True)
class Choice:
    values: tuple

    def __call__(self, key: str, value: Any) -> Any:
        expect_choice(key, value, self.values)
        return value

    def allowed(self) -> str:
        return " | ".join("null" if v is None else str(v) for v in self.values)


@dataclass(frozen=True)
class Flag:
    def __call__(self, key: str, value: Any) -> bool:
        return expect_flag(key, value)

    def allowed(self) -> str:
        return "true | false"


@dataclass(frozen=True)
class Text:
    optional: bool = False

    def __call__(self, key: str, value: Any) -> str | None:
        if value is None and self.optional:
            return None
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return str(value)

    def allowed(self) -> str:
        return "null or a string" if self.optional else "a string"


@dataclass(frozen=True)
class Size:
    def __call__(self, key: str, value: Any) -> tuple[int, int]:
        size = list(value) if isinstance(value, list | tuple) else [value]
        if len(size) != 2 or any(isinstance(s, bool) or not isinstance(s, int) or s < 32 or s % 32 for s in size):
            raise ConfigError(f"{key}: expected [H, W] with sides positive multiples of 32, got {size}")
        return tuple(size)

    def allowed(self) -> str:
        return "[H, W], multiples of 32"


@dataclass(frozen=True)
class Precision:
    def __call__(self, key: str, value: Any) -> Any:
        from demon_lab.core import execution

        try:
            execution.normalize_precision(value)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        return value

    def allowed(self) -> str:
        return "32 | bf16-mixed | 16-mixed"


@dataclass(frozen=True)
class Uri:
    def __call__(self, key: str, value: Any) -> str:
        if not isinstance(value, str) or not value:
            raise ConfigError(f"{key}: expected a URI such as sqlite:///mlflow.db, got {value!r}")
        scheme = value.split("://", 1)[0].split("+", 1)[0] if "://" in value else ""
        if scheme not in TRACKING_SCHEMES:
            raise ConfigError(f"{key}: expected a URI with one of the schemes {', '.join(TRACKING_SCHEMES)} "
                              f"(e.g. sqlite:///mlflow.db, http://127.0.0.1:5000), got {value!r}")
        return value

    def allowed(self) -> str:
        return f"a URI ({', '.join(TRACKING_SCHEMES)})"


@dataclass(frozen=True)
class Sources:
    """A list of data sources (``_target_`` nodes, instantiated where they are read), kept as nodes;
    null or left out: none."""

    required: bool = False

    def __call__(self, key: str, value: Any) -> tuple:
        if not value and self.required:
            raise ConfigError(f"{key}: expected at least one training source")
        return tuple(value or ())

    def allowed(self) -> str:
        return "a list of sources" + (" (at least one)" if self.required else "")


@dataclass(frozen=True)
class Nested:
    """A section inside a section (null where the key may be left out or null)."""

    section: type

    def __call__(self, key: str, value: Any):
        if value is None:
            return None
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        return self.section.of(OmegaConf.create(value), key)

    def allowed(self) -> str:
        return "null or a mapping"


@dataclass(frozen=True)
class Free:
    """A value passed on as it is (a mapping whose own owner checks it, a tag)."""

    def __call__(self, key: str, value: Any) -> Any:
        return value

    def allowed(self) -> str:
        return "-"


def setting(check, default: Any = MISSING):
    """A section's field: its ``check``, and a default only for a key a config may leave out."""
    return field(default=default, metadata={"check": check})


def allowed(section: type, key: str) -> str:
    """What ``section``'s field ``key`` accepts, in words (``docs/config.md``)."""
    return next(f.metadata["check"].allowed() for f in fields(section) if f.name == key)


class Section:
    """A config section read key by key through its fields' checks; subclasses are frozen dataclasses
    whose ``__post_init__`` holds the rules across their own keys."""

    @classmethod
    def values(cls, node: DictConfig, where: str) -> dict[str, Any]:
        """The checked value of each field that has a check (a key left out takes its default)."""
        values = {}
        for f in fields(cls):
            check = f.metadata.get("check")
            if check is None:
                continue
            if f.name not in node:
                if f.default is MISSING:
                    raise ConfigError(f"{where}{f.name}: missing (every config sets it)")
                continue
            raw = node[f.name]  # (resolved; a list of sources stays a list of nodes)
            if isinstance(raw, DictConfig | ListConfig) and not isinstance(check, Sources):
                raw = OmegaConf.to_container(raw, resolve=True)
            values[f.name] = check(f"{where}{f.name}", raw)
        return values

    @classmethod
    def of(cls, node: DictConfig, where: str, **extra: Any):
        """``node`` (the config's section at ``where``) as settings; ``extra``: fields read elsewhere."""
        return cls(**cls.values(node, f"{where}."), **extra)


# --- the sections -----------------------------------------------------------------------------

@dataclass(frozen=True)
class DataSettings(Section):
    """``data``: the training, test and held-apart sources and how they are batched. A data config's
    other keys (``real_pair``, ``train_length``, ``root``, ...) are inputs of its sources."""

    size: tuple[int, int] = setting(Size())
    batch_size: int = setting(Int(1))
    num_workers: int = setting(Int(0))
    train: tuple = setting(Sources(required=True))
    test: tuple = setting(Sources())
    val: tuple = setting(Sources(), default=())


@dataclass(frozen=True)
class TrainerSettings(Section):
    """``trainer``: where the stages train."""

    accelerator: str = setting(Choice(ACCELERATORS))
    devices: int = setting(Int(1))
    num_nodes: int = setting(Int(1))
    reuse_frozen: bool = setting(Flag())
    profile: bool = setting(Flag())

    @property
    def world(self) -> int:
        """The training processes: ``devices x num_nodes`` (more than 1: DDP)."""
        return self.devices * self.num_nodes


@dataclass(frozen=True)
class EvalSettings(Section):
    """``eval``: how the test sets are scored and what is kept for pictures."""

    batch_size: int = setting(Int(1))
    max_samples: int | None = setting(Int(1, optional=True))
    visualize: int = setting(Int(0))
    point_clouds: int = setting(Int(0))
    ceiling: bool = setting(Flag(), default=False)
    """(:func:`demon_lab.pipeline.evaluate.flow_ceiling`)"""


@dataclass(frozen=True)
class ServerSettings(Section):
    """``tracking.server`` (``tracking=local_server``): an MLflow server on 127.0.0.1 for one command
    (:class:`demon_lab.pipeline.tracking.LocalServer`)."""

    port: int = setting(Int(1))
    backend_store_uri: str = setting(Text())
    artifacts_destination: str = setting(Text())
    startup_timeout: float | None = setting(Number(optional=True), default=None)
    """Seconds for the server to answer; null or left out: :class:`~demon_lab.pipeline.tracking.LocalServer`'s."""

    def arguments(self) -> dict[str, Any]:
        """:class:`~demon_lab.pipeline.tracking.LocalServer`'s keyword arguments (its own default where unset)."""
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


@dataclass(frozen=True)
class TrackingSettings(Section):
    """``tracking``: the MLflow store and how often a stage logs."""

    uri: str = setting(Uri())
    artifact_dir: str = setting(Text())
    log_every_n_steps: int = setting(Int(1))
    val_every_n_steps: int = setting(Int(0))
    server: ServerSettings | None = setting(Nested(ServerSettings), default=None)


@dataclass(frozen=True)
class ScaleSettings(Section):
    """``scale``: the sizes a scale sets (its step counts are read by the schedule's stages)."""

    name: str = setting(Text())
    batch_size: int = setting(Int(1))
    checkpoint_every: int = setting(Int(0))
    """(0: Lightning's checkpoint every step, as 1)"""
    queue_size: int = setting(Int(0))
    steps: Mapping = setting(Free())


def stage_order(schedule: DictConfig) -> tuple[str, ...]:
    """The order the stages train in: ``schedule.order`` where a config sets it (a design that adds a
    stage between two others: the stages' mapping keeps the order they were written in, so an added one
    comes last), else the stages' own order. ``order`` must name each stage once."""
    stages = tuple(schedule.stages)
    order = schedule.get("order")
    if order is None:
        return stages
    if not isinstance(order, ListConfig | list) or sorted(map(str, order)) != sorted(stages):
        raise ConfigError(f"schedule.order: expected each of the stages ({', '.join(stages)}) once, got "
                          f"{OmegaConf.to_container(order) if isinstance(order, ListConfig) else order!r}")
    return tuple(map(str, order))


@dataclass(frozen=True)
class ScheduleSettings(Section):
    """``schedule``: the optimiser's settings and the stages (each typed by its kind's
    :class:`~demon_lab.pipeline.kinds.StageSpec`, :func:`~demon_lab.pipeline.kinds.stage_spec`)."""

    lr_schedule: str = setting(Choice(LR_SCHEDULES))
    weight_decay: float = setting(Number(allow_zero=True))
    grad_clip: float = setting(Number())
    until: str = setting(Text())
    order: Any = setting(Free(), default=None)
    """(read by :func:`stage_order` into ``stages``)"""
    stages: tuple[str, ...] = ()

    def __post_init__(self):
        expect_choice("schedule.until", self.until, self.stages)

    def trained(self) -> tuple[str, ...]:
        """The stages the job trains: those up to ``until``."""
        return self.stages[: self.stages.index(self.until) + 1]


@dataclass(frozen=True)
class JobSettings(Section):
    """The whole job: its own keys (checked first), then a section per group."""

    seed: int = setting(Int(0))
    method: str = setting(Choice(tuple(METHODS)))
    iterations: int = setting(Int(0))
    oracle: str | None = setting(Choice(ORACLES))
    precision: int | str = setting(Precision())
    force: bool = setting(Flag())
    train: bool = setting(Flag())
    experiment: str = setting(Text())
    row: str | int | None = setting(Free())
    cache_dir: str = setting(Text())
    threads: int | None = setting(Int(1, optional=True))
    model: ModelSpec
    data: DataSettings
    trainer: TrainerSettings
    eval: EvalSettings
    tracking: TrackingSettings
    scale: ScaleSettings
    schedule: ScheduleSettings
    stages: Mapping[str, StageSpec]
    """Each stage's spec by name (:func:`~demon_lab.pipeline.kinds.stage_spec`)."""
    baseline: BaselineConfig
    loss: Mapping[str, float]
    config: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)
    """The job's whole config as plain, resolved values: what its keys hash (a key is defined on the
    config as written, :mod:`demon_lab.pipeline.identity`) and what its run logs. Read, never changed."""

    @classmethod
    def of(cls, cfg: DictConfig) -> JobSettings:
        """``cfg`` as settings, or its first error as one ConfigError line."""
        own = cls.values(cfg, "")
        if not method(own["method"]).scores_passes and own["oracle"] is not None:  # (the passes take the oracle)
            raise ConfigError(f"oracle: expected null with method={own['method']} (oracles feed the DeMoN chain), "
                              f"got {own['oracle']!r}")
        try:
            baseline = BaselineConfig(**OmegaConf.to_container(cfg.baseline, resolve=True), seed=own["seed"])
        except (TypeError, ValueError) as e:
            raise ConfigError(str(e).splitlines()[0]) from None
        model = ModelSpec.of(cfg.model)
        data = DataSettings.of(cfg.data, "data")
        schedule = ScheduleSettings.of(cfg.schedule, "schedule", stages=stage_order(cfg.schedule))
        stages = {name: stage_spec(cfg, name) for name in schedule.stages}
        loss = OmegaConf.to_container(cfg.loss, resolve=True)
        try:
            check_weights(loss)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        return cls(**own, model=model, data=data, schedule=schedule, stages=stages, loss=loss, baseline=baseline,
                   eval=EvalSettings.of(cfg.eval, "eval"), trainer=TrainerSettings.of(cfg.trainer, "trainer"),
                   tracking=TrackingSettings.of(cfg.tracking, "tracking"), scale=ScaleSettings.of(cfg.scale, "scale"),
                   config=OmegaConf.to_container(cfg, resolve=True))

    def __post_init__(self):
        trained = self.schedule.trained()
        flow_oracle_study = self.oracle == "depth_motion" and "flow2" in trained  # scores flow2 only (EPE)
        if self.iterations > 0 and self.train and not {"flow2", "dm2"} <= set(trained) and not flow_oracle_study:
            raise ConfigError(f"iterations: expected 0 when schedule.until={self.schedule.until} "
                              f"(the iterative nets flow2 and dm2 are not trained), got {self.iterations}")
        synthetic = any(entry.dataset.get("_target_") == SYNTHETIC_SOURCE for entry in self.data.train)
        for name, spec in self.stages.items():
            if spec.fresh_scenes and not synthetic:
                raise ConfigError(f"schedule.stages.{name}.fresh_scenes: renders synthetic scenes, and data.train "
                                  f"has no {SYNTHETIC_SOURCE} source")
            if spec.keep_best and not self.data.val:
                raise ConfigError(f"schedule.stages.{name}.keep_best: scores the held-apart sets, and data.val "
                                  f"has none; set data.val or keep_best=0")
            if getattr(spec, "restarts", None) is not None and self.trainer.world > 1:
                raise ConfigError(f"schedule.stages.{name}.restarts: screening restarts runs in one process; "
                                  f"train with trainer.devices=1 trainer.num_nodes=1")
        for name, spec in self.stages.items():
            batch = spec.batch_size or self.data.batch_size
            if batch % self.trainer.world:
                raise ConfigError(f"trainer.devices: the batch of stage {name} ({batch}) must split evenly over "
                                  f"trainer.devices x trainer.num_nodes = {self.trainer.world} processes")
