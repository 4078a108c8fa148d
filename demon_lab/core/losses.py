"""DeMoN's training losses (DeMoN's `python/depthmotionnet/v2/losses.py` and the weights of
`training/v2/training.py`; docs/reference.md §4): pure functions returning ``(loss, terms)``.

All point-wise losses use :func:`pointwise_l2` (DeMoN's ``pointwise_l2_loss``) — the mean over
batch and pixels of ``sqrt(sum_channels d^2 + eps)`` with ``d = replace_nonfinite(pred - gt)``
(invalid ground truth contributes the constant ``sqrt(eps)`` and still counts in the mean, as in
DeMoN). For one channel it is a smoothed L1, for flow the end-point error, for normals the
Euclidean distance.

Weights come from a preset (``conf/loss/``); ``ramp`` multiplies the scale-invariant gradient
(sig) terms and ``level5`` the level-5 flow terms (the stage computes both from its step).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch

from demon_lab.core import geometry as geo
from demon_lab.core import loss_maps
from demon_lab.core.epipolar import sampson_px
from demon_lab.core.execution import float32

EPS = 1e-5
WEIGHT_KEYS = ("flow", "flow_conf", "flow_sig", "flow_conf_sig", "depth", "depth_sig", "normals",
               "rotation", "translation", "refine_depth", "refine_depth_sig", "refine_normals")
FLOW_WEIGHTS = ("flow", "flow_conf", "flow_sig", "flow_conf_sig")
OPTIONAL_WEIGHTS = {"fit_residual": 0.0, "flow_match": 0.0, "fit_weight": 0.0}
"""Weights a preset may leave out, with the value it then has (added after the presets were written; a
key leaves a weight at this value out, so older keys hold): ``fit_residual``, the geometric residual of
the predicted motion (:func:`motion_residual`); ``flow_match``, the flow refinement's match loss
(:func:`match_loss`); ``fit_weight``, the motion fit's per-pixel weights classified against the flow's
precise vectors (:func:`fit_weight_loss`)."""
REFINED_FLOW_WEIGHTS = ("flow", "flow_match", "fit_weight")
REFINED_FLOW_DECAY = 0.8
"""The weight of each update's flow in :func:`refined_flow_loss` relative to the next one's (RAFT's)."""
DEPTH_MOTION_WEIGHTS = ("depth", "depth_sig", "normals", "rotation", "translation", "fit_residual")
REFINE_WEIGHTS = ("refine_depth", "refine_depth_sig", "refine_normals")
FLOW_SIG_WEIGHTS = ("flow_sig", "flow_conf_sig")
PRECISE_PX = 1.0
"""A flow vector :func:`fit_weight_loss` calls precise: its end point within this many input pixels of
the truth's (the ceiling table's oracle pick, ``pick1``)."""


Terms = dict[str, torch.Tensor]


@float32
def pointwise_l2(pred: torch.Tensor, gt: torch.Tensor, eps: float = EPS) -> torch.Tensor:
    """Mean over (batch, y, x) of sqrt(sum over channels of (pred - gt)^2 + eps); (B, C, H, W).
    Pixels without ground truth (non-finite ``gt``) count as zero error; a non-finite prediction
    where there is ground truth makes the loss non-finite (the stage then stops and says so)."""
    gt = gt.detach()
    valid = torch.isfinite(gt)
    d = torch.where(valid, pred - torch.where(valid, gt, torch.zeros_like(gt)), torch.zeros_like(pred))
    return torch.sqrt((d * d).sum(1) + eps).mean()


@float32
def sig_loss(pred: torch.Tensor, gt: torch.Tensor, eps_pred: float = 1e-3, eps_gt: float = 1e-3) -> torch.Tensor:
    """Point-wise loss between scale-invariant gradient images (spacings 1, 2, 4, 8, 16), one
    Euclidean norm over the 10 gradient channels per pixel; channels of a map are separate items."""
    sp = loss_maps.scale_invariant_gradients(pred, eps=eps_pred)
    sg = loss_maps.scale_invariant_gradients(gt, eps=eps_gt)
    return pointwise_l2(sp.flatten(0, 1), sg.flatten(0, 1))


def _sig_term(weight: float, pred: torch.Tensor, gt: torch.Tensor, *eps: float) -> torch.Tensor:
    """``weight * sig_loss(pred, gt, *eps)``, and an exact zero without computing the sig images
    when the weight is 0 (a ramp not yet started, or a preset without the term): the loss and its
    gradients are bit for bit those of the full product, without its cost (docs/notes/2026-11-cpu-profile.md, "Time
    and memory")."""
    if weight == 0:
        return pred.new_zeros(())
    return weight * sig_loss(pred, gt, *eps)


@float32
def vector_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """DeMoN's motion loss: mean over the batch of sum_xyz sqrt((pred - gt)^2 + eps) (B, 3)."""
    d = pred - gt.detach()
    return torch.sqrt(d * d + EPS).sum(1).mean()


@float32
def confidence_target(flow_pred: torch.Tensor, flow_gt: torch.Tensor, scale: float = 10.0) -> torch.Tensor:
    """GT of the confidence: exp(-scale |f_pred - f_gt|) per component, with the current
    prediction (stop-gradient; DeMoN's conf_diff_scale = 10 on normalised flow)."""
    return torch.exp(-scale * (flow_pred.detach() - flow_gt).abs())


def _weighted(terms: Terms) -> torch.Tensor:
    return sum(terms.values(), torch.zeros(()))


@float32
def flow_loss(flowconf5: torch.Tensor, flowconf2: torch.Tensor, gt: Mapping[str, torch.Tensor],
              weights: Mapping[str, float], ramp: float = 1.0, level5: float = 1.0) -> tuple[torch.Tensor, Terms]:
    """Loss of a flow net: flow and confidence at levels 2 and 5, sig of flow and confidence.

    Args:
        flowconf5, flowconf2: (B, 4, h, w) predictions [flow (2), confidence (2)].
        gt: ``flow2`` and ``flow5`` ground truth (NaN = unknown).
        weights: a loss preset; ramp, level5: the stage's ramp factors.
    """
    f2, c2 = flowconf2[:, :2], flowconf2[:, 2:]
    f5, c5 = flowconf5[:, :2], flowconf5[:, 2:]
    conf2_gt = confidence_target(f2, gt["flow2"])
    terms: Terms = {
        "flow2": weights["flow"] * pointwise_l2(f2, gt["flow2"]),
        "conf2": weights["flow_conf"] * pointwise_l2(c2, conf2_gt),
        "flow2_sig": _sig_term(weights["flow_sig"] * ramp, f2, gt["flow2"]),
        "conf2_sig": _sig_term(weights["flow_conf_sig"] * ramp, c2, conf2_gt),
    }
    if level5 > 0:
        terms["flow5"] = weights["flow"] * level5 * pointwise_l2(f5, gt["flow5"])
        terms["conf5"] = weights["flow_conf"] * level5 * pointwise_l2(c5, confidence_target(f5, gt["flow5"]))
    return _weighted(terms), terms


@float32
def depth_motion_loss(inv_depth: torch.Tensor, normals: torch.Tensor, motion: torch.Tensor,
                      gt: Mapping[str, torch.Tensor], weights: Mapping[str, float],
                      ramp: float = 1.0, intrinsics: torch.Tensor | None = None,
                      fit_weights: torch.Tensor | None = None,
                      fit_flow: torch.Tensor | None = None) -> tuple[torch.Tensor, Terms]:
    """Loss of a depth-motion net: inverse depth, its sig, normals at level 2, rotation, translation,
    and where ``weights`` give ``fit_residual`` > 0 the motion's geometric residual
    (:func:`motion_residual`, with ``intrinsics``; not DeMoN's), where they give ``fit_weight`` > 0 and
    the caller gives the motion fit's per-pixel weights ``fit_weights``, their :func:`fit_weight_loss` on
    the flow the net read, ``fit_flow`` (not DeMoN's; the iterative stage, whose passes return no
    weights, leaves it out).

    ``gt``: ``inv_depth2``, ``normals2`` (level 2) and ``motion`` (B, 6), and ``flow2`` for the residual.
    The predicted depth's sig uses eps 0.01, the GT's 0.001 (as DeMoN).
    """
    terms: Terms = {
        "depth2": weights["depth"] * pointwise_l2(inv_depth, gt["inv_depth2"]),
        "depth2_sig": _sig_term(weights["depth_sig"] * ramp, inv_depth, gt["inv_depth2"], 1e-2, 1e-3),
        "normal2": weights["normals"] * pointwise_l2(normals, gt["normals2"]),
        "rotation": weights["rotation"] * vector_loss(motion[:, :3], gt["motion"][:, :3]),
        "translation": weights["translation"] * vector_loss(motion[:, 3:], gt["motion"][:, 3:]),
    }
    if weights.get("fit_residual", 0.0) > 0:
        if intrinsics is None:
            raise ValueError("loss.fit_residual: the motion's geometric residual needs the intrinsics")
        terms["fit_residual"] = weights["fit_residual"] * motion_residual(motion, gt["flow2"], intrinsics)
    if weights.get("fit_weight", 0.0) > 0 and fit_weights is not None:
        terms["fit_weight"] = weights["fit_weight"] * fit_weight_loss(fit_weights, fit_flow, gt["flow2"])
    return _weighted(terms), terms


@float32
def refined_flow_loss(refinement, gt: Mapping[str, torch.Tensor],
                      weights: Mapping[str, float]) -> tuple[torch.Tensor, Terms]:
    """Loss of the flow refinement (``model.flow_refine``, a
    :class:`demon_lab.nets.flow_refine.Refinement`): the level-2 endpoint error of each update's flow
    (:func:`pointwise_l2` against ``gt["flow2"]``, as flow1's), weighted by :data:`REFINED_FLOW_DECAY`
    to the power of the updates after it (the last weighs 1), times the flow weight (RAFT's sequence
    loss; the norm per pixel, not its square, so the precise vectors count as much as the far ones);
    and where ``weights`` give ``flow_match`` > 0, that weight times the sum over the updates of their
    :func:`match_loss` against the true flow at the update's level; where they give ``fit_weight`` > 0
    and the refinement has a confidence head, that weight times its :func:`fit_weight_loss` on the
    refined flow (``flow_precise``)."""
    flows = refinement.flows
    n = len(flows)
    terms: Terms = {"flow2_refined": weights["flow"] * sum(
        REFINED_FLOW_DECAY ** (n - 1 - k) * pointwise_l2(f, gt["flow2"]) for k, f in enumerate(flows))}
    if weights.get("flow_match", 0.0) > 0:
        terms["flow_match"] = weights["flow_match"] * sum(
            match_loss(m.log_probs, m.start, gt[f"flow{m.level}"]) for m in refinement.matches)
    if weights.get("fit_weight", 0.0) > 0 and refinement.confidence is not None:
        terms["flow_precise"] = weights["fit_weight"] * fit_weight_loss(refinement.confidence, flows[-1],
                                                                        gt["flow2"])
    return _weighted(terms), terms


@float32
def window_target(start: torch.Tensor, truth: torch.Tensor, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The true displacement from ``start`` to ``truth`` (B, 2, h, w, normalised flows) as a distribution
    over a window of reach ``radius`` pixels (B, D*D, h, w; the order of
    :func:`demon_lab.nets.blocks.correlation`'s channels): its four neighbouring displacements with
    their bilinear weights, so that the distribution's mean is the displacement; and where it lies in
    the window with a true flow there (B, h, w), bool."""
    height, width = start.shape[2:]
    d = (truth - start) * start.new_tensor([width, height]).view(1, 2, 1, 1)
    known = torch.isfinite(d).all(1)
    x, y = (torch.where(known, d[:, i], torch.zeros_like(d[:, i])) + radius for i in (0, 1))
    n = 2 * radius + 1
    inside = known & (x >= 0) & (x <= n - 1) & (y >= 0) & (y <= n - 1)
    x, y = x.clamp(0, n - 1), y.clamp(0, n - 1)
    x0, y0 = x.floor().clamp(max=n - 2), y.floor().clamp(max=n - 2)
    ax, ay = x - x0, y - y0
    target = start.new_zeros(start.shape[0], n * n, height, width)
    for dx, dy, weight in ((0, 0, (1 - ax) * (1 - ay)), (1, 0, ax * (1 - ay)), (0, 1, (1 - ax) * ay), (1, 1, ax * ay)):
        target.scatter_add_(1, ((y0 + dy) * n + x0 + dx).long().unsqueeze(1), weight.unsqueeze(1))
    return target, inside


@float32
def match_loss(log_probs: torch.Tensor, start: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """The cross-entropy of a window's match probabilities (``log_probs`` (B, D*D, h, w), centred on the
    flow ``start``) with the true displacement's :func:`window_target`, over the pixels whose true
    displacement lies in the window: it trains the features to match where the endpoint error of a
    soft argmax trains them only through the mean (the probe: docs/notes/2026-12-learned-motion.md)."""
    radius = (math.isqrt(log_probs.shape[1]) - 1) // 2
    target, inside = window_target(start, truth.detach(), radius)
    per_pixel = -(target * log_probs).sum(1)
    return (per_pixel * inside).sum() / inside.sum().clamp_min(1)


@float32
def fit_weight_loss(fit_weights: torch.Tensor, flow: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """The binary cross-entropy of the motion fit's per-pixel weights (B, 1, h, w) in (0, 1) with the
    label "this vector of ``flow`` (B, 2, h, w, normalised, a level-2 grid of 1/4 of the input) is
    precise" (its end point within :data:`PRECISE_PX` input pixels of ``truth``'s), over the pixels
    whose truth is known: the weights learn to be the probability that a vector is precise.

    The fit's motion loss alone moves them by a gradient through the solver, summed over every pixel of
    the pair; Yi et al. (CVPR 2018, "Learning to Find Good Correspondences", Section 4) found that loss
    alone does not train the weights from scratch and classify each correspondence as well. The fit
    design's weights trained without this loss read the motion worse than RANSAC on the same flow
    (docs/notes/2026-12-learned-motion.md, the ceiling table's row "no loss.fit_weight")."""
    height, width = flow.shape[2:]
    pixels = flow.new_tensor([4 * width, 4 * height]).view(1, 2, 1, 1)
    error = ((flow.detach().float() - truth) * pixels).norm(dim=1, keepdim=True)
    known = torch.isfinite(error)
    label = (error <= PRECISE_PX).float()
    per_pixel = torch.nn.functional.binary_cross_entropy(fit_weights.float().clamp(1e-6, 1 - 1e-6), label,
                                                         reduction="none")
    return (per_pixel * known).sum() / known.sum().clamp_min(1)


@float32
def motion_residual(motion: torch.Tensor, flow: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """The geometric residual of a predicted motion (B, 6): the mean, over the pixels where the
    ground-truth ``flow`` (B, 2, h, w) is known, of ``log(1 + d)`` with ``d`` the Sampson distance in
    pixels of that flow's correspondences to the motion's epipolar geometry
    (:func:`demon_lab.core.epipolar.sampson_px`): zero for the true motion, and a gradient for every
    motion, robust to the pixels far off."""
    distance, valid = sampson_px(flow.detach(), motion, intrinsics)
    return (torch.log1p(distance) * valid).sum() / valid.sum().clamp_min(1)


@float32
def refine_loss(refined: torch.Tensor, gt: Mapping[str, torch.Tensor], weights: Mapping[str, float],
                ramp: float = 1.0) -> tuple[torch.Tensor, Terms]:
    """Loss of the refinement net at full resolution: depth, its sig, and (v2) normals."""
    terms: Terms = {
        "depth0": weights["refine_depth"] * pointwise_l2(refined[:, :1], gt["inv_depth0"]),
        "depth0_sig": _sig_term(weights["refine_depth_sig"] * ramp, refined[:, :1], gt["inv_depth0"], 1e-2, 1e-3),
    }
    if refined.shape[1] == 4:
        terms["normal0"] = weights["refine_normals"] * pointwise_l2(refined[:, 1:], gt["normals0"])
    return _weighted(terms), terms


class GroundTruth(Mapping):
    """DeMoN's ``prepare_ground_truth_tensors`` (`python/depthmotionnet/v2/losses.py`;
    docs/reference.md §4) from a batch of samples, each tensor computed on first access: inverse
    depth at levels 0, 2, 5 (median pyramid, built only as deep as a key needs), flow at levels 2
    and 5 from depth and motion (level 1 of both too, for the flow refinement's matches: not
    DeMoN's; or, for a batch that carries ``flow`` and no geometry, the 2-D
    layers of ``layers_first``, that flow's mean over each level's pixel), normals at levels 0 and 2,
    and the motion. A stage reads only what its loss does (the flow stages no normals, the
    depth-motion stages no level 5), with the same values as computing everything."""

    KEYS = ("inv_depth0", "inv_depth1", "inv_depth2", "inv_depth5", "flow1", "flow2", "flow5", "normals0", "normals2",
            "motion")

    def __init__(self, batch: Mapping[str, torch.Tensor]):
        self._batch = batch
        self._values: dict[str, torch.Tensor] = {}
        self._pyramid: list[torch.Tensor] = []

    def _level(self, k: int) -> torch.Tensor:
        if not self._pyramid:
            self._pyramid = loss_maps.inverse_depth_pyramid(self._batch["inv_depth"], levels=0)
        while len(self._pyramid) <= k:
            self._pyramid.append(loss_maps.median_downsample(self._pyramid[-1]))
        return self._pyramid[k]

    def _compute(self, key: str) -> torch.Tensor:
        b = self._batch
        k1, k2 = b["intrinsics"], b.get("intrinsics2", b["intrinsics"])
        if key == "motion":
            return b["motion"]
        kind, level = key.rstrip("0123456789"), int(key[-1])
        if kind == "inv_depth":
            return self._level(level)
        if kind == "flow" and "inv_depth" not in b:  # a pair with flow and no geometry (2-D layers): its area mean
            return torch.nn.functional.avg_pool2d(b["flow"], 2**level) if level else b["flow"]
        if kind == "flow":
            return geo.flow_from_depth_motion(self._level(level), self["motion"], k1, k2)
        return geo.normals_from_depth(self._level(level), k1)

    def __getitem__(self, key: str) -> torch.Tensor:
        if key not in self.KEYS:
            raise KeyError(key)
        if key not in self._values:
            self._values[key] = self._compute(key)
        return self._values[key]

    def __setitem__(self, key: str, value: torch.Tensor) -> None:
        """Replace one target (tests and diagnostics substitute their own)."""
        if key not in self.KEYS:
            raise KeyError(key)
        self._values[key] = value

    def __iter__(self):
        return iter(self.KEYS)

    def __len__(self) -> int:
        return len(self.KEYS)


def ground_truth(batch: Mapping[str, torch.Tensor]) -> GroundTruth:
    """The loss targets of a batch (:class:`GroundTruth`, computed as the loss reads them)."""
    return GroundTruth(batch)


def ease_out_quad(step: int, duration: float) -> float:
    """tfutils' ease_out_quad from 0 to 1 over ``duration`` steps (1 for duration <= 0)."""
    if duration <= 0:
        return 1.0
    t = min(max(step / duration, 0.0), 1.0)
    return 1 - (1 - t) ** 2


def ease_in_quad_down(step: int, duration: float) -> float:
    """tfutils' ease_in_quad from 1 to 0 over ``duration`` steps (0 for duration <= 0)."""
    if duration <= 0:
        return 0.0
    t = min(max(step / duration, 0.0), 1.0)
    return 1 - t * t


def preset(name: str) -> dict[str, float]:
    """The loss weights of ``conf/loss/NAME.yaml`` (``released_code``: the job's default), with the
    presets it builds on (its ``defaults``) merged in, as Hydra composes them."""
    import yaml

    from demon_lab.resources import CONF

    def load(name: str) -> dict:
        data = yaml.safe_load((CONF / "loss" / f"{name}.yaml").read_text())
        merged: dict = {}
        for parent in data.pop("defaults", []):
            merged.update(load(parent))
        return {**merged, **data}

    return check_weights(load(name))


def check_weights(weights: Mapping[str, float]) -> dict[str, float]:
    missing = [k for k in WEIGHT_KEYS if k not in weights]
    extra = [k for k in weights if k not in WEIGHT_KEYS and k not in OPTIONAL_WEIGHTS and k != "name"]
    if missing or extra:
        raise ValueError(f"loss: weights {missing or extra} {'missing' if missing else 'unknown'}; "
                         f"expected {', '.join(WEIGHT_KEYS)} (and optionally {', '.join(OPTIONAL_WEIGHTS)})")
    out = {k: float(weights[k]) for k in WEIGHT_KEYS}
    out |= {k: float(weights.get(k, v)) for k, v in OPTIONAL_WEIGHTS.items()}
    bad = [k for k, v in out.items() if not v >= 0]
    if bad:
        raise ValueError(f"loss.{bad[0]}: expected a non-negative weight, got {out[bad[0]]}")
    return out
