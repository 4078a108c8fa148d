"""The kinds of training stage, one class each: flow net, depth-motion net, iterative pair, refinement net.

A stage of the schedule (``schedule.stages.NAME``, told apart by its ``kind``) is an instance of
its kind's class, and the class is everything the kind is: its options with their defaults and
rules (the options every stage of a kind has come from ``conf/schedule/``; those a stage may leave
out, the departures and probes of the ``cpu`` scale, have their defaults here, and an option its
kind does not take is an error), the loss it trains on (:meth:`StageSpec.loss`, run by the one
LightningModule of every kind, :class:`demon_lab.pipeline.stages.base.StageModule`), the nets it
trains, the ground-truth inputs it may train on, the loss weights it reads, its held-apart scores
and the state it carries from step to step. A module of this package holds each kind; a new kind is
a subclass of :class:`StageSpec` in a module of its own, listed in :data:`STAGE_SPECS`, and the YAML
that schedules it.

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
from dataclasses import fields

from omegaconf import DictConfig, OmegaConf

from demon_lab.pipeline.config import ConfigError, expect_choice
from demon_lab.pipeline.kinds.base import PRIOR_FIELDS, StageSpec, pair_priors
from demon_lab.pipeline.kinds.depth_motion import DepthMotionStage
from demon_lab.pipeline.kinds.flow import FLOW1_ONLY, FlowStage
from demon_lab.pipeline.kinds.iterative import IterativeStage
from demon_lab.pipeline.kinds.refine import RefineStage

__all__ = ["PRIOR_FIELDS", "STAGE_SPECS", "DepthMotionStage", "FlowStage", "IterativeStage", "RefineStage",
           "StageSpec", "options_of", "pair_priors", "stage_spec"]

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
