"""DeMoN's flow encoder-decoder, bootstrap and iterative (``flow_block`` in DeMoN's
`python/depthmotionnet/v2/blocks.py`, ``flow_block_demon_original`` in
`python/depthmotionnet/blocks_original.py`; docs/reference.md §1.1)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from demon_lab.core.warping import warp_image
from demon_lab.nets.blocks import (
    Conv,
    ConvPair,
    Head,
    UpConv,
    add_encoder_levels,
    check_correlation,
    check_variant,
    correlation,
    initialise,
    lrelu,
    scaled,
)
from demon_lab.nets.prior import DIS_UPSAMPLE, check_prior, dis_prior


class Dense5(nn.Module):
    """v2's global layer: an fc over the first 96 channels of conv5_1, reshaped and appended."""

    def __init__(self, channels: int, level5: tuple[int, int]):
        super().__init__()
        self.channels, self.level5 = channels, level5
        units = channels * level5[0] * level5[1]
        self.fc = nn.Linear(units, units)
        initialise(self.fc)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        head = x[:, : self.channels].flatten(1)  # C, H, W order
        y = lrelu(self.fc(head)).view(x.shape[0], self.channels, *self.level5)
        return torch.cat([x, y], 1)


class FlowNet(nn.Module):
    """Predicts optical flow and its confidence at 1/32 (level 5) and 1/4 (level 2) of the input.

    Args:
        iterative: the iterative net's encoder (conv2 with 32 channels plus 9 extra inputs at
            level 2: warped image 2, flow from the previous depth+motion, previous depth and
            normals); otherwise the bootstrap net.
        variant: 'v1' (Caffe port) or 'v2' (released training code).
        width: multiplier of every channel count.
        size: (H, W) of the input; v2's dense layer depends on it.
        correlation: ``(max_displacement, stride)`` of a correlation front (FlowNetC's design,
            Dosovitskiy et al. 2015; not DeMoN's): conv1 and conv2 run on each image separately
            with shared weights, and the encoder from ``conv2_1`` on reads the correlation of the two
            feature maps at level 2 over displacements ``-max_displacement .. max_displacement``
            in steps of ``stride`` (level-2 pixels), next to a 1x1 projection of image 1's features.
            None: DeMoN's net, both images stacked at the input.
        prior: ``"dis"`` or ``"dis_x2"``: a classical prior flow of the pair (:mod:`demon_lab.nets.prior`; not
            DeMoN's design) enters at level 2 as the iterative net's prior does (5 extra inputs:
            image 2 warped with the prior, the prior), and the net predicts a correction: the
            prior is added to its flow at levels 5 and 2. Bootstrap net only. None: no prior.

    ``forward(pair, extra=None)`` with ``pair`` (B, 6, H, W) = [image 1, image 2] returns
    ``(flowconf5, flowconf2)``: (B, 4, H/32, W/32) and (B, 4, H/4, W/4), channels
    [flow x, flow y, confidence x, confidence y], flow normalised.
    """

    def __init__(self, iterative: bool = False, variant: str = "v1", width: float = 1.0,
                 size: tuple[int, int] = (192, 256), correlation: tuple[int, int] | None = None,
                 prior: str | None = None):
        super().__init__()
        check_variant(variant)
        if check_prior(prior) and iterative:
            raise ValueError("prior: the iterative flow net has its prior from the previous depth and motion")
        self.iterative, self.variant, self.prior = iterative, variant, prior
        self.correlation = None if correlation is None else check_correlation(correlation)
        c = lambda n: scaled(n, width)  # noqa: E731
        v1 = variant == "v1"
        self.conv1 = ConvPair(3 if self.correlation else 6, c(32) if v1 else (c(24), c(32)), 9, 2, variant)
        c2 = c(32) if iterative else (c(64) if v1 else (c(48), c(64)))
        self.conv2 = ConvPair(c(32), c2, 7, 2, variant)
        level2 = self.conv2.out_channels
        if self.correlation:
            max_displacement, stride = self.correlation
            self.project2 = Conv(level2, c(32), (1, 1), (1, 1), variant)
            level2 = c(32) + (2 * (max_displacement // stride) + 1) ** 2
        if iterative:
            self.conv2_extra = ConvPair(9, c(32), 3, 1, variant)
            level2 += c(32)
        if prior:
            self.conv2_prior = ConvPair(5, c(32), 3, 1, variant)
            level2 += c(32)
        c5 = add_encoder_levels(self, width, variant, conv5_kernel=5, conv2_1_in=level2)
        if not v1:
            self.dense5 = Dense5(c(96), (size[0] // 32, size[1] // 32))
            c5 += c(96)
        self.predict_flow5 = Head(c5, 4, variant, hidden=c(24))
        self.upsample_flow5to4 = UpConv(4, 2, relu=False)
        self.refine4 = UpConv(c5, c(256))
        self.refine3 = UpConv(c(256) + c(256) + 2, c(128))
        self.refine2 = UpConv(c(128) + c(128), c(64))
        self.predict_flow2 = Head(c(64) + c(64), 4, variant, hidden=c(24))

    def prior_flow(self, pair: torch.Tensor) -> torch.Tensor:
        """The net's classical prior flow of ``pair`` at level 2 (:func:`demon_lab.nets.prior.dis_prior`)."""
        with torch.no_grad():
            return dis_prior(pair, level=2, upsample=DIS_UPSAMPLE[self.prior])

    def forward(self, pair: torch.Tensor, extra: torch.Tensor | None = None,
                prior2: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(flowconf5, flowconf2)``. ``prior2``: the prior flow at level 2 where the caller has
        it (:meth:`prior_flow`); None computes it."""
        if self.correlation:
            features1 = self.conv2(self.conv1(pair[:, :3]))
            features2 = self.conv2(self.conv1(pair[:, 3:]))
            x = torch.cat([self.project2(features1),
                           lrelu(correlation(features1, features2, *self.correlation))], 1)
        else:
            x = self.conv2(self.conv1(pair))
        if self.iterative:
            if extra is None:
                raise ValueError("extra: the iterative flow net needs its 9 extra input channels")
            x = torch.cat([x, self.conv2_extra(extra)], 1)
        if self.prior:
            with torch.no_grad():
                prior2 = (self.prior_flow(pair) if prior2 is None else prior2).float()
                warped = warp_image(F.avg_pool2d(pair[:, 3:].float(), 4), prior2)
            x = torch.cat([x, self.conv2_prior(torch.cat([warped, prior2], 1).to(x.dtype))], 1)
        conv2_1 = self.conv2_1(x)
        conv3_1 = self.conv3_1(self.conv3(conv2_1))
        conv4_1 = self.conv4_1(self.conv4(conv3_1))
        conv5_1 = self.conv5_1(self.conv5(conv4_1))
        if self.variant == "v2":
            conv5_1 = self.dense5(conv5_1)
        flowconf5 = self.predict_flow5(conv5_1)
        r4 = torch.cat([self.refine4(conv5_1), conv4_1, self.upsample_flow5to4(flowconf5)], 1)
        r3 = torch.cat([self.refine3(r4), conv3_1], 1)
        r2 = torch.cat([self.refine2(r3), conv2_1], 1)
        flowconf5, flowconf2 = flowconf5.float(), self.predict_flow2(r2).float()  # float32, also under autocast
        if self.prior:
            prior5 = F.avg_pool2d(prior2, 8)
            flowconf5 = torch.cat([flowconf5[:, :2] + prior5, flowconf5[:, 2:]], 1)
            flowconf2 = torch.cat([flowconf2[:, :2] + prior2, flowconf2[:, 2:]], 1)
        return flowconf5, flowconf2
