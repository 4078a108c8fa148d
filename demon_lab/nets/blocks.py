"""Building blocks of DeMoN's encoder-decoders (docs/reference.md §1.0; in DeMoN's released code
``convrelu2`` of `python/depthmotionnet/v2/helpers.py` and ``_refine`` of `python/depthmotionnet/v2/blocks.py`,
v1: ``convrelu2_caffe_padding`` of `python/depthmotionnet/helpers.py` and ``_refine_caffe_padding`` of
`python/depthmotionnet/blocks_original.py`).

Two variants: ``v1`` is the original Caffe network (symmetric ``k // 2`` padding), ``v2`` the
released training code's (TF 'same' padding: for a stride-2 layer on an even size the extra pad
goes at the end). Leaky ReLU with slope 0.1 follows every layer except predictions.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

VARIANTS = ("v1", "v2")


def scaled(channels: int, width: float) -> int:
    """A channel count under the width multiplier (at least 1)."""
    return max(1, round(channels * width))


def lrelu(x: torch.Tensor) -> torch.Tensor:
    return F.leaky_relu(x, 0.1)


def initialise(layer: nn.Module) -> None:
    """The flow and depth-motion nets' initialisation of a convolution, transposed convolution or
    (v2's ``Dense5``) fully connected layer: He-normal weights (TF's variance scaling), zero biases.
    Other modules are left as they are, so ``net.apply(initialise)`` draws a new start for a net."""
    if isinstance(layer, nn.Conv2d | nn.ConvTranspose2d | nn.Linear):
        nn.init.kaiming_normal_(layer.weight, a=0.0, nonlinearity="relu")
        nn.init.zeros_(layer.bias)


def _same_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """TF 'same' padding (before, after) along one axis."""
    out = -(-size // stride)
    total = max((out - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


class Conv(nn.Module):
    """A k_h x k_w convolution with DeMoN's padding, optionally followed by leaky ReLU."""

    def __init__(self, c_in: int, c_out: int, kernel: tuple[int, int], stride: tuple[int, int],
                 variant: str, relu: bool = True):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, kernel, stride)
        self.kernel, self.stride, self.variant, self.relu = kernel, stride, variant, relu
        initialise(self.conv)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        (kh, kw), (sh, sw) = self.kernel, self.stride
        if self.variant == "v1":
            pad = (kw // 2, kw // 2, kh // 2, kh // 2)
        else:
            top, bottom = _same_padding(x.shape[2], kh, sh)
            left, right = _same_padding(x.shape[3], kw, sw)
            pad = (left, right, top, bottom)
        y = self.conv(F.pad(x, pad))
        return lrelu(y) if self.relu else y


class ConvPair(nn.Module):
    """DeMoN's ``convrelu2``: a k x 1 conv (stride (s, 1)) then a 1 x k conv (stride (1, s))."""

    def __init__(self, c_in: int, c_out: int | tuple[int, int], kernel: int, stride: int, variant: str):
        super().__init__()
        c_y, c_x = (c_out, c_out) if isinstance(c_out, int) else c_out
        self.y = Conv(c_in, c_y, (kernel, 1), (stride, 1), variant)
        self.x = Conv(c_y, c_x, (1, kernel), (1, stride), variant)
        self.out_channels = c_x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.x(self.y(x))


class UpConv(nn.Module):
    """4x4 transposed convolution, stride 2: exactly twice the input size (a Caffe deconvolution
    with pad 1)."""

    def __init__(self, c_in: int, c_out: int, relu: bool = True):
        super().__init__()
        self.deconv = nn.ConvTranspose2d(c_in, c_out, 4, 2, 1)
        self.relu = relu
        initialise(self.deconv)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.deconv(x)
        return lrelu(y) if self.relu else y


class Head(nn.Module):
    """Prediction head: conv 3x3 -> ``hidden`` (leaky ReLU), conv 3x3 -> ``c_out`` (linear)."""

    def __init__(self, c_in: int, c_out: int, variant: str, hidden: int = 24):
        super().__init__()
        self.hidden = Conv(c_in, hidden, (3, 3), (1, 1), variant)
        self.out = Conv(hidden, c_out, (3, 3), (1, 1), variant, relu=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.hidden(x))


def add_encoder_levels(net: nn.Module, width: float, variant: str, conv5_kernel: int,
                       conv2_1_in: int | None = None) -> int:
    """Add the encoder layers shared by the flow and depth-motion nets, conv2_1 .. conv5_1
    (the layer tables of docs/reference.md §1.1 and §1.2; only conv5's kernel differs).
    ``conv2_1_in``: conv2_1's input channels (default DeMoN's ``c(64)``). Returns conv5_1's channel count."""
    c = lambda n: scaled(n, width)  # noqa: E731
    v1 = variant == "v1"
    net.conv2_1 = ConvPair(c(64) if conv2_1_in is None else conv2_1_in, c(64), 3, 1, variant)
    net.conv3 = ConvPair(c(64), c(128) if v1 else (c(96), c(128)), 5, 2, variant)
    net.conv3_1 = ConvPair(c(128), c(128), 3, 1, variant)
    net.conv4 = ConvPair(c(128), c(256) if v1 else (c(192), c(256)), 5, 2, variant)
    net.conv4_1 = ConvPair(c(256), c(256), 3, 1, variant)
    c5 = c(512) if v1 else c(384)
    net.conv5 = ConvPair(c(256), c5, conv5_kernel, 2, variant)
    net.conv5_1 = ConvPair(c5, c5, 3, 1, variant)
    return c5


CORRELATION_VERSION = 2
"""How :func:`correlation` computes, where it changes the rounding of a correlation front's nets (their
keys carry it: :func:`demon_lab.pipeline.identity.model_identity`): 1, the channel means of the D*D shifted
products, concatenated, differentiated by autograd; 2, the same forward pass (bit for bit) as one
operation with its own backward pass (:class:`Correlation`), equal to version 1 within float rounding."""


def correlation(features1: torch.Tensor, features2: torch.Tensor, max_displacement: int,
                stride: int = 1) -> torch.Tensor:
    """FlowNetC's correlation of two (B, C, H, W) feature maps (Dosovitskiy et al. 2015, Eq. 1 with a
    1x1 patch): channel ``k`` of the (B, D*D, H, W) result, ``D = 2 * (max_displacement // stride) + 1``,
    is the channel mean of ``features1[x] * features2[x + d_k]`` for the displacement ``d_k`` (row-major
    over ``dy``, then ``dx``, each from ``-max_displacement`` to ``max_displacement`` in steps of
    ``stride``); zero where ``x + d_k`` leaves the map. One operation (:class:`Correlation`)."""
    return Correlation.apply(features1, features2, max_displacement, stride)


class Correlation(torch.autograd.Function):
    """:func:`correlation` with its own backward pass: the gradients of all displacements accumulate
    in place into one buffer per input, where autograd would keep every displacement's product and
    sum a zero-padded gradient per displacement (the two timed against each other: ``python -m
    demon_lab.bench train``, reports/bench.md)."""

    @staticmethod
    def forward(ctx, features1: torch.Tensor, features2: torch.Tensor, max_displacement: int,
                stride: int) -> torch.Tensor:
        reach = (max_displacement // stride) * stride
        shifts = [(dy, dx) for dy in range(-reach, reach + 1, stride) for dx in range(-reach, reach + 1, stride)]
        padded = F.pad(features2, (reach, reach, reach, reach))
        batch, _, height, width = features1.shape
        out = features1.new_empty(batch, len(shifts), height, width)
        for k, (dy, dx) in enumerate(shifts):
            window = padded[:, :, reach + dy: reach + dy + height, reach + dx: reach + dx + width]
            out[:, k] = (features1 * window).mean(1)
        ctx.save_for_backward(features1, padded)
        ctx.reach, ctx.shifts = reach, shifts
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        features1, padded = ctx.saved_tensors
        reach, (height, width) = ctx.reach, features1.shape[2:]
        grad = grad / features1.shape[1]  # the channel mean's
        grad1, grad_padded = torch.zeros_like(features1), torch.zeros_like(padded)
        for k, (dy, dx) in enumerate(ctx.shifts):
            window = (slice(None), slice(None), slice(reach + dy, reach + dy + height),
                      slice(reach + dx, reach + dx + width))
            grad1.addcmul_(grad[:, k: k + 1], padded[window])
            grad_padded[window].addcmul_(grad[:, k: k + 1], features1)
        return grad1, grad_padded[:, :, reach: reach + height, reach: reach + width], None, None


def check_correlation(spec) -> tuple[int, int]:
    """``(max_displacement, stride)`` of a correlation front: positive integers, the stride at most
    the displacement."""
    values = tuple(spec) if isinstance(spec, list | tuple) else ()
    if (len(values) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in values)
            or values[1] > values[0]):
        raise ValueError(f"correlation: expected [max_displacement, stride], positive integers with the stride "
                         f"at most the displacement, got {spec!r}")
    return values


def check_variant(variant: str) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")


def check_size(height: int, width: int) -> None:
    if height % 32 or width % 32 or height < 32 or width < 32:
        raise ValueError(f"input size: sides must be positive multiples of 32 (the coarsest level is "
                         f"1/32 of the input), got {width}x{height}")
