"""A refinement of the bootstrap flow on warped features (``model.flow_refine``; not DeMoN's design).

The bootstrap flow net reads its flow from an encoder-decoder whose correlation front, at the cpu
scale, moves in steps of 2 level-2 pixels, and whose level-2 flow is about as wide an error as the
parallax it should carry (docs/notes/2026-12-learned-motion.md, the ceiling table). :class:`FlowRefine`
sharpens it as PWC-Net and RAFT do (Sun et al., CVPR 2018; Teed & Deng, ECCV 2020): both images
through one small encoder to level 2; then, ``iterations`` times, image 2's features warped by the
current flow, their correlation with image 1's at stride 1 within ``radius`` level-2 pixels, and a
small convolutional update that adds a correction to the flow, in level-2 pixels. Each update starts
from the previous flow without its gradient (as RAFT's), and the last layer starts at zero, so the
untrained refinement returns the flow it is given.
"""

from __future__ import annotations

import torch
from torch import nn

from demon_lab.core.warping import warp_image
from demon_lab.nets.blocks import Conv, correlation, lrelu, scaled

RADIUS = 4
"""The correlation's reach in level-2 pixels (a 9 x 9 neighbourhood at stride 1)."""


class FlowRefine(nn.Module):
    """``forward(pair, flow)``: ``pair`` (B, 6, H, W) = [image 1, image 2], ``flow`` (B, 2, H/4, W/4)
    normalised -> the refined flows after each update, a list of ``iterations`` (B, 2, H/4, W/4)
    normalised, float32; the last is the refinement's output.

    Args:
        variant, width: as :class:`demon_lab.nets.flow_net.FlowNet`.
        iterations: updates of the flow (their weights shared).
        radius: the correlation's reach, level-2 pixels.
    """

    def __init__(self, variant: str = "v1", width: float = 1.0, iterations: int = 3, radius: int = RADIUS):
        super().__init__()
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"flow_refine: expected null or a number of updates >= 1, got {iterations!r}")
        c = lambda n: scaled(n, width)  # noqa: E731
        self.iterations, self.radius = iterations, radius
        self.encoder = nn.Sequential(Conv(3, c(32), (7, 7), (2, 2), variant),
                                     Conv(c(32), c(64), (5, 5), (2, 2), variant),
                                     Conv(c(64), c(64), (3, 3), (1, 1), variant))
        self.project = Conv(c(64), c(32), (1, 1), (1, 1), variant)
        cost = (2 * radius + 1) ** 2
        self.update = nn.Sequential(Conv(cost + c(32) + 2, c(96), (3, 3), (1, 1), variant),
                                    Conv(c(96), c(64), (3, 3), (1, 1), variant),
                                    Conv(c(64), c(32), (3, 3), (1, 1), variant))
        self.delta = Conv(c(32), 2, (3, 3), (1, 1), variant, relu=False)
        with torch.no_grad():  # the untrained refinement returns the flow it is given
            self.delta.conv.weight.zero_()
            self.delta.conv.bias.zero_()

    def forward(self, pair: torch.Tensor, flow: torch.Tensor) -> list[torch.Tensor]:
        features1, features2 = self.encoder(pair[:, :3]), self.encoder(pair[:, 3:])
        context = self.project(features1)
        height, width = flow.shape[2:]
        pixels = flow.new_tensor([width, height]).view(1, 2, 1, 1)
        flows = []
        for _ in range(self.iterations):
            flow = flow.detach().float()
            warped = warp_image(features2, flow.to(features2.dtype))
            cost = lrelu(correlation(features1, warped, self.radius, 1))
            x = self.update(torch.cat([cost, context, (flow * pixels).to(cost.dtype)], 1))
            flow = flow + self.delta(x).float() / pixels
            flows.append(flow)
        return flows
