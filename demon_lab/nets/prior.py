"""Classical priors for the bootstrap nets (``model.flow1_prior``, ``model.dm1_prior``; not DeMoN's design).

DeMoN's bootstrap flow net reads the two images alone; its iterative flow net reads a prior flow
(from the previous depth and motion) and image 2 warped with it. ``model.flow1_prior=dis`` gives the
bootstrap net a prior in the same form, from a classical optical flow of the pair: OpenCV's DIS
flow (Kroeger et al. 2016), the flow Base-FF reads (:mod:`demon_lab.baselines.methods`), computed
at the input resolution and averaged down to level 2. The net predicts a correction of it
(docs/cpu_scale.md, "Classical priors for the bootstrap nets").

DeMoN's bootstrap depth-motion net reads the flow alone; its iterative one also reads the depth
triangulated from the flow with the previous motion. ``model.dm1_prior=ransac`` gives the bootstrap
net a motion in the same form, from a classical solver on the flow it reads: Nister's 5-point
algorithm in OpenCV's USAC (a RANSAC variant) on a fixed subset of the level-2 flow vectors, the
solver Base-Mat-F runs on the whole flow (:mod:`demon_lab.baselines.methods`) made cheap enough for
every training step, and the net predicts a correction of that motion.

DeMoN's iterative depth-motion net reads the previous pass's motion (through the depth triangulated
with it) and predicts the motion anew. ``model.dm2_prior=previous`` makes it predict a correction
of the previous motion instead, starting at none: a pass begins where the last one ended.

DeMoN's iterative flow net reads the flow of the previous depth and motion (and image 2 warped with
it) and predicts the flow anew. ``model.flow2_prior=previous`` makes it predict a correction of the
previous pass's flow instead, starting at none, as ``dm2_prior=previous`` does for the motion: the
geometric flow stays an input, and a pass starts from the flow the pass before it found.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from demon_lab.baselines.twoview import (
    BaselineFailure,
    dense_flow,
    pixel_intrinsics,
    pose_from_essential,
    scaled_threshold,
    to_gray_u8,
)

PRIORS = (None, "dis")
"""``model.flow1_prior``: none, or OpenCV's DIS flow."""
MOTION_PRIORS = (None, "ransac")
"""``model.dm1_prior``: none, or 5-point RANSAC on the flow."""
PREVIOUS_MOTION_PRIORS = (None, "previous")
"""``model.dm2_prior``: none, or the previous pass's motion."""
PREVIOUS_FLOW_PRIORS = (None, "previous")
"""``model.flow2_prior``: none, or the previous pass's flow."""
RANSAC_THRESHOLD_PX = 2.0
"""The 5-point RANSAC's inlier threshold in pixels at width 256, scaled to the flow's width."""
RANSAC_POINTS = 256
"""Flow vectors the RANSAC reads (a fixed random subset of the level-2 flow's)."""
MIN_INLIERS = 16

DIS_SETTINGS = ("medium", 0, 25)
"""DIS preset, finest scale and gradient-descent iterations: Base-FF's defaults (``conf/baseline``)."""


CHOICES = {"flow1_prior": PRIORS, "dm1_prior": MOTION_PRIORS, "flow2_prior": PREVIOUS_FLOW_PRIORS,
           "dm2_prior": PREVIOUS_MOTION_PRIORS}
"""The choices of each prior option of the chain."""


def check_prior(prior: str | None, option: str = "flow1_prior") -> str | None:
    """``prior`` if it is one of ``option``'s choices (:data:`CHOICES`); else a ValueError."""
    if prior not in CHOICES[option]:
        raise ValueError(f"{option}: expected one of {CHOICES[option]}, got {prior!r}")
    return prior


def _pixel_flow(pair: np.ndarray) -> np.ndarray:
    """(6, H, W) float image pair in [-0.5, 0.5] -> (2, H, W) DIS flow in pixels."""
    image1, image2 = torch.from_numpy(pair[:3]), torch.from_numpy(pair[3:])
    return dense_flow(to_gray_u8(image1), to_gray_u8(image2), *DIS_SETTINGS).transpose(2, 0, 1)


def dis_prior(pair: torch.Tensor, level: int = 2) -> torch.Tensor:
    """The DIS flow of each pair of ``pair`` (B, 6, H, W) = [image 1, image 2], normalised (x by the
    width, y by the height) and averaged over ``2**level`` x ``2**level`` blocks: (B, 2, H/2**level,
    W/2**level), float32 on ``pair``'s device. No gradient flows through it. The pairs run on as many
    threads as torch uses (OpenCV releases the GIL)."""
    height, width = pair.shape[2:]
    images = pair.detach().float().cpu().numpy()
    with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
        flows = list(pool.map(_pixel_flow, images))
    flow = torch.from_numpy(np.stack(flows)).to(pair.device)
    flow = flow / torch.tensor([width, height], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    return F.avg_pool2d(flow, 2**level) if level else flow


def _five_point(args: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(2, h, w) normalised flow and (4,) normalised intrinsics -> motion [r, t] (6,), unit t; zeros
    (no rotation, no translation) where the flow gives no essential matrix."""
    flow, intrinsics = args
    _, h, w = flow.shape
    ys, xs = np.nonzero(np.isfinite(flow).all(0))
    if len(xs) > RANSAC_POINTS:
        pick = np.random.default_rng(0).choice(len(xs), RANSAC_POINTS, replace=False)
        ys, xs = ys[pick], xs[pick]
    if len(xs) < MIN_INLIERS:
        return np.zeros(6)
    x1 = np.stack([xs, ys], 1).astype(np.float64)
    x2 = x1 + np.stack([flow[0, ys, xs] * w, flow[1, ys, xs] * h], 1)
    K = pixel_intrinsics(intrinsics, h, w)
    try:
        E, mask = cv2.findEssentialMat(x1, x2, K, method=cv2.USAC_FAST, prob=0.999,
                                       threshold=scaled_threshold(RANSAC_THRESHOLD_PX, w))
        if E is None or E.shape != (3, 3) or mask is None or mask.sum() < MIN_INLIERS:
            return np.zeros(6)
        return pose_from_essential(E, x1, x2, K, mask[:, 0].astype(bool))
    except (cv2.error, BaselineFailure):
        return np.zeros(6)


def ransac_motion(flow: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """The camera motion of each sample by 5-point RANSAC on its flow: ``flow`` (B, 2, h, w)
    normalised, ``intrinsics`` (B, 4) normalised -> (B, 6) [r, t] float32 on ``flow``'s device, t of
    unit length, zeros for a sample without a solution. No gradient flows through it."""
    flows = flow.detach().double().cpu().numpy()
    cams = intrinsics.detach().double().cpu().numpy()
    with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
        motions = list(pool.map(_five_point, zip(flows, cams, strict=True)))
    return torch.from_numpy(np.stack(motions)).float().to(flow.device)
