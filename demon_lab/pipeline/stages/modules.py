"""The four kinds of training stage: flow net, depth-motion net, iterative pair, refinement net.

The schedule (``conf/schedule/``) composes them in the released code's order: flow1 and dm1
(bootstrap), flow2 and dm2 (iterative nets trained one after the other), iterative (flow2 + dm2
jointly, with DeMoN's queue of previous predictions) and refine.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from demon_lab.core import losses
from demon_lab.nets.chain import Prediction, ground_truth_inputs
from demon_lab.pipeline.stages.base import PRIOR_FIELDS, StageModule, pair_priors


class FlowStage(StageModule):
    """Trains ``flow1`` (bootstrap) or ``flow2`` (iterative, its inputs from the frozen bootstrap
    net, or from ground truth with ``oracle='depth_motion'``). Sig weights ramp in over the first
    third; the level-5 losses fade out over it (DeMoN's `training/v2/training.py`; docs/reference.md §4).

    ``sig_start`` (a fraction of the stage, default 0 as DeMoN; 1: never) holds the sig weights at 0 until
    then and starts their ramp there: a stage far shorter than DeMoN's lets the net find correspondence
    with the flow term alone first, since near zero flow, where an untrained net starts, the sig terms'
    gradient outweighs the flow term's (the ratios: docs/notes/2026-11-cpu-profile.md, "The flow stages train without
    their sig terms").

    ``level5_fade`` (a fraction of the stage, default DeMoN's 1/3) is how long the level-5 terms take
    to fade out: an option for probes of a short schedule (its probe: docs/notes/2026-11-cpu-profile.md, "What limits
    learning: probes of the recipe").
    """

    def __init__(self, *args, net: str = "flow1", sig_start: float = 0.0, level5_fade: float = 1 / 3, **kwargs):
        super().__init__(*args, trained=[net], **kwargs)
        self.net, self.sig_start, self.level5_fade = net, float(sig_start), float(level5_fade)

    def stage_loss(self, batch, gt):
        pair, image2_2, K = self.inputs(batch)
        if self.net == "flow1":
            prior2 = batch.get("prior_flow")  # computed once per pair where the data carries it
            if self.chain.flow1_prior and prior2 is None:
                prior2, = self.frozen(lambda p: (self.chain.prior_flow(p),), pair)
            flow5, flow2 = self.chain.flow1(pair, prior2=prior2)
        else:
            oracle = self.oracle == "depth_motion"
            prev = self.bootstrap(pair, image2_2, K, batch) if not oracle or self.chain.flow2_prior else None
            with torch.no_grad():
                src = ground_truth_inputs(batch, K) if oracle else prev
            flow5, flow2 = self.chain.flow_net2(pair, image2_2, K, src, prev)
        return losses.flow_loss(flow5, flow2, gt, self.weights, ramp=self.ramp(1 / 3, self.sig_start),
                                 level5=self.level5(self.level5_fade))


class DepthMotionStage(StageModule):
    """Trains ``dm1`` (fed by the frozen flow1) or ``dm2`` (fed by the frozen flow2 on top of the
    bootstrap net, and the bootstrap motion). With ``oracle='flow'`` it is fed ground-truth flow.
    The depth-sig weight ramps over twice the stage for dm1 (DeMoN's 2M-step ramp in a 1M-step
    stage) and over the stage for dm2.

    ``gt_flow_warmup`` (a fraction of the stage, default 0 as DeMoN) feeds ground-truth flow, as the
    oracle does, for that first part of the stage, and the flow net's from then on: the net learns
    to read motion from a flow that shows it before it meets the flow it will be given.
    """

    def __init__(self, *args, net: str = "dm1", gt_flow_warmup: float = 0.0, **kwargs):
        super().__init__(*args, trained=[net], **kwargs)
        self.net, self.gt_flow_warmup = net, float(gt_flow_warmup)

    def stage_loss(self, batch, gt):
        pair, image2_2, K = self.inputs(batch)
        given = self.oracle == "flow" or self.global_step < self.gt_flow_warmup * self.steps
        prior = None  # dm1's prior motion where the memo has it
        if self.net == "dm1" and not given:
            flow, conf, *prior = self.frozen(self._bootstrap_flow, pair, K, *pair_priors(batch))
            prior = prior[0] if prior else None
        elif self.net == "dm2":
            *fields, flow, conf = self.frozen(self._iterative_flow, pair, image2_2, K, *pair_priors(batch))
            prev = Prediction(*fields)
        if given:
            with torch.no_grad():
                flow = ground_truth_inputs(batch, K).flow
                conf = torch.isfinite(flow).to(flow.dtype)
        if self.net == "dm1":
            dm = self.chain.depth_motion1(pair, image2_2, flow, conf, K, prior)
        else:  # (the inputs are built without gradient)
            dm = self.chain.depth_motion2(pair, image2_2, flow, conf, prev.motion, K)
        ramp = self.ramp(2.0 if self.net == "dm1" else 1.0)
        return losses.depth_motion_loss(dm.inv_depth, dm.normals, dm.motion, gt, self.weights, ramp=ramp)

    def _bootstrap_flow(self, pair, K, prior_flow=None, prior_motion=None):
        """``flow1``'s flow and confidence, and with ``dm1_prior`` the RANSAC motion of that flow (or of
        its prior flow); ``prior_flow``, ``prior_motion`` where the batch carries them (``ransac_prior``'s
        motion is the prior flow's: :mod:`demon_lab.pipeline.stages.priors`)."""
        _, flowconf, prior_flow = self.chain.flow_net1(pair, prior_flow)
        flow, conf = _flow_and_conf(flowconf)
        given = prior_motion is not None and self.chain.dm1_prior == "ransac_prior"
        prior = prior_motion if given else self.chain.prior_motion(flow, K, prior_flow)
        return (flow, conf) if prior is None else (flow, conf, prior)

    def _iterative_flow(self, pair, image2_2, K, *priors):
        """The bootstrap pass's fields, then the iterative flow net's flow and confidence on it."""
        prev = self.chain.bootstrap(pair, image2_2, K, None, None, *priors)
        return (*_fields(prev), *_flow_and_conf(self.chain.flow_net2(pair, image2_2, K, prev, prev)[1]))


def _flow_and_conf(flowconf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return flowconf[:, :2], flowconf[:, 2:]


class IterativeStage(StageModule):
    """Trains flow2 and dm2 jointly (``_simulated_iterations`` of DeMoN's `training/v2/training.py`;
    docs/reference.md §5).

    Each step takes the batch's ``B`` new samples (their previous prediction from the frozen
    bootstrap net) plus up to ``queue_size`` samples from a FIFO queue (their previous prediction
    is their own last dm2 output); after the step the first ``queue_size`` of these, with their
    new dm2 outputs, are queued. So every sample passes the iterative net several times without
    back-propagation between passes. DeMoN: 8 new + 24 queued = 32, i.e. 4 passes per sample.

    The stage starts where DeMoN's ramps have ended: every weight at full value. ``sig_start`` (a
    fraction of the stage, default 0; 1: never) holds the flow loss's sig weights at 0 until then,
    as for :class:`FlowStage`; the depth-sig weight is not affected.
    """

    def __init__(self, *args, queue_size: int = 24, sig_start: float = 0.0, **kwargs):
        super().__init__(*args, trained=["flow2", "dm2"], **kwargs)
        self.queue_size, self.sig_start = int(queue_size), float(sig_start)
        self.queue: list[tuple[dict, Prediction]] = []

    def stage_loss(self, batch, gt):
        pair, image2_2, K = self.inputs(batch)
        prev = self.bootstrap(pair, image2_2, K, batch)
        # (a queued sample's previous prediction is its own: it needs no priors)
        samples = [({k: v[i] for k, v in batch.items() if isinstance(v, torch.Tensor) and k not in PRIOR_FIELDS},
                    _index(prev, i)) for i in range(pair.shape[0])]
        combined = samples + self.queue[: self.queue_size]
        self.queue = self.queue[self.queue_size:]
        merged = {k: torch.stack([s[k] for s, _ in combined]) for k in combined[0][0]}
        prev_all = _stack([p for _, p in combined])
        gt_all = losses.ground_truth(merged)
        pair, image2_2, K = self.inputs(merged)
        out = self.chain.iterate(pair, image2_2, K, prev_all)
        flow_sig = float(self.global_step >= self.sig_start * self.steps)
        flow_total, flow_terms = losses.flow_loss(torch.cat([out.flow5, out.conf5], 1),
                                                  torch.cat([out.flow, out.conf], 1), gt_all,
                                                  self.weights, ramp=flow_sig, level5=0.0)
        dm_total, dm_terms = losses.depth_motion_loss(out.inv_depth, out.normals, out.motion, gt_all,
                                                      self.weights, ramp=1.0)
        detached = Prediction(*(t.detach() for t in (out.flow, out.conf, out.flow5, out.conf5,
                                                       out.inv_depth, out.normals, out.motion)))
        self.queue += [(combined[i][0], _index(detached, i)) for i in range(min(self.queue_size, len(combined)))]
        return flow_total + dm_total, {**flow_terms, **dm_terms}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """The queue is training state: a resumed stage continues with the same queued samples."""
        if self.queue:
            keys = list(self.queue[0][0])
            checkpoint["demon_lab_queue"] = {
                "samples": {k: torch.stack([s[k] for s, _ in self.queue]) for k in keys},
                "predictions": {f: torch.stack([getattr(p, f) for _, p in self.queue])
                                for f in Prediction.__dataclass_fields__}}

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        saved = checkpoint.get("demon_lab_queue")
        self.queue = []
        if saved:
            n = next(iter(saved["samples"].values())).shape[0]
            preds = _stack([Prediction(**{f: v[i] for f, v in saved["predictions"].items()}) for i in range(n)])
            self.queue = [({k: v[i] for k, v in saved["samples"].items()}, _index(preds, i)) for i in range(n)]


def _fields(p: Prediction) -> tuple[torch.Tensor, ...]:
    return tuple(getattr(p, f) for f in Prediction.__dataclass_fields__)


def _index(p: Prediction, i: int) -> Prediction:
    return Prediction(*(getattr(p, f)[i] for f in Prediction.__dataclass_fields__))


def _stack(ps: list[Prediction]) -> Prediction:
    return Prediction(*(torch.stack([getattr(p, f) for p in ps]) for f in Prediction.__dataclass_fields__))


class RefineStage(StageModule):
    """Trains the refinement net on the depth of the frozen chain after ``iterations`` iterative
    passes; its depth-sig weight ramps in over the stage."""

    def __init__(self, *args, iterations: int = 3, **kwargs):
        super().__init__(*args, trained=["refine_net"], **kwargs)
        self.iterations = int(iterations)

    def stage_loss(self, batch: Mapping[str, torch.Tensor], gt):
        pair, image2_2, K = self.inputs(batch)
        inv_depth, = self.frozen(self._passes, pair, image2_2, K, *pair_priors(batch))
        refined = self.chain.refine(batch["image1"], inv_depth)
        return losses.refine_loss(refined, gt, self.weights, ramp=self.ramp(1.0))

    def _passes(self, pair, image2_2, K, *priors):
        """The inverse depth of the frozen chain's last pass."""
        p = self.chain.bootstrap(pair, image2_2, K, None, None, *priors)
        for _ in range(self.iterations):
            p = self.chain.iterate(pair, image2_2, K, p)
        return (p.inv_depth,)
