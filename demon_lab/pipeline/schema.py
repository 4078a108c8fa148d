"""The chain's options (``model``) as a typed value.

Hydra composes ``conf/`` into a DictConfig and :func:`demon_lab.pipeline.validate.validate`
checks it, one line per error. The pipeline then reads the chain's options through
:class:`ModelSpec` rather than through the raw config: every key is in ``conf/model/demon.yaml``, so
its defaults are written there and nowhere else. Each training stage is typed by its kind's class
(:mod:`demon_lab.pipeline.kinds`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from typing import Any

from omegaconf import DictConfig, OmegaConf

from demon_lab.pipeline.config import (
    ConfigError,
    expect_flag,
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
    motion_fit: int | None
    flow_refine: int | None
    fit_weights: str
    fit_starts: int
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
                          {k: values[k] for k in PRIOR_KEYS}, prefix="model.", motion_fit=values["motion_fit"],
                          flow_refine=values["flow_refine"], fit_weights=values["fit_weights"],
                          fit_starts=values["fit_starts"])
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

    def net_options(self) -> dict[str, str | int | None]:
        """The options that decide the chain's nets beside variant, width and correlation, as the chain
        takes them (keyword arguments): the priors, the motion fit and the flow refinement."""
        return {**self.priors(), "motion_fit": self.motion_fit, "flow_refine": self.flow_refine,
                "fit_weights": self.fit_weights, "fit_starts": self.fit_starts}

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
