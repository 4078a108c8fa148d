"""A refinement of the bootstrap flow on warped features (``model.flow_refine``; not DeMoN's design).

The bootstrap flow net reads its flow from an encoder-decoder whose correlation front, at the cpu
scale, moves in steps of 2 level-2 pixels, and whose level-2 flow is about as wide an error as the
parallax it should carry (docs/notes/2026-12-learned-motion.md, the ceiling table). :class:`FlowRefine`
sharpens it as PWC-Net and RAFT do (Sun et al., CVPR 2018; Teed & Deng, ECCV 2020), coarse to fine:
both images through one small encoder, its features at level 1 and level 2 scaled to unit length;
then ``iterations`` updates at level 2 and :data:`FINE_UPDATES` at level 1, each with image 2's
features warped by the current flow, their cosine similarity to image 1's at stride 1 within a window
(:data:`RADIUS`, :data:`FINE_RADIUS`), a softmax over the window (a learned temperature), the
displacement it expects (a soft argmax, as GMFlow reads its matches: Xu et al., CVPR 2022), and a
small convolutional correction of it, starting at none. Each update starts from the previous flow
without its gradient (as RAFT's). The match probabilities are returned beside the flows, so that a
loss can train the features to match directly (:func:`demon_lab.core.losses.match_loss`: trained by
the endpoint error alone, a refinement that regressed its correction hardly moved the flow,
docs/notes/2026-12-learned-motion.md).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from demon_lab.core.warping import warp_image
from demon_lab.nets.blocks import Conv, correlation, scaled

RADIUS = 4
"""The level-2 window's reach in level-2 pixels (9 x 9 displacements at stride 1; 16 input pixels)."""
FINE_RADIUS = 3
"""The level-1 window's reach in level-1 pixels (7 x 7 displacements; 6 input pixels)."""
FINE_UPDATES = 2
"""Updates at level 1 after the level-2 ones; their flow is averaged back to level 2 (what dm1 reads)."""
TEMPERATURE = 20.0
"""The softmax's starting scale of the cosine similarities (learned)."""


class Match(NamedTuple):
    """One update's match: ``log_probs`` (B, D*D, h, w), the log-probability of each displacement of
    the window (row-major over dy, then dx, from -r to r), ``start`` (B, 2, h, w) the normalised flow the
    window is centred on (no gradient), ``level`` (1 or 2) the level of both."""

    log_probs: torch.Tensor
    start: torch.Tensor
    level: int


class Refinement(NamedTuple):
    """:class:`FlowRefine`'s output: ``flows``, the level-2 flow (B, 2, H/4, W/4), normalised, after each
    update (the last is the refinement's flow); ``matches``, each update's :class:`Match`;
    ``confidence`` (B, 1, H/4, W/4) in (0, 1), each vector's probability of being precise, where the
    refinement has a confidence head (else None)."""

    flows: list[torch.Tensor]
    matches: list[Match]
    confidence: torch.Tensor | None = None


def displacements(radius: int, like: torch.Tensor) -> torch.Tensor:
    """The window's displacements (1, 2, D*D, 1, 1), x then y, in the order of :func:`correlation`'s channels."""
    d = torch.arange(-radius, radius + 1, device=like.device, dtype=torch.float32)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    return torch.stack([dx.reshape(-1), dy.reshape(-1)]).view(1, 2, -1, 1, 1)


class Update(nn.Module):
    """One level's update: match in the window around the current flow, its expected displacement, a
    correction of it (zero at the start)."""

    def __init__(self, radius: int, hidden: tuple[int, int], variant: str, level: int):
        super().__init__()
        self.radius, self.level = radius, level
        window = (2 * radius + 1) ** 2
        self.log_temperature = nn.Parameter(torch.tensor(math.log(TEMPERATURE)))
        self.convs = nn.Sequential(Conv(window + 2, hidden[0], (3, 3), (1, 1), variant),
                                   Conv(hidden[0], hidden[1], (3, 3), (1, 1), variant))
        self.delta = Conv(hidden[1], 2, (3, 3), (1, 1), variant, relu=False)
        with torch.no_grad():
            self.delta.conv.weight.zero_()
            self.delta.conv.bias.zero_()

    def forward(self, features1: torch.Tensor, features2: torch.Tensor, flow: torch.Tensor
                ) -> tuple[torch.Tensor, Match, torch.Tensor]:
        """The flow after the update, its match, and the hidden features the correction is read from."""
        flow = flow.detach().float()
        height, width = flow.shape[2:]
        pixels = flow.new_tensor([width, height]).view(1, 2, 1, 1)
        warped = warp_image(features2, flow.to(features2.dtype))
        cosine = correlation(features1, warped, self.radius, 1).float() * features1.shape[1]
        log_probs = torch.log_softmax(cosine * self.log_temperature.exp(), 1)
        probs = log_probs.exp()
        expected = (probs.unsqueeze(1) * displacements(self.radius, probs)).sum(2)
        x = self.convs(torch.cat([probs, expected], 1).to(features1.dtype))
        step = expected + self.delta(x).float()
        return flow + step / pixels, Match(log_probs, flow, self.level), x


class FlowRefine(nn.Module):
    """``forward(pair, flow)``: ``pair`` (B, 6, H, W) = [image 1, image 2], ``flow`` (B, 2, H/4, W/4)
    normalised -> :class:`Refinement` (the level-2 flow after each of the ``iterations`` + :data:`FINE_UPDATES`
    updates, float32, and each update's match).

    Args:
        variant, width: as :class:`demon_lab.nets.flow_net.FlowNet`.
        iterations: updates at level 2 (their weights shared).
        radius: the level-2 window's reach, level-2 pixels.
        confidence: a head that reads, from the last level-1 update's hidden features (the shape of its
            match), each vector's probability of being precise, averaged back to level 2 (starting at 0.5
            everywhere; trained by ``loss.fit_weight``, the motion fit's weights under
            ``model.fit_weights=confidence``).
    """

    def __init__(self, variant: str = "v1", width: float = 1.0, iterations: int = 3, radius: int = RADIUS,
                 confidence: bool = False):
        super().__init__()
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"flow_refine: expected null or a number of updates >= 1, got {iterations!r}")
        c = lambda n: scaled(n, width)  # noqa: E731
        self.iterations = iterations
        self.level1 = nn.Sequential(Conv(3, c(32), (7, 7), (2, 2), variant),
                                    Conv(c(32), c(32), (3, 3), (1, 1), variant))
        self.level2 = nn.Sequential(Conv(c(32), c(64), (5, 5), (2, 2), variant),
                                    Conv(c(64), c(64), (3, 3), (1, 1), variant),
                                    Conv(c(64), c(64), (3, 3), (1, 1), variant, relu=False))
        self.fine = Conv(c(32), c(32), (3, 3), (1, 1), variant, relu=False)
        self.update = Update(radius, (c(96), c(64)), variant, level=2)
        self.fine_update = Update(FINE_RADIUS, (c(64), c(32)), variant, level=1)
        self.confidence = None
        if confidence:
            self.confidence = nn.Sequential(Conv(c(32), c(32), (3, 3), (1, 1), variant),
                                            Conv(c(32), 1, (3, 3), (1, 1), variant, relu=False))
            with torch.no_grad():
                self.confidence[1].conv.weight.zero_()
                self.confidence[1].conv.bias.zero_()

    def features(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """An image's unit-length features at level 1 and level 2."""
        level1 = self.level1(image)
        return F.normalize(self.fine(level1), dim=1), F.normalize(self.level2(level1), dim=1)

    def forward(self, pair: torch.Tensor, flow: torch.Tensor) -> Refinement:
        (fine1, coarse1), (fine2, coarse2) = self.features(pair[:, :3]), self.features(pair[:, 3:])
        flows, matches = [], []
        for _ in range(self.iterations):
            flow, match, _ = self.update(coarse1, coarse2, flow)
            flows.append(flow)
            matches.append(match)
        fine = F.interpolate(flow, scale_factor=2, mode="bilinear", align_corners=False)
        for _ in range(FINE_UPDATES):
            fine, match, hidden = self.fine_update(fine1, fine2, fine)
            flows.append(F.avg_pool2d(fine, 2))
            matches.append(match)
        if self.confidence is None:
            return Refinement(flows, matches)
        return Refinement(flows, matches, F.avg_pool2d(torch.sigmoid(self.confidence(hidden).float()), 2))
