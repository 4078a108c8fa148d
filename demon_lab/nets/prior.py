"""Classical priors for the bootstrap nets (``model.flow1_prior``, ``model.dm1_prior``; not DeMoN's design).

DeMoN's bootstrap flow net reads the two images alone; its iterative flow net reads a prior flow
(from the previous depth and motion) and image 2 warped with it. ``model.flow1_prior=dis`` gives the
bootstrap net a prior in the same form, from a classical optical flow of the pair: OpenCV's DIS
flow (Kroeger et al. 2016), the flow Base-FF reads (:mod:`demon_lab.baselines.methods`), computed
at the input resolution and averaged down to level 2. The net predicts a correction of it
(docs/notes/2026-11-cpu-profile.md, "Classical priors for the bootstrap nets").

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

PRIORS = (None, "dis", "dis_x2")
"""``model.flow1_prior``: none, OpenCV's DIS flow of the pair, or of the pair upsampled 2x."""
DIS_UPSAMPLE = {"dis": 1, "dis_x2": 2}
"""How much each DIS prior upsamples the pair (bicubic) before the flow is computed: at the ``cpu``
scale's 128x96 DIS finds sub-pixel matches on the 2x images that it misses on the pair itself
(docs/notes/2026-11-cpu-profile.md, "A finer classical prior")."""
MOTION_PRIORS = (None, "ransac", "ransac_prior")
"""``model.dm1_prior``: none, 5-point RANSAC on the flow ``dm1`` reads (``flow1``'s), or on
``flow1``'s classical prior flow (needs ``model.flow1_prior``)."""
PREVIOUS_MOTION_PRIORS = (None, "previous")
"""``model.dm2_prior``: none, or the previous pass's motion."""
PREVIOUS_FLOW_PRIORS = (None, "previous")
"""``model.flow2_prior``: none, or the previous pass's flow."""
RANSAC_THRESHOLD_PX = 2.0
"""The 5-point RANSAC's inlier threshold in pixels at width 256, scaled to the flow's width."""
RANSAC_POINTS = 256
"""Flow vectors the RANSAC reads (a fixed random subset of the level-2 flow's)."""
PRIOR_RANSAC = (1024, 1.0)
"""``ransac_prior``'s points (every level-2 vector up to this many) and inlier threshold (pixels at
width 256): a classical flow is precise where it matches, so a tight threshold keeps its matches."""
RANSAC_SETTINGS = {"ransac": (RANSAC_POINTS, RANSAC_THRESHOLD_PX), "ransac_prior": PRIOR_RANSAC}
"""Each ``model.dm1_prior``'s points and threshold (:func:`ransac_motion`)."""
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


def _pixel_flow(args: tuple[np.ndarray, int]) -> np.ndarray:
    """(6, H, W) float image pair in [-0.5, 0.5] and an upsampling factor -> (2, uH, uW) DIS flow in
    pixels of the upsampled pair."""
    pair, upsample = args
    image1, image2 = to_gray_u8(torch.from_numpy(pair[:3])), to_gray_u8(torch.from_numpy(pair[3:]))
    if upsample > 1:
        image1, image2 = (cv2.resize(im, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
                          for im in (image1, image2))
    return dense_flow(image1, image2, *DIS_SETTINGS).transpose(2, 0, 1)


def dis_prior(pair: torch.Tensor, level: int = 2, upsample: int = 1) -> torch.Tensor:
    """The DIS flow of each pair of ``pair`` (B, 6, H, W) = [image 1, image 2], computed on the pair
    upsampled ``upsample`` times, normalised (x by the width, y by the height) and averaged over the
    blocks of one pixel at ``level``: (B, 2, H/2**level, W/2**level), float32 on ``pair``'s device. No
    gradient flows through it. The pairs run on as many threads as torch uses (OpenCV releases the GIL)."""
    height, width = pair.shape[2:]
    images = pair.detach().float().cpu().numpy()
    with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
        flows = list(pool.map(_pixel_flow, [(image, upsample) for image in images]))
    flow = torch.from_numpy(np.stack(flows)).to(pair.device)
    scale = torch.tensor([width * upsample, height * upsample], dtype=flow.dtype, device=flow.device)
    flow = flow / scale.view(1, 2, 1, 1)
    block = 2**level * upsample
    return F.avg_pool2d(flow, block) if block > 1 else flow


def _five_point(args: tuple[np.ndarray, np.ndarray, int, float]) -> np.ndarray:
    """(2, h, w) normalised flow, (4,) normalised intrinsics, the most points to read and the inlier
    threshold (pixels at width 256) -> motion [r, t] (6,), unit t; zeros (no rotation, no
    translation) where the flow gives no essential matrix."""
    flow, intrinsics, points, threshold = args
    _, h, w = flow.shape
    ys, xs = np.nonzero(np.isfinite(flow).all(0))
    if len(xs) > points:
        pick = np.random.default_rng(0).choice(len(xs), points, replace=False)
        ys, xs = ys[pick], xs[pick]
    if len(xs) < MIN_INLIERS:
        return np.zeros(6)
    x1 = np.stack([xs, ys], 1).astype(np.float64)
    x2 = x1 + np.stack([flow[0, ys, xs] * w, flow[1, ys, xs] * h], 1)
    K = pixel_intrinsics(intrinsics, h, w)
    try:
        E, mask = cv2.findEssentialMat(x1, x2, K, method=cv2.USAC_FAST, prob=0.999,
                                       threshold=scaled_threshold(threshold, w))
        if E is None or E.shape != (3, 3) or mask is None or mask.sum() < MIN_INLIERS:
            return np.zeros(6)
        return pose_from_essential(E, x1, x2, K, mask[:, 0].astype(bool))
    except (cv2.error, BaselineFailure):
        return np.zeros(6)


def ransac_motion(flow: torch.Tensor, intrinsics: torch.Tensor, points: int = RANSAC_POINTS,
                  threshold: float = RANSAC_THRESHOLD_PX) -> torch.Tensor:
    """The camera motion of each sample by 5-point RANSAC on its flow: ``flow`` (B, 2, h, w)
    normalised, ``intrinsics`` (B, 4) normalised -> (B, 6) [r, t] float32 on ``flow``'s device, t of
    unit length, zeros for a sample without a solution; on at most ``points`` flow vectors, with an
    inlier ``threshold`` in pixels at width 256. No gradient flows through it."""
    flows = flow.detach().double().cpu().numpy()
    cams = intrinsics.detach().double().cpu().numpy()
    with ThreadPoolExecutor(max(1, torch.get_num_threads())) as pool:
        motions = list(pool.map(_five_point, [(f, k, points, threshold) for f, k in zip(flows, cams, strict=True)]))
    return torch.from_numpy(np.stack(motions)).float().to(flow.device)
