"""Textured 2-D layers under affine motion: image pairs with exact optical flow, cheap enough to draw
a new pair for every training sample.

This is the idea of FlowNet's "Flying Chairs" (Dosovitskiy et al., ICCV 2015): a textured background
and a few textured shapes in front of it, each moved by its own affine map between the two views.
FlowNet 2.0 (Ilg et al., CVPR 2017, §4) found that a flow net trained on such 2-D motion before 3-D
scenes ends better than one trained on 3-D scenes alone. demon_lab uses it as an option of the
``cpu`` scale's flow stages (``layers_first``; docs/cpu_scale.md, "Departures from DeMoN"): DeMoN's
own flow net never sees such data.

A pair has no depth and no camera motion, only flow: its samples carry ``flow`` (2, H, W), normalised
as everywhere in demon_lab (x by the width, y by the height), and the flow stages' loss reads it
(:class:`demon_lab.core.losses.GroundTruth`). The textures are those of the synthetic scenes
(:func:`demon_lab.data.textures.texture_bank`: scikit-image's photographs and procedural patterns).

A pair is a pure function of ``(seed, size)``: the layer set and the affine maps come from numpy's
PCG64 generator; the textures are resampled by OpenCV's ``warpAffine`` (bilinear, 8 bits, as the
rendered scenes' images).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from demon_lab.core.geometry import DEMON_INTRINSICS
from demon_lab.data.textures import texture_bank

MAX_LAYERS = 4
"""Foreground shapes per pair: 1 to MAX_LAYERS, over the background."""


@functools.lru_cache(maxsize=1)
def _textures() -> tuple[np.ndarray, ...]:
    """The texture bank in 8 bits, each texture tiled 2 x 2: a view's texels stay inside it
    (:func:`_layout`), so resampling never takes OpenCV's slow path for coordinates outside the image."""
    return tuple(np.tile(np.floor(t * 255 + 0.5).astype(np.uint8), (2, 2, 1)) for t in texture_bank())


def _affine(rng: np.random.Generator, width: int, height: int, shift: float, angle: float,
            zoom: float) -> np.ndarray:
    """A random similarity about the image centre, as a 3x3 matrix in pixels: translation up to
    ``shift`` x the width (uniform in a disc), rotation up to ``angle`` degrees, scale in
    ``[1 - zoom, 1 + zoom]``."""
    r = shift * width * math.sqrt(rng.random())
    phi = 2 * math.pi * rng.random()
    a = math.radians(angle) * (2 * rng.random() - 1)
    s = 1 + zoom * (2 * rng.random() - 1)
    cx, cy = width / 2, height / 2
    c, n = s * math.cos(a), s * math.sin(a)
    return np.array([[c, -n, cx - c * cx + n * cy + r * math.cos(phi)],
                     [n, c, cy - n * cx - c * cy + r * math.sin(phi)],
                     [0.0, 0.0, 1.0]])


def _layout(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Where a layer's texture sits in view 1 (pixels -> texels of the tiled texture): a random
    rotation, 0.35-1.2 texels per pixel, and the image centre within 48 texels of the tile's centre
    (256, 256), so that both views, moved by up to ~40 pixels, stay inside the 512 x 512 tile at 128x96."""
    a = 2 * math.pi * rng.random()
    s = rng.uniform(0.35, 1.2) * 128 / max(width, 128)  # (larger images: the same texels per image)
    c, n = s * math.cos(a), s * math.sin(a)
    u, v = 256 + rng.uniform(-48, 48), 256 + rng.uniform(-48, 48)
    cx, cy = width / 2, height / 2
    return np.array([[c, -n, u - c * cx + n * cy], [n, c, v - n * cx - c * cy], [0.0, 0.0, 1.0]])


def render_layers(seed: int, size: tuple[int, int] = (96, 128)) -> dict:
    """The layered pair of ``seed`` at ``size`` (H, W): ``image1``, ``image2`` (3, H, W) float32 in
    [-0.5, 0.5], ``flow`` (2, H, W) normalised (exact: the affine motion of the front-most layer at
    each pixel of view 1; it may leave the image, as in Flying Chairs), ``intrinsics`` (DeMoN's;
    no geometry depends on them)."""
    import cv2

    height, width = size
    rng = np.random.default_rng([seed, 7])
    bank = _textures()
    xs, ys = _grid(height, width)

    background = _affine(rng, width, height, shift=0.12, angle=8.0, zoom=0.06)
    layers = [(int(rng.integers(len(bank))), _layout(rng, width, height), None, background)]
    for _ in range(int(rng.integers(1, MAX_LAYERS + 1))):
        # a shape: an ellipse of random axes (10-45 % of the width), at a random place of view 1
        axes = rng.uniform(0.10, 0.45, size=2) * width
        centre = np.array([rng.uniform(0, width), rng.uniform(0, height)])
        own = _affine(rng, width, height, shift=0.10, angle=15.0, zoom=0.08)
        shape = (centre, axes, 2 * math.pi * rng.random())
        layers.append((int(rng.integers(len(bank))), _layout(rng, width, height), shape, own @ background))

    # Painted back to front. A layer's coordinates are view 1's pixels; view 2 sees its point q at
    # motion @ q, so view 2's pixel p shows the layer's point motion^-1 @ p.
    images = [np.zeros((height, width, 3), np.uint8) for _ in range(2)]
    flow = np.zeros((height, width, 2), np.float32)
    for texture, layout, shape, motion in layers:
        for view, to_layer in enumerate((np.eye(3), np.linalg.inv(motion))):
            to_texel = (layout @ to_layer)[:2]
            colour = cv2.warpAffine(bank[texture], to_texel, (width, height), flags=cv2.INTER_LINEAR
                                    | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT_101)
            q = to_layer[:2]
            inside = (True if shape is None else
                      _in_ellipse(q[0, 0] * xs + q[0, 1] * ys + q[0, 2], q[1, 0] * xs + q[1, 1] * ys + q[1, 2], shape))
            np.copyto(images[view], colour, where=inside if shape is None else inside[..., None])
            if view == 0:
                np.copyto(flow, _layer_flow(motion, xs, ys), where=inside if shape is None else inside[..., None])
    as_image = lambda im: torch.from_numpy(im.transpose(2, 0, 1).astype(np.float32) / 255 - 0.5)  # noqa: E731
    normalised = (flow / np.array([width, height], np.float32)).transpose(2, 0, 1).copy()
    return {"id": f"layers/{seed}", "image1": as_image(images[0]), "image2": as_image(images[1]),
            "flow": torch.from_numpy(normalised), "intrinsics": torch.tensor(DEMON_INTRINSICS, dtype=torch.float32)}


@functools.lru_cache(maxsize=4)
def _grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    return xs, ys


def _layer_flow(motion: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(H, W, 2) pixel flow ``motion @ p - p`` of every pixel ``p`` of view 1."""
    m = (motion - np.eye(3)).astype(np.float32)
    return np.stack([m[0, 0] * xs + m[0, 1] * ys + m[0, 2], m[1, 0] * xs + m[1, 1] * ys + m[1, 2]], -1)


def _in_ellipse(x: np.ndarray, y: np.ndarray, shape) -> np.ndarray:
    (cx, cy), (a, b), phi = shape
    dx, dy = x - cx, y - cy
    c, s = math.cos(phi), math.sin(phi)
    u, v = (c * dx + s * dy) / a, (-s * dx + c * dy) / b
    return u * u + v * v <= 1.0
