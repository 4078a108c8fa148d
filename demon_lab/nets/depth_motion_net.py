"""DeMoN's depth and motion encoder-decoder (``depthmotion_block`` in
DeMoN's `python/depthmotionnet/v2/blocks.py`, ``depthmotion_block_demon_original`` in
`python/depthmotionnet/blocks_original.py`; docs/reference.md §1.2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from demon_lab.nets.blocks import Conv, ConvPair, Head, UpConv, add_encoder_levels, check_variant, lrelu, scaled
from demon_lab.nets.flow_net import Dense5


@dataclass
class DepthMotion:
    inv_depth: torch.Tensor  # (B, 1, H/4, W/4) = scale * raw depth
    normals: torch.Tensor  # (B, 3, H/4, W/4), raw (not re-normalised)
    motion: torch.Tensor  # (B, 6) [r, t]
    scale: torch.Tensor  # (B, 1)
    weights: torch.Tensor | None = None  # (B, 1, H/4, W/4) in (0, 1): the motion fit's (fit=True), else None


def _linear(c_in: int, c_out: int) -> nn.Linear:
    fc = nn.Linear(c_in, c_out)
    nn.init.xavier_uniform_(fc.weight)  # TF's default for dense layers (Glorot uniform)
    nn.init.zeros_(fc.bias)
    return fc


class DepthMotionNet(nn.Module):
    """Predicts inverse depth and normals at 1/4 of the input and the camera motion.

    Args:
        iterative: 8 extra input channels at level 2 (warped image 2, flow + confidence, depth from
            the flow and the previous motion) instead of the bootstrap net's 7.
        variant, width, size: as :class:`demon_lab.nets.flow_net.FlowNet`.
        fit: the depth head predicts a fifth channel, each pixel's weight in the motion fit
            (``model.motion_fit``, :func:`demon_lab.core.epipolar.fit_motion`): a sigmoid, starting at
            0.5 everywhere (its layer's weights at zero). Not DeMoN's design.

    ``forward(pair, extra)`` returns a :class:`DepthMotion`. The motion head predicts 7 values
    [r (3), t (3), s (1)]; the depth is ``s * raw`` (s unconstrained, per sample).
    """

    def __init__(self, iterative: bool = False, variant: str = "v1", width: float = 1.0,
                 size: tuple[int, int] = (192, 256), fit: bool = False):
        super().__init__()
        check_variant(variant)
        self.iterative, self.variant, self.fit = iterative, variant, fit
        c = lambda n: scaled(n, width)  # noqa: E731
        v1 = variant == "v1"
        level5 = (size[0] // 32, size[1] // 32)
        self.conv1 = ConvPair(6, c(32) if v1 else (c(24), c(32)), 9, 2, variant)
        self.conv2 = ConvPair(c(32), c(32), 7, 2, variant)
        self.conv2_extra = ConvPair(8 if iterative else 7, c(32), 3, 1, variant)
        c5 = add_encoder_levels(self, width, variant, conv5_kernel=3)
        if v1:
            self.motion_conv1 = Conv(c5, c(128), (3, 3), (1, 1), variant)
        else:
            self.dense5 = Dense5(c(96), level5)
            self.motion_conv3 = ConvPair(c(64), c(64), 5, 2, variant)
            self.motion_conv4 = ConvPair(c(64), c(64), 5, 2, variant)
            self.motion_conv5a = ConvPair(c(64), c(64), 3, 2, variant)
            self.motion_conv5b = Conv(c5 + c(96), c(64), (3, 3), (1, 1), variant)
        motion_channels = c(128) if v1 else 2 * c(64)
        self.motion_fc1 = _linear(motion_channels * level5[0] * level5[1], c(1024))
        self.motion_fc2 = _linear(c(1024), c(128))
        self.motion_fc3 = _linear(c(128), 7)
        self.refine4 = UpConv(c5, c(256))
        self.refine3 = UpConv(c(256) + c(256), c(128))
        self.refine2 = UpConv(c(128) + c(128), c(64))
        self.predict_depth2 = Head(c(64) + c(64), 5 if fit else 4, variant, hidden=c(24))
        if fit:
            with torch.no_grad():  # every pixel's weight starts at sigmoid(0) = 0.5
                self.predict_depth2.out.conv.weight[4:].zero_()
                self.predict_depth2.out.conv.bias[4:].zero_()

    def forward(self, pair: torch.Tensor, extra: torch.Tensor) -> DepthMotion:
        x = torch.cat([self.conv2(self.conv1(pair)), self.conv2_extra(extra)], 1)
        conv2_1 = self.conv2_1(x)
        conv3_1 = self.conv3_1(self.conv3(conv2_1))
        conv4_1 = self.conv4_1(self.conv4(conv3_1))
        conv5_1 = self.conv5_1(self.conv5(conv4_1))
        if self.variant == "v1":
            m = self.motion_conv1(conv5_1)
        else:
            m5a = self.motion_conv5a(self.motion_conv4(self.motion_conv3(conv2_1)))
            m = torch.cat([m5a, self.motion_conv5b(self.dense5(conv5_1))], 1)
        m = lrelu(self.motion_fc2(lrelu(self.motion_fc1(m.flatten(1)))))
        motion_scale = self.motion_fc3(m).float()  # float32 out, also under autocast
        # The decoder starts from conv5_1 in both variants (not from v2's dense5 output).
        r4 = torch.cat([self.refine4(conv5_1), conv4_1], 1)
        r3 = torch.cat([self.refine3(r4), conv3_1], 1)
        r2 = torch.cat([self.refine2(r3), conv2_1], 1)
        out = self.predict_depth2(r2).float()
        scale = motion_scale[:, 6:7]
        return DepthMotion(inv_depth=out[:, :1] * scale[:, :, None, None], normals=out[:, 1:4],
                           motion=motion_scale[:, :6], scale=scale,
                           weights=torch.sigmoid(out[:, 4:5]) if self.fit else None)
