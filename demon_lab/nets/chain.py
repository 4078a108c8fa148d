"""The DeMoN chain: bootstrap net, iterative net, refinement net (docs/reference.md §1.4; DeMoN's
``BootstrapNet``, ``IterativeNet`` and ``RefinementNet`` in `python/depthmotionnet/networks_original.py`,
chained by `examples/example.py`).

``DeMoN.forward(image1, image2, intrinsics, iterations=3, oracle=None, gt=None)`` returns one
:class:`Prediction` per pass — index 0 is the bootstrap net, index k the k-th iterative pass —
and the refined full-resolution inverse depth, so an iteration sweep is an argument, not a model.

Oracles are inputs, not separate models (the same weights run with and without them):
``oracle="flow"`` replaces the flow (and confidence) fed to the depth-motion nets with the
ground-truth flow; ``oracle="depth_motion"`` replaces the depth, normals and motion fed to the
iterative flow net with ground truth. Both need ``gt`` with
``inv_depth`` (B, 1, H, W) and ``motion`` (B, 6). The extra inputs of every net are built by
:func:`flow_net_inputs` and :func:`depth_motion_net_inputs`, which the training stages share.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from demon_lab.core import geometry as geo
from demon_lab.core import loss_maps, warping
from demon_lab.core.epipolar import fit_motion
from demon_lab.core.execution import float32
from demon_lab.nets.blocks import VARIANTS, check_correlation, check_size
from demon_lab.nets.depth_motion_net import DepthMotion, DepthMotionNet
from demon_lab.nets.flow_net import FlowNet
from demon_lab.nets.flow_refine import FlowRefine, Refinement
from demon_lab.nets.prior import CHOICES as PRIOR_CHOICES
from demon_lab.nets.prior import DIS_UPSAMPLE, RANSAC_SETTINGS, dis_prior, ransac_motion
from demon_lab.nets.refine_net import RefineNet
from demon_lab.nets.slots import ATTRIBUTES, SLOTS

ORACLES = (None, "flow", "depth_motion")
FIT_WEIGHTS = ("learned", "uniform", "confidence")
"""``DeMoN(fit_weights=...)``: the motion fit's per-pixel weights, the depth-motion net's (``learned``),
all equal (``uniform``: what the learned weights add is the difference), or the depth-motion net's times
the confidence of the flow it reads (``confidence``: under ``flow_refine`` the bootstrap flow's
confidence is the refinement's own head, :class:`demon_lab.nets.flow_refine.FlowRefine`, and dm1 reads
it as its confidence input; elsewhere the flow net's confidence channels, their mean within [0, 1])."""
COMPATS = (None, "demon_original")
"""``DeMoN(compat=...)``: None (demon_lab's inputs, docs/reference.md §11) or DeMoN's released graph exactly."""



def _choices(values: tuple) -> str:
    return ", ".join("null" if v is None else str(v) for v in values)


def check_options(variant: str, width: float, compat: str | None, correlation, priors: dict[str, str | None],
                  prefix: str = "", motion_fit: int | None = None, flow_refine: int | None = None,
                  fit_weights: str = "learned", fit_starts: int = 0) -> None:
    """The rules of the chain's options, one ValueError line naming the option (``prefix`` + its name:
    ``model.`` where a config sets them): the variant and compat, a positive width, the correlation
    front, each prior's choices, ``ransac_prior``'s flow1 prior, the motion fit's steps (a positive
    integer, without a motion prior: the fit reads the motion itself; its further starts, >= 0, only
    with it), the flow refinement's updates (a
    positive integer), and DeMoN's released graph (``compat=demon_original``) with neither a correlation
    front, nor priors, nor a motion fit, nor a flow refinement."""
    p = prefix
    if fit_weights not in FIT_WEIGHTS:
        raise ValueError(f"{p}fit_weights: expected one of {_choices(FIT_WEIGHTS)}, got {fit_weights!r}")
    if fit_weights != "learned" and motion_fit is None:
        raise ValueError(f"{p}fit_weights: {fit_weights} weighs the motion fit's vectors; set {p}motion_fit")
    if isinstance(fit_starts, bool) or not isinstance(fit_starts, int) or fit_starts < 0:
        raise ValueError(f"{p}fit_starts: expected a number of further starts >= 0, got {fit_starts!r}")
    if fit_starts and motion_fit is None:
        raise ValueError(f"{p}fit_starts: {fit_starts} starts of the motion fit; set {p}motion_fit")
    for key, value, counted, lacking in (
            ("flow_refine", flow_refine, "updates", "which has no flow refinement"),
            ("motion_fit", motion_fit, "Gauss-Newton steps", "whose motion is a fully connected head")):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{p}{key}: expected null or a number of {counted} >= 1, got {value!r}")
        if compat == "demon_original":
            raise ValueError(f"{p}{key}: compat=demon_original reproduces DeMoN's released graph, {lacking}; "
                             f"leave {p}{key} null")
    if motion_fit is not None:
        for key in ("dm1_prior", "dm2_prior"):
            if priors.get(key) is not None:
                raise ValueError(f"{p}{key}: the motion fit (motion_fit={motion_fit}) reads the motion from the flow "
                                 f"itself, not as a correction of a prior motion; leave {p}{key} null")
    if variant not in VARIANTS:
        raise ValueError(f"{p}variant: expected one of {_choices(VARIANTS)}, got {variant!r}")
    if isinstance(width, bool) or not isinstance(width, int | float) or not width > 0:
        raise ValueError(f"{p}width: expected a positive number, got {width!r}")
    if compat not in COMPATS:
        raise ValueError(f"{p}compat: expected one of {_choices(COMPATS)}, got {compat!r}")
    if compat == "demon_original" and variant != "v1":
        raise ValueError(f"{p}compat: demon_original reproduces DeMoN's released v1 graph; it needs {p}variant=v1, "
                         f"got {variant}")
    if correlation is not None:
        try:
            check_correlation(correlation)
        except ValueError as e:
            raise ValueError(f"{p}{e}") from None
        if compat == "demon_original":
            raise ValueError(f"{p}correlation: compat=demon_original reproduces DeMoN's released graph, which has "
                             f"no correlation front; leave {p}correlation null")
    for key, value in priors.items():
        if value not in PRIOR_CHOICES[key]:
            raise ValueError(f"{p}{key}: expected one of {_choices(PRIOR_CHOICES[key])}, got {value!r}")
    if priors["dm1_prior"] == "ransac_prior" and priors["flow1_prior"] is None:
        raise ValueError(f"{p}dm1_prior: ransac_prior reads flow1's classical prior flow; set {p}flow1_prior "
                         f"(dis or dis_x2)")
    for key, value in priors.items():
        if value is not None and compat == "demon_original":
            raise ValueError(f"{p}{key}: compat=demon_original reproduces DeMoN's released graph, whose nets have "
                             f"no priors; leave {p}{key} null")

@dataclass
class Prediction:
    """One pass of the chain, all at level 2 (1/4 of the input) except ``*5`` (level 5)."""

    flow: torch.Tensor  # (B, 2, h, w) normalised
    conf: torch.Tensor  # (B, 2, h, w)
    flow5: torch.Tensor  # (B, 2, h/8, w/8)
    conf5: torch.Tensor
    inv_depth: torch.Tensor  # (B, 1, h, w), unit-baseline scale
    normals: torch.Tensor  # (B, 3, h, w)
    motion: torch.Tensor  # (B, 6)


@dataclass
class ChainOutput:
    passes: list[Prediction]  # bootstrap, then one per iteration
    refined: torch.Tensor | None  # (B, 1, H, W) inverse depth (v2: (B, 4, H, W) with normals); None unrefined
    priors: Prediction | None = None  # the classical priors alone, no net (DeMoN.priors_alone), where asked


def finite(x: torch.Tensor) -> torch.Tensor:
    """DeMoN's ``replace_nonfinite``: NaN and inf -> 0."""
    return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def net_intrinsics(intrinsics: torch.Tensor, compat: str | None = None) -> torch.Tensor:
    """The intrinsics the iterative net's inputs are computed with: the given ones (demon_lab), or
    under ``compat="demon_original"`` DeMoN's constant (``IterativeNet`` of
    `python/depthmotionnet/networks_original.py` builds its ``depth_to_flow`` and ``flow_to_depth``
    with [0.89115971, 1.18821287, 0.5, 0.5], whatever the images)."""
    if compat != "demon_original":
        return intrinsics
    return torch.tensor(geo.DEMON_INTRINSICS, dtype=intrinsics.dtype, device=intrinsics.device).expand_as(intrinsics)


def downsample_image(image: torch.Tensor) -> torch.Tensor:
    """Image 2 at level 2, by 4x4 area averaging (the training code's ``resize_area``)."""
    return F.avg_pool2d(image, 4)


@dataclass
class GroundTruthInputs:
    """Ground truth at level 2 for the oracles."""

    flow: torch.Tensor
    inv_depth: torch.Tensor
    normals: torch.Tensor
    motion: torch.Tensor


@float32
def ground_truth_inputs(gt: dict, intrinsics: torch.Tensor) -> GroundTruthInputs:
    inv2 = loss_maps.inverse_depth_pyramid(gt["inv_depth"], levels=2)[2]
    return GroundTruthInputs(
        flow=geo.flow_from_depth_motion(inv2, gt["motion"], intrinsics),
        inv_depth=inv2, normals=geo.normals_from_depth(inv2, intrinsics), motion=gt["motion"])


@float32
def flow_net_inputs(image2_2: torch.Tensor, inv_depth: torch.Tensor, normals: torch.Tensor,
                    motion: torch.Tensor, intrinsics: torch.Tensor, compat: str | None = None) -> torch.Tensor:
    """The iterative flow net's 9 extra channels (stop-gradient): image 2 warped with the flow of
    the previous depth+motion, that flow (vectors of norm >= 1, and NaN, set to 0), the previous
    inverse depth and normals (non-finite values set to 0; ``compat="demon_original"``: as they
    are, and DeMoN's ``warp2d``, as ``flow_block_demon_original`` does)."""
    original = compat == "demon_original"
    with torch.no_grad():
        flow = geo.flow_from_depth_motion(inv_depth, motion, intrinsics)
        keep = (flow.norm(dim=1, keepdim=True) < 1)  # False for NaN
        flow = torch.where(keep, flow, torch.zeros_like(flow))
        warped = (warping.warp2d if original else warping.warp_image)(image2_2, flow)
        if original:
            return torch.cat([warped, flow, inv_depth, normals], 1)
        return torch.cat([warped, flow, finite(inv_depth), finite(normals)], 1)


@float32
def depth_motion_net_inputs(image2_2: torch.Tensor, flow: torch.Tensor, conf: torch.Tensor,
                            prev_motion: torch.Tensor | None, intrinsics: torch.Tensor,
                            compat: str | None = None) -> torch.Tensor:
    """The depth-motion net's extra channels (stop-gradient): image 2 warped with the flow, the
    flow and its confidence, and (iterative net) the inverse depth triangulated from the flow with
    the previous motion, clipped to [0, 50] as v2 does; non-finite values set to 0. demon_lab
    clips for v1 too, because it trains v1 from scratch and an untrained flow net's triangulated
    inverse depth is unbounded (docs/notes/2026-11-cpu-profile.md, "The triangulated depth is clipped for v1 too").
    ``compat="demon_original"``: what
    ``depthmotion_block_demon_original`` feeds its net, i.e. DeMoN's ``warp2d``, no clipping and
    the flow and confidence as they are."""
    with torch.no_grad():
        if compat == "demon_original":
            parts = [warping.warp2d(image2_2, flow), flow, conf]
            if prev_motion is not None:
                parts.append(geo.depth_from_flow_motion(flow, prev_motion, intrinsics))
            return torch.cat(parts, 1)
        flow = finite(flow)
        parts = [warping.warp_image(image2_2, flow), flow, finite(conf)]
        if prev_motion is not None:
            parts.append(finite(geo.depth_from_flow_motion(flow, prev_motion, intrinsics, clip=(0.0, 50.0))))
        return torch.cat(parts, 1)


class DeMoN(nn.Module):
    """The whole chain. ``size`` is the input (H, W): sides multiples of 32. ``compat``: None
    (demon_lab's net inputs) or ``"demon_original"``, the inputs DeMoN's released graph computes
    (docs/reference.md §11: DeMoN's ``warp2d``, no clipping, no replacement of non-finite
    values), for its converted weights (``python -m demon_lab.convert``). ``correlation``:
    ``(max_displacement, stride)`` of a correlation front in both flow nets (:class:`FlowNet`;
    not DeMoN's design), or None. ``flow1_prior``: ``"dis"`` gives the bootstrap flow net a
    classical prior flow (:mod:`demon_lab.nets.prior`; not DeMoN's design; ``"dis_x2"``: computed on
    the pair upsampled 2x), or None. ``dm1_prior``:
    ``"ransac"`` gives the bootstrap depth-motion net the motion that 5-point RANSAC reads from the
    flow (``"ransac_prior"``: from flow1's classical prior flow), in the form the iterative net reads
    the previous motion (the depth triangulated with it), and the net predicts a correction of that
    motion, starting at none; or None. ``dm2_prior``:
    ``"previous"`` makes the iterative depth-motion net predict a correction of the previous pass's
    motion (which it reads, as DeMoN's does), starting at none, instead of the motion itself; or
    None (:mod:`demon_lab.nets.prior`; not DeMoN's design). ``flow2_prior``: ``"previous"`` makes the
    iterative flow net predict a correction of the previous pass's flow (at levels 2 and 5), starting
    at none, instead of the flow itself; or None (not DeMoN's design). ``motion_fit``: the depth-motion
    nets predict a weight per pixel and their motion is the weighted fit to the flow they read, with
    this many Gauss-Newton steps (:func:`demon_lab.core.epipolar.fit_motion`), not their fully
    connected head's; or None (DeMoN's); ``fit_weights``: :data:`FIT_WEIGHTS`; ``fit_starts``: the fit's
    starts beside the 8-point one (:func:`demon_lab.core.epipolar.fit_motion`). ``flow_refine``: the
    bootstrap flow is refined on warped features with this many updates at level 2, then
    :data:`demon_lab.nets.flow_refine.FINE_UPDATES` at level 1
    (:class:`demon_lab.nets.flow_refine.FlowRefine`, the net ``flow1_refine``, trained in a stage of its
    own after flow1); or None (DeMoN's). ``nets``: nets of one's own for
    some of the chain's slots (``flow1``, ``dm1``, ``flow2``, ``dm2``, ``refine``; each with the
    slot's signature, :mod:`demon_lab.nets.slots`), in place of DeMoN's."""

    def __init__(self, variant: str = "v1", width: float = 1.0, size: tuple[int, int] = (192, 256),
                 compat: str | None = None, correlation: tuple[int, int] | None = None,
                 flow1_prior: str | None = None, dm1_prior: str | None = None, flow2_prior: str | None = None,
                 dm2_prior: str | None = None, nets: Mapping[str, nn.Module] | None = None,
                 motion_fit: int | None = None, flow_refine: int | None = None, fit_weights: str = "learned",
                 fit_starts: int = 0):
        super().__init__()
        check_options(variant, width, compat, correlation,
                      dict(flow1_prior=flow1_prior, dm1_prior=dm1_prior, flow2_prior=flow2_prior, dm2_prior=dm2_prior),
                      motion_fit=motion_fit, flow_refine=flow_refine, fit_weights=fit_weights, fit_starts=fit_starts)
        check_size(*size)
        given = dict(nets or {})
        if set(given) - set(SLOTS):
            raise ValueError(f"nets: no slot {sorted(set(given) - set(SLOTS))}; expected some of {', '.join(SLOTS)}")
        self.variant, self.width, self.size, self.compat = variant, width, tuple(size), compat
        self.correlation = None if correlation is None else check_correlation(correlation)
        self.flow1_prior, self.dm1_prior = flow1_prior, dm1_prior
        self.flow2_prior, self.dm2_prior = flow2_prior, dm2_prior
        self.motion_fit, self.fit_weights, self.fit_starts = motion_fit, fit_weights, fit_starts
        kw = dict(variant=variant, width=width, size=self.size)
        fit = dict(fit=True) if motion_fit else {}
        own = {  # DeMoN's net of each slot that none is given for
            "flow1": lambda: FlowNet(iterative=False, correlation=self.correlation, prior=flow1_prior, **kw),
            "dm1": lambda: DepthMotionNet(iterative=dm1_prior is not None, **kw, **fit),  # + the depth from the prior
            "flow2": lambda: FlowNet(iterative=True, correlation=self.correlation, **kw),
            "dm2": lambda: DepthMotionNet(iterative=True, **kw, **fit),
            "refine": lambda: RefineNet(variant=variant, width=width)}
        for slot in SLOTS:
            setattr(self, ATTRIBUTES[slot], given[slot] if slot in given else own[slot]())
        self.plugins = tuple(slot for slot in SLOTS if slot in given)
        self.flow_refine = flow_refine
        if flow_refine:  # (a net only where asked: every other chain's state is as it was)
            self.flow1_refine = FlowRefine(variant, width, flow_refine, confidence=fit_weights == "confidence")
        with torch.no_grad():
            if self.flow2_prior and "flow2" not in given:  # the correction of the previous flow starts at none
                for head in (self.flow2.predict_flow5, self.flow2.predict_flow2):
                    head.out.conv.weight[:2].zero_()
                    head.out.conv.bias[:2].zero_()
            for slot, prior in (("dm1", self.dm1_prior), ("dm2", self.dm2_prior)):
                if prior and slot not in given:  # the correction of the prior motion starts at none
                    getattr(self, slot).motion_fc3.weight[:6].zero_()
                    getattr(self, slot).motion_fc3.bias[:6].zero_()

    def prior_flow(self, pair: torch.Tensor) -> torch.Tensor:
        """flow1's classical prior flow of ``pair`` at level 2 (``flow1_prior``:
        :func:`demon_lab.nets.prior.dis_prior`)."""
        with torch.no_grad():
            return dis_prior(pair, level=2, upsample=DIS_UPSAMPLE[self.flow1_prior])

    def bootstrap(self, pair: torch.Tensor, image2_2: torch.Tensor, intrinsics: torch.Tensor,
                  gt2: GroundTruthInputs | None = None, oracle: str | None = None,
                  prior_flow: torch.Tensor | None = None, prior_motion: torch.Tensor | None = None) -> Prediction:
        """The bootstrap pass. ``prior_flow``, ``prior_motion``: flow1's classical prior flow and
        the 5-point motion of it (``dm1_prior=ransac_prior``) where the caller has them
        (:meth:`flow_net1`, :meth:`prior_motion`); None computes them."""
        flowconf5, flowconf2, prior_flow = self.flow_net1(pair, prior_flow)
        flow, conf = flowconf2[:, :2], flowconf2[:, 2:]
        dm_flow, dm_conf = flow, conf
        if oracle == "flow":  # the ground-truth flow replaces flow1's flow and its prior
            dm_flow, dm_conf, prior_flow, prior_motion = gt2.flow, _oracle_confidence(gt2.flow), None, None
        if self.dm1_prior != "ransac_prior":  # (then the motion dm1 corrects is not the prior flow's)
            prior_motion = None
        dm = self.depth_motion1(pair, image2_2, dm_flow, dm_conf, intrinsics, prior=prior_motion,
                                prior_flow=prior_flow)
        return Prediction(flow, conf, flowconf5[:, :2], flowconf5[:, 2:], dm.inv_depth, dm.normals, dm.motion)

    def depth_motion1(self, pair: torch.Tensor, image2_2: torch.Tensor, flow: torch.Tensor, conf: torch.Tensor,
                      intrinsics: torch.Tensor, prior: torch.Tensor | None = None,
                      prior_flow: torch.Tensor | None = None) -> DepthMotion:
        """The bootstrap depth-motion net on a flow and its confidence (with ``dm1_prior``: on the
        5-point RANSAC motion of that flow, or of ``prior_flow``, flow1's classical prior, too, and
        the motion it returns is that motion corrected; ``prior`` is that motion where the caller
        has it, :meth:`prior_motion`)."""
        if not self.dm1_prior:
            return self.fitted(self.dm1(pair, depth_motion_net_inputs(image2_2, flow, conf, None, intrinsics,
                                                                       self.compat)), flow, conf, intrinsics, "dm1")
        prior = self.prior_motion(flow, intrinsics, prior_flow) if prior is None else prior
        dm = self.dm1(pair, depth_motion_net_inputs(image2_2, flow, conf, prior, intrinsics, self.compat))
        return replace(dm, motion=dm.motion + prior)

    def flow_net1(self, pair: torch.Tensor, prior_flow: torch.Tensor | None = None, refine: bool = True
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The bootstrap flow net: ``(flowconf5, flowconf2)`` as :class:`FlowNet` returns them (with
        ``flow_refine`` and ``refine``: the level-2 flow refined, :meth:`refine_flow`), and its
        classical prior flow at level 2 (``flow1_prior``; None without one): ``prior_flow`` where the
        caller has it, else computed (:meth:`FlowNet.prior_flow`)."""
        if not self.flow1_prior:
            prior_flow = None
        elif prior_flow is None:
            prior_flow = self.prior_flow(pair)
        flowconf5, flowconf2 = self.flow1(pair, prior2=prior_flow)
        if self.flow_refine and refine:
            flowconf2 = torch.cat(refined(self.refine_flow(pair, flowconf2[:, :2]), flowconf2[:, 2:]), 1)
        return flowconf5, flowconf2, prior_flow

    def refine_flow(self, pair: torch.Tensor, flow: torch.Tensor) -> Refinement:
        """The bootstrap flow at level 2 after each update of the flow refinement (``flow_refine``), with
        each update's match (:class:`demon_lab.nets.flow_refine.Refinement`)."""
        return self.flow1_refine(pair, flow)

    def prior_motion(self, flow: torch.Tensor, intrinsics: torch.Tensor,
                     prior_flow: torch.Tensor | None = None) -> torch.Tensor | None:
        """The motion ``dm1`` corrects (``dm1_prior``): 5-point RANSAC on ``flow`` (``ransac``) or on
        ``prior_flow`` where given (``ransac_prior``, on every level-2 vector with a tight
        threshold); None without the prior."""
        if not self.dm1_prior:
            return None
        read = prior_flow if self.dm1_prior == "ransac_prior" and prior_flow is not None else flow
        return ransac_motion(read, intrinsics, *RANSAC_SETTINGS[self.dm1_prior])

    def depth_motion2(self, pair: torch.Tensor, image2_2: torch.Tensor, flow: torch.Tensor, conf: torch.Tensor,
                      prev_motion: torch.Tensor, intrinsics: torch.Tensor) -> DepthMotion:
        """The iterative depth-motion net on a flow, its confidence and the previous motion (with
        ``dm2_prior``: the motion it returns is the previous motion corrected)."""
        prev_motion = prev_motion.detach()
        dm = self.dm2(pair, depth_motion_net_inputs(image2_2, flow, conf, prev_motion, intrinsics, self.compat))
        if self.dm2_prior:
            return replace(dm, motion=dm.motion + prev_motion)
        return self.fitted(dm, flow, conf, intrinsics, "dm2")

    def fitted(self, dm: DepthMotion, flow: torch.Tensor, conf: torch.Tensor, intrinsics: torch.Tensor,
               slot: str) -> DepthMotion:
        """``dm`` with ``motion_fit``: its motion the weighted fit to ``flow`` (the flow the net read, with
        its confidence ``conf``) with the weights :data:`FIT_WEIGHTS` names
        (:func:`demon_lab.core.epipolar.fit_motion`), ``dm.weights`` then the weights the fit used;
        without: ``dm`` as it is."""
        if not self.motion_fit:
            return dm
        if self.fit_weights == "uniform":
            return replace(dm, motion=fit_motion(flow, torch.ones_like(flow[:, :1]), intrinsics, self.motion_fit,
                                                 self.fit_starts))
        if dm.weights is None:
            raise ValueError(f"model.motion_fit: the {slot} net returns no per-pixel weights (DepthMotion.weights) "
                             f"for the motion fit")
        weights = dm.weights
        if self.fit_weights == "confidence":
            weights = weights * conf.float().mean(1, keepdim=True).clamp(0, 1)
        return replace(dm, motion=fit_motion(flow, weights, intrinsics, self.motion_fit, self.fit_starts),
                       weights=weights)

    def flow_net2(self, pair: torch.Tensor, image2_2: torch.Tensor, intrinsics: torch.Tensor,
                  src: Prediction | GroundTruthInputs, prev: Prediction) -> tuple[torch.Tensor, torch.Tensor]:
        """The iterative flow net on the flow of ``src``'s depth and motion (the previous pass, or
        ground truth under the depth-motion oracle): ``(flowconf5, flowconf2)`` as :class:`FlowNet`
        returns them (with ``flow2_prior``: its flows are ``prev``'s corrected). ``intrinsics`` as
        :func:`net_intrinsics` gives them."""
        extra = flow_net_inputs(image2_2, src.inv_depth, src.normals, src.motion, intrinsics, self.compat)
        flowconf5, flowconf2 = self.flow2(pair, extra)
        if self.flow2_prior:
            flowconf5 = torch.cat([flowconf5[:, :2] + prev.flow5.detach(), flowconf5[:, 2:]], 1)
            flowconf2 = torch.cat([flowconf2[:, :2] + prev.flow.detach(), flowconf2[:, 2:]], 1)
        return flowconf5, flowconf2

    def iterate(self, pair: torch.Tensor, image2_2: torch.Tensor, intrinsics: torch.Tensor,
                prev: Prediction, gt2: GroundTruthInputs | None = None,
                oracle: str | None = None) -> Prediction:
        src = gt2 if oracle == "depth_motion" else prev
        intrinsics = net_intrinsics(intrinsics, self.compat)
        flowconf5, flowconf2 = self.flow_net2(pair, image2_2, intrinsics, src, prev)
        flow, conf = flowconf2[:, :2], flowconf2[:, 2:]
        dm_flow, dm_conf = (gt2.flow, _oracle_confidence(gt2.flow)) if oracle == "flow" else (flow, conf)
        dm = self.depth_motion2(pair, image2_2, dm_flow, dm_conf, prev.motion, intrinsics)
        return Prediction(flow, conf, flowconf5[:, :2], flowconf5[:, 2:], dm.inv_depth, dm.normals, dm.motion)

    def refine(self, image1: torch.Tensor, inv_depth2: torch.Tensor) -> torch.Tensor:
        return self.refine_net(image1, inv_depth2.detach())

    def priors_alone(self, pair: torch.Tensor, intrinsics: torch.Tensor) -> Prediction | None:
        """The chain's classical priors with no net, where it has both bootstrap priors
        (``flow1_prior`` and ``dm1_prior``; None otherwise): flow1's prior flow, the 5-point RANSAC
        motion of that flow as dm1 reads it (:meth:`prior_motion`), and the inverse depth triangulated
        from the two (clipped to [0, 50], as the iterative net's input is). What the trained nets add
        to the profile is measured against it. (Its confidence is 1; it has no level-5 flow and no
        normals: zeros.)"""
        if not (self.flow1_prior and self.dm1_prior):
            return None
        with torch.no_grad():
            flow = self.prior_flow(pair).float()
            motion = self.prior_motion(flow, intrinsics, flow)
            inv_depth = finite(geo.depth_from_flow_motion(flow, motion, intrinsics, clip=(0.0, 50.0)))
        b, _, h, w = flow.shape
        level5 = flow.new_zeros(b, 2, h // 8, w // 8)
        return Prediction(flow, torch.ones_like(flow), level5, level5, inv_depth, flow.new_zeros(b, 3, h, w), motion)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, intrinsics: torch.Tensor,
                iterations: int = 3, oracle: str | None = None, gt: dict | None = None,
                refine: bool = True, priors: bool = False, prior_flow: torch.Tensor | None = None,
                prior_motion: torch.Tensor | None = None) -> ChainOutput:
        """``refine=False`` leaves out the refinement net (``refined`` is None); ``priors=True`` adds
        the classical priors alone (:meth:`priors_alone`) where the chain has them. ``prior_flow``,
        ``prior_motion``: the bootstrap pass's classical priors of this pair where the caller has them
        (:meth:`bootstrap`); None computes them."""
        if oracle not in ORACLES:
            raise ValueError(f"oracle: expected one of {ORACLES}, got {oracle!r}")
        if iterations < 0:
            raise ValueError(f"iterations: expected >= 0, got {iterations}")
        if tuple(image1.shape[2:]) != self.size:
            raise ValueError(f"image1: expected size {self.size[1]}x{self.size[0]} (H x W = {self.size}), "
                             f"got {tuple(image1.shape[2:])}")
        if oracle is not None and gt is None:
            raise ValueError(f"oracle={oracle!r} needs gt with 'inv_depth' and 'motion'")
        pair = torch.cat([image1, image2], 1)
        image2_2 = downsample_image(image2)
        gt2 = ground_truth_inputs(gt, intrinsics) if oracle is not None else None
        passes = [self.bootstrap(pair, image2_2, intrinsics, gt2, oracle, prior_flow, prior_motion)]
        for _ in range(iterations):
            passes.append(self.iterate(pair, image2_2, intrinsics, passes[-1], gt2, oracle))
        return ChainOutput(passes, self.refine(image1, passes[-1].inv_depth) if refine else None,
                           self.priors_alone(pair, intrinsics) if priors else None)


def refined(refinement: Refinement, conf: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The refined bootstrap flow and its confidence: the refinement's own (both components) where it has a
    confidence head (``fit_weights=confidence``), else ``conf``, flow1's."""
    if refinement.confidence is None:
        return refinement.flows[-1], conf
    return refinement.flows[-1], refinement.confidence.expand(-1, 2, -1, -1).to(conf.dtype)


def _oracle_confidence(flow: torch.Tensor) -> torch.Tensor:
    """Confidence fed with ground-truth flow: 1 where the flow is known, 0 elsewhere."""
    return torch.isfinite(flow).to(flow.dtype)
