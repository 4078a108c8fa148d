"""Backward warping of image 2 into view 1 along a flow: DeMoN's ``warp2d`` and the nets' own
variant (:func:`warp_image`). The conventions of :mod:`demon_lab.core.geometry` hold (``flow``
``(B, 2, H, W)`` normalised by its resolution's width and height).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from demon_lab.core.execution import float32
from demon_lab.core.geometry import check_map, normalised_grid

Tensor = torch.Tensor


def _check_warp_inputs(image: Tensor, flow: Tensor) -> tuple[int, int, int, int]:
    """A (B, C, H, W) image and a (B, 2, H, W) flow of its size; returns B, C, H, W."""
    if not isinstance(image, torch.Tensor) or image.dim() != 4:
        raise ValueError(f"image: expected shape (B, C, H, W), "
                         f"got {tuple(getattr(image, 'shape', ()))}")
    check_map("flow", flow, 2)
    batch, channels, height, width = image.shape
    if flow.shape[0] != batch or flow.shape[2:] != image.shape[2:]:
        raise ValueError(f"flow: expected shape ({batch}, 2, {height}, {width}) to match image, "
                         f"got {tuple(flow.shape)}")
    return batch, channels, height, width


@float32
def warp_image(image: Tensor, flow: Tensor) -> Tensor:
    """Backward-warp image 2 into view 1 with bilinear interpolation (DeMoN's ``warp2d``).

    ``out(x, y) = image(x + W fx(x, y), y + H fy(x, y))`` in pixel indices. The output is 0 unless
    all four bilinear neighbours lie inside the image (no blending with the border); NaN flow
    gives 0. Since images live in [-0.5, 0.5], 0 is mid grey.

    One deliberate difference from DeMoN's kernel (:func:`warp2d`, used under
    ``model.compat=demon_original``): it truncates sample positions toward zero, so for
    -1 < p < 0 it extrapolates linearly from pixels 0 and 1; here the neighbours are
    ``floor(p)``, ``floor(p) + 1`` and such samples are outside (0), which is what the
    all-four-neighbours rule means. The two agree everywhere else.

    Args:
        image: (B, C, H, W) image of view 2.
        flow: (B, 2, H, W) normalised flow from view 1 to view 2.

    Returns:
        (B, C, H, W) image 2 seen from view 1. Differentiable in ``image`` and ``flow``.
    """
    _, _, height, width = _check_warp_inputs(image, flow)
    # Pixel index p = x + W flow has its 4 neighbours inside iff 0 <= p <= W - 2 after floor,
    # i.e. -x <= W flow < W - 1 - x (likewise for y); NaN compares False.
    xs = torch.arange(width, dtype=flow.dtype, device=flow.device)
    ys = torch.arange(height, dtype=flow.dtype, device=flow.device).view(height, 1)
    px, py = width * flow[:, 0], height * flow[:, 1]
    inside = (px >= -xs) & (px < (width - 1) - xs) & (py >= -ys) & (py < (height - 1) - ys)
    # Samples outside (and NaN) are moved far out of the image, where grid_sample gives 0.
    flow = torch.where(inside.unsqueeze(1), flow, torch.full_like(flow[:1, :1, :1, :1], -4.0))
    # grid_sample's align_corners=False grid is 2 u - 1 in normalised coordinates u.
    u, v = normalised_grid(height, width, flow)
    base = torch.stack(torch.broadcast_tensors(2 * u - 1, 2 * v - 1), dim=-1)  # (1, H, W, 2)
    grid = torch.addcmul(base, flow.permute(0, 2, 3, 1), flow.new_tensor(2.0))
    return F.grid_sample(image, grid.to(image.dtype), mode="bilinear", padding_mode="zeros",
                         align_corners=False)


@float32
def warp2d(image: Tensor, flow: Tensor) -> Tensor:
    """DeMoN's ``warp2d`` exactly (lmbspecialops' `src/warp2d.cc`, as DeMoN's graph calls it:
    ``normalized=True, border_mode='value'``, border value 0); ``model.compat=demon_original``.

    The sample position ``p = x + W fx`` (likewise y) is truncated toward zero, ``x0 = trunc(p)``,
    with weights ``a = p - x0``; the sample is valid only when ``x0 >= 0``, ``x0 + 1 < W``,
    ``y0 >= 0`` and ``y0 + 1 < H``, and 0 otherwise (NaN flow: 0). For ``-1 < p < 0`` this takes
    pixels 0 and 1 with a negative weight, i.e. extrapolates; :func:`warp_image` (demon_lab's
    default) gives 0 there (docs/reference.md §11 lists the differences between the two modes).

    Args and returns: as :func:`warp_image`.
    """
    batch, channels, height, width = _check_warp_inputs(image, flow)
    flow = flow.to(image.dtype)
    xs = torch.arange(width, dtype=image.dtype, device=image.device).view(1, 1, width)
    ys = torch.arange(height, dtype=image.dtype, device=image.device).view(1, height, 1)
    px, py = xs + flow[:, 0] * width, ys + flow[:, 1] * height  # the kernel's p1 + v, v scaled first
    x0, y0 = torch.trunc(px), torch.trunc(py)
    a, b = px - x0, py - y0
    valid = (x0 >= 0) & (x0 + 1 < width) & (y0 >= 0) & (y0 + 1 < height)  # False for NaN
    zero = torch.zeros_like(x0)
    ix, iy = torch.where(valid, x0, zero).long(), torch.where(valid, y0, zero).long()
    flat = image.reshape(batch, channels, height * width)

    def corner(dy: int, dx: int) -> Tensor:
        index = ((iy + dy) * width + ix + dx).clamp(max=height * width - 1).view(batch, 1, -1)
        return flat.gather(2, index.expand(-1, channels, -1)).view(batch, channels, height, width)

    a, b = a.unsqueeze(1), b.unsqueeze(1)
    out = ((1 - a) * (1 - b) * corner(0, 0) + a * (1 - b) * corner(0, 1)
           + (1 - a) * b * corner(1, 0) + a * b * corner(1, 1))
    return torch.where(valid.unsqueeze(1), out, torch.zeros_like(out))
