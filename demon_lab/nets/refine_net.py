"""DeMoN's depth refinement encoder-decoder (``depth_refine_block`` in
DeMoN's `python/depthmotionnet/v2/blocks.py`, ``depth_refine_block_demon_original`` in
`python/depthmotionnet/blocks_original.py`; docs/reference.md §1.3)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from demon_lab.nets.blocks import Conv, Head, UpConv, check_variant, scaled


class RefineNet(nn.Module):
    """Upsamples the level-2 depth to the input resolution, guided by image 1.

    Input: image 1 (B, 3, H, W) and the inverse depth at (H/4, W/4), upsampled 4x by nearest
    neighbour. Output: (B, 1, H, W) inverse depth (v1) or (B, 4, H, W) depth + normals (v2).
    """

    def __init__(self, variant: str = "v1", width: float = 1.0):
        super().__init__()
        check_variant(variant)
        c = lambda n: scaled(n, width)  # noqa: E731
        conv = lambda a, b, s: Conv(a, b, (3, 3), (s, s), variant)  # noqa: E731
        self.conv0 = conv(4, c(32), 1)
        self.conv1 = conv(c(32), c(64), 2)
        self.conv1_1 = conv(c(64), c(64), 1)
        self.conv2 = conv(c(64), c(128), 2)
        self.conv2_1 = conv(c(128), c(128), 1)
        self.refine1 = UpConv(c(128), c(64))
        self.refine0 = UpConv(c(64) + c(64), c(32))
        self.predict_depth0 = Head(c(32) + c(32), 1 if variant == "v1" else 4, variant, hidden=c(16))

    def forward(self, image1: torch.Tensor, inv_depth2: torch.Tensor) -> torch.Tensor:
        depth = F.interpolate(inv_depth2, scale_factor=4, mode="nearest")
        conv0 = self.conv0(torch.cat([image1, depth], 1))
        conv1_1 = self.conv1_1(self.conv1(conv0))
        conv2_1 = self.conv2_1(self.conv2(conv1_1))
        r1 = torch.cat([self.refine1(conv2_1), conv1_1], 1)
        r0 = torch.cat([self.refine0(r1), conv0], 1)
        return self.predict_depth0(r0).float()  # float32 out, also under autocast
