"""The flow net's stage kind (``flow1``, ``flow2``)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from demon_lab.core import losses
from demon_lab.core.losses import FLOW_WEIGHTS, REFINED_FLOW_WEIGHTS
from demon_lab.nets.chain import DeMoN, ground_truth_inputs
from demon_lab.pipeline.config import ConfigError, expect_choice, expect_fraction, expect_positive
from demon_lab.pipeline.kinds.base import StageSpec, pair_priors, without_unstarted_sig

FLOW_NETS = ("flow1", "flow2", "flow1_refine")
"""The nets a flow stage trains."""

FLOW1_ONLY = {"layers_first": "trains on 2-D layers", "restarts": "screens restarts"}
"""The options only the bootstrap flow net's stage takes, and what they do."""

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
    """The net the stage trains: ``flow1`` (bootstrap), ``flow2`` (iterative) or ``flow1_refine`` (the
    refinement of the bootstrap flow, ``model.flow_refine``: its updates' level-2 flows scored against the
    true flow, the later ones more, and their matches against the true displacement with
    ``loss.flow_match``, :func:`demon_lab.core.losses.refined_flow_loss`; the frozen flow1's flow as its
    input)."""
    sig_start: float = 0.0
    """The fraction of the stage before its sig terms ramp in (0: DeMoN's; 1: never)."""
    level5_fade: float = 1 / 3
    """The fraction of the stage over which the level-5 terms fade out (DeMoN's third)."""
    layers_first: float | None = None
    """``flow1``: the first fraction of the stage on 2-D layers under affine motion (None: none)."""
    restarts: tuple[int, int] | None = None
    """``flow1``: ``[k, steps]`` starts screened on the held-apart sets (None: one start)."""

    def weight_keys(self) -> tuple[str, ...]:
        if self.net == "flow1_refine":
            return REFINED_FLOW_WEIGHTS
        return without_unstarted_sig(self.loss_weights, self.sig_start)

    def curriculum(self) -> dict[str, Any]:
        return {**super().curriculum(), "layers_first": self.layers_first}

    def loss(self, stage, batch, gt):
        chain = stage.chain
        pair, image2_2, K = stage.inputs(batch)
        if self.net == "flow1_refine":
            flow, = stage.frozen(functools.partial(_unrefined_flow, chain), pair, *pair_priors(batch))
            return losses.refined_flow_loss(chain.refine_flow(pair, flow), gt, stage.weights)
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
        expect_choice(key + "net", net, FLOW_NETS)
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


def _unrefined_flow(chain: DeMoN, pair, prior_flow=None, prior_motion=None):
    """The frozen flow1's level-2 flow, before the refinement (on the classical prior the batch carries)."""
    return (chain.flow_net1(pair, prior_flow, refine=False)[1][:, :2],)
