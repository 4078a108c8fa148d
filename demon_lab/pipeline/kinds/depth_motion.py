"""The depth-motion net's stage kind (``dm1``, ``dm2``)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from demon_lab.core import losses
from demon_lab.core.losses import DEPTH_MOTION_WEIGHTS, REFINED_FLOW_WEIGHTS
from demon_lab.nets.chain import DeMoN, Prediction, ground_truth_inputs, refined
from demon_lab.pipeline.config import ConfigError, expect_flag, expect_fraction
from demon_lab.pipeline.kinds.base import StageSpec, pair_priors, prediction_fields


@dataclass(frozen=True)
class DepthMotionStage(StageSpec):
    """A depth-motion net's stage: ``dm1`` (fed by the frozen flow1) or ``dm2`` (fed by the frozen
    flow2 on top of the bootstrap net, and the bootstrap motion). With ``oracle='flow'`` it is fed
    ground-truth flow. The depth-sig weight ramps over twice the stage for dm1 (DeMoN's 2M-step ramp in
    a 1M-step stage) and over the stage for dm2.

    ``gt_flow_warmup`` (a fraction of the stage, default 0 as DeMoN) feeds ground-truth flow, as the
    oracle does, for that first part of the stage, and the flow net's from then on: the net learns to
    read motion from a flow that shows it before it meets the flow it will be given.

    ``joint`` (``dm1`` of a chain with ``model.flow_refine``; default off) fine-tunes the flow refinement
    with dm1: dm1 reads the refined flow with its gradient, so the motion's losses (through
    ``model.motion_fit``, the fitted motion's) reach the refinement, whose own sequence loss stays beside
    them (not DeMoN's, whose stages train one net on the frozen flow).
    """

    kind: ClassVar[str] = "depth_motion"
    oracles: ClassVar[tuple[str | None, ...]] = (None, "flow")
    loss_weights: ClassVar[tuple[str, ...]] = (*DEPTH_MOTION_WEIGHTS, "fit_weight")
    scores_motion: ClassVar[bool] = True
    best_metric: ClassVar[str] = "tran_deg"  # the motion the depth's scale and the next pass rest on
    net: str = "dm1"
    """The net the stage trains: ``dm1`` (bootstrap) or ``dm2`` (iterative)."""
    gt_flow_warmup: float = 0.0
    """The first fraction of the stage fed ground-truth flow (0: none, as DeMoN)."""
    joint: bool = False
    """``dm1``: train the flow refinement (``flow1_refine``) with it (False: dm1 alone, as DeMoN)."""

    @classmethod
    def check(cls, name: str, values: dict[str, Any]) -> None:
        super().check(name, values)
        expect_fraction(f"schedule.stages.{name}.gt_flow_warmup", values["gt_flow_warmup"])
        expect_flag(f"schedule.stages.{name}.joint", values["joint"])
        if values["joint"] and values["net"] != "dm1":
            raise ConfigError(f"schedule.stages.{name}.joint: only dm1 is fine-tuned jointly with the flow "
                              f"refinement (this stage's net: {values['net']})")

    def trained_nets(self) -> tuple[str, ...]:
        return ("dm1", "flow1_refine") if self.joint else (self.net,)

    def weight_keys(self) -> tuple[str, ...]:
        return (*self.loss_weights, *REFINED_FLOW_WEIGHTS) if self.joint else self.loss_weights

    def loss(self, stage, batch, gt):
        chain = stage.chain
        pair, image2_2, K = stage.inputs(batch)
        given = self.oracle == "flow" or stage.global_step < self.gt_flow_warmup * self.steps
        prior = None  # dm1's prior motion where the memo has it
        if self.joint and not given:
            flow, conf = stage.frozen(functools.partial(_unrefined_flow_and_conf, chain), pair, *pair_priors(batch))
            refinement = chain.refine_flow(pair, flow)
            flow_total, flow_terms = losses.refined_flow_loss(refinement, gt, stage.weights)
            flow, conf = refined(refinement, conf)
            dm = chain.depth_motion1(pair, image2_2, flow, conf, K)
            total, terms = losses.depth_motion_loss(dm.inv_depth, dm.normals, dm.motion, gt, stage.weights,
                                                    ramp=stage.ramp(2.0), intrinsics=K,
                                                    fit_weights=_fit_weights(stage, dm), fit_flow=flow)
            return total + flow_total, {**terms, **flow_terms}
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
        return losses.depth_motion_loss(dm.inv_depth, dm.normals, dm.motion, gt, stage.weights, ramp=ramp,
                                        intrinsics=K, fit_weights=_fit_weights(stage, dm), fit_flow=flow)


def _fit_weights(stage, dm):
    """The motion fit's weights for ``loss.fit_weight``: an error where that weight is set and the net
    predicts none (no ``model.motion_fit``)."""
    if stage.weights.get("fit_weight", 0.0) > 0 and dm.weights is None:
        raise ConfigError("loss.fit_weight: classifies the motion fit's per-pixel weights; set model.motion_fit")
    return dm.weights


def _unrefined_flow_and_conf(chain: DeMoN, pair, prior_flow=None, prior_motion=None):
    """The frozen flow1's level-2 flow before the refinement, and its confidence."""
    return _flow_and_conf(chain.flow_net1(pair, prior_flow, refine=False)[1])


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
    return (*prediction_fields(prev), *_flow_and_conf(chain.flow_net2(pair, image2_2, K, prev, prev)[1]))


def _flow_and_conf(flowconf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return flowconf[:, :2], flowconf[:, 2:]
