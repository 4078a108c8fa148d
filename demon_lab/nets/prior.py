"""A classical prior flow for the bootstrap flow net (``model.flow1_prior``; not DeMoN's design).

DeMoN's bootstrap flow net reads the two images alone; its iterative flow net reads a prior flow
(from the previous depth and motion) and image 2 warped with it. ``model.flow1_prior=dis`` gives the
bootstrap net a prior in the same form, from a classical optical flow of the pair: OpenCV's DIS
flow (Kroeger et al. 2016), the flow Base-FF reads (:mod:`demon_lab.baselines.methods`), computed
at the input resolution and averaged down to level 2. The net predicts a correction of it
(docs/cpu_scale.md, "A classical prior for the bootstrap flow net").
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
import torch.nn.functional as F

from demon_lab.baselines.twoview import dense_flow, to_gray_u8

PRIORS = (None, "dis")

DIS_SETTINGS = ("medium", 0, 25)
"""DIS preset, finest scale and gradient-descent iterations: Base-FF's defaults (``conf/baseline``)."""


def check_prior(prior: str | None) -> str | None:
    if prior not in PRIORS:
        raise ValueError(f"flow1_prior: expected one of {PRIORS}, got {prior!r}")
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
