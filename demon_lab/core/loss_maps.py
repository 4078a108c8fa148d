"""The maps DeMoN's losses compare, built from a prediction or its ground truth: scale-invariant
gradients at several spacings, and the inverse-depth pyramid of 2x2 medians.

The conventions of :mod:`demon_lab.core.geometry` hold (``inv_depth`` ``(B, 1, H, W)``, NaN or 0
marking invalid pixels).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from demon_lab.core.execution import float32
from demon_lab.core.geometry import check_map, valid_depth

Tensor = torch.Tensor


@float32
def scale_invariant_gradients(
    x: Tensor, spacings: Sequence[int] = (1, 2, 4, 8, 16), eps: float = 1e-3
) -> Tensor:
    """DeMoN's scale-invariant gradients of every channel at several spacings
    (lmbspecialops' ``scale_invariant_gradient``; docs/reference.md §3).

    ``g_x^h(i, j) = (f(i, j+h) - f(i, j)) / (|f(i, j+h)| + |f(i, j)| + eps)`` and likewise
    ``g_y^h`` along rows; a term whose neighbour is outside the image is 0. NaN propagates.
    DeMoN uses ``eps = 1e-3`` for ground truth and predicted flow, ``1e-2`` for predicted depth.

    Args:
        x: (B, C, H, W) any map (inverse depth, flow, confidence).
        spacings: the spacings h.

    Returns:
        (B, C, 2 * len(spacings), H, W) with order [gx^h1, gy^h1, gx^h2, gy^h2, ...].
    """
    if not isinstance(x, torch.Tensor) or x.dim() != 4:
        raise ValueError(f"x: expected shape (B, C, H, W), got {tuple(getattr(x, 'shape', ()))}")
    height, width = x.shape[2:]
    terms = []
    for h in spacings:
        if h < 1:
            raise ValueError(f"spacings: expected positive integers, got {h}")
        gx = torch.zeros_like(x)
        gy = torch.zeros_like(x)
        if h < width:
            a, b = x[..., :, h:], x[..., :, :-h]
            gx[..., :, :-h] = (a - b) / (a.abs() + b.abs() + eps)
        if h < height:
            a, b = x[..., h:, :], x[..., :-h, :]
            gy[..., :-h, :] = (a - b) / (a.abs() + b.abs() + eps)
        terms += [gx, gy]
    return torch.stack(terms, dim=2)


@float32
def median_downsample(x: Tensor) -> Tensor:
    """Halve the resolution with 3x3 medians (DeMoN's ``median3x3_downsample``).

    Output size ``ceil(H/2) x ceil(W/2)``; ``out(i, j)`` is the median of the 3x3 neighbourhood
    centred at input ``(2i, 2j)``, borders clamped. NaN follows DeMoN's kernel, a partial
    selection sort with ``>`` comparisons over the window read row by row, in which NaNs never
    move: the output is NaN iff the centre is NaN; otherwise it is the m-th smallest of the
    window's non-NaN values, m = the number of non-NaN values among the first four (top row and
    left neighbour). Without NaNs this is the plain median.

    Args:
        x: (B, C, H, W), floating point.

    Returns:
        (B, C, ceil(H/2), ceil(W/2)).
    """
    if not isinstance(x, torch.Tensor) or x.dim() != 4:
        raise ValueError(f"x: expected shape (B, C, H, W), got {tuple(getattr(x, 'shape', ()))}")
    h, w = (x.shape[2] + 1) // 2, (x.shape[3] + 1) // 2
    padded = F.pad(x, (1, 1, 1, 1), mode="replicate")
    window = [padded[:, :, dy:dy + 2 * h:2, dx:dx + 2 * w:2] for dy in range(3) for dx in range(3)]
    nan = [torch.isnan(v) for v in window]
    rank = sum((~n).to(torch.uint8) for n in nan[:4])
    # NaN as +inf sorts last, as torch.sort puts NaN; with the centre valid the window has at least
    # rank + 1 valid values, so the rank-th smallest is a valid one (the same even with real infs).
    v = [torch.where(n, torch.inf, t) for n, t in zip(nan, window)]
    for i, j in MEDIAN9_NETWORK:
        v[i], v[j] = torch.minimum(v[i], v[j]), torch.maximum(v[i], v[j])
    median = v[4]
    for k in range(4):
        median = torch.where(rank == k, v[k], median)
    return torch.where(nan[4], window[4], median)


MEDIAN9_NETWORK = ((0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (0, 3), (3, 6), (0, 3),
                   (1, 4), (4, 7), (1, 4), (2, 5), (5, 8), (2, 5), (1, 3), (5, 7), (2, 6), (4, 6), (2, 4), (2, 3),
                   (5, 6))
"""A 25-comparator sorting network for 9 values (it sorts all 512 inputs of 0s and 1s, hence every
input: tests/test_geometry.py): the 3x3 windows sorted by 50 element-wise min/max ops rather than by
``Tensor.sort`` over a window dimension, the slower of the two on the cpu scale's batches (the speed-up:
docs/notes/2026-11-cpu-profile.md, "Time and memory")."""


@float32
def inverse_depth_pyramid(inv_depth: Tensor, levels: int = 5) -> list[Tensor]:
    """Ground-truth pyramid by recursive median downsampling (DeMoN's
    ``recursive_median_downsample`` in `python/depthmotionnet/v2/helpers.py`; docs/reference.md §3-§4).

    Invalid pixels (0, negative, inf) are first turned into NaN so they do not enter the medians.

    Args:
        inv_depth: (B, 1, H, W) inverse depth at level 0.
        levels: number of halvings.

    Returns:
        ``[level 0, level 1, ..., level levels]``; at 256x192 level 2 is 64x48, level 5 is 8x6.
    """
    check_map("inv_depth", inv_depth, 1)
    level = torch.where(valid_depth(inv_depth), inv_depth, torch.full_like(inv_depth, math.nan))
    pyramid = [level]
    for _ in range(levels):
        level = median_downsample(level)
        pyramid.append(level)
    return pyramid
