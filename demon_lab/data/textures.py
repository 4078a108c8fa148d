"""Texture bank for the synthetic scenes: scikit-image's photographs plus procedural patterns.

Everything is built from bytes that ship with scikit-image and from numpy's PCG64 generator with
basic arithmetic only, so the bank is identical on every machine (no download, no resampling
library whose SIMD paths could round differently). Lookups are filtered to the pixel's footprint
(:func:`sample_filtered` on :func:`mip_bank`), so that a minified texture does not alias.
"""

from __future__ import annotations

import functools

import numpy as np

# Photographs scikit-image ships (no download). Grey ones get a random tint per use.
PHOTOS = ("astronaut", "brick", "camera", "chelsea", "clock", "coffee", "coins", "colorwheel",
          "grass", "gravel", "hubble_deep_field", "immunohistochemistry", "moon", "page",
          "rocket", "text", "retina", "cell", "microaneurysms")
N_PROCEDURAL = 12
SIZE = 256  # textures are stored as SIZE x SIZE RGB float64 in [0, 1]


def _crop_square(a: np.ndarray) -> np.ndarray:
    h, w = a.shape[:2]
    s = min(h, w)
    a = a[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    # integer-step subsampling to SIZE (exact; photos are >= 300 px except microaneurysms)
    idx = (np.arange(SIZE) * s) // SIZE
    return a[idx][:, idx]


def _photo(name: str) -> np.ndarray:
    from skimage import data

    a = np.asarray(getattr(data, name)())
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=2)
    a = a[..., :3].astype(np.float64)
    if a.max() > 1.5:
        a = a / 255.0
    return _crop_square(a)


def _value_noise(rng: np.random.Generator, cells: int) -> np.ndarray:
    """Bilinear value noise, tileable, built with basic arithmetic."""
    grid = rng.random((cells + 1, cells + 1, 3))
    grid[-1], grid[:, -1] = grid[0], grid[:, 0]
    t = (np.arange(SIZE) + 0.5) * cells / SIZE
    i = np.floor(t).astype(np.int64)
    f = t - i
    a = grid[i][:, i] * ((1 - f)[:, None, None] * (1 - f)[None, :, None])
    a += grid[i + 1][:, i] * (f[:, None, None] * (1 - f)[None, :, None])
    a += grid[i][:, i + 1] * ((1 - f)[:, None, None] * f[None, :, None])
    a += grid[i + 1][:, i + 1] * (f[:, None, None] * f[None, :, None])
    return a


def _procedural(k: int) -> np.ndarray:
    """Procedural texture ``k``. Tiles and stripes take a random colour per cell, so no patch of a
    tile repeats inside it (a periodic pattern makes correspondence ambiguous)."""
    rng = np.random.default_rng(1000 + k)
    kind = k % 4
    yy, xx = np.meshgrid(np.arange(SIZE), np.arange(SIZE), indexing="ij")
    if kind == 0:  # tiles of random colours, with noise
        cells = 2 ** int(rng.integers(2, 5))  # 4, 8 or 16 per side
        palette = rng.random((cells, cells, 3))
        base = palette[yy // (SIZE // cells), xx // (SIZE // cells)]
        return np.clip(0.75 * base + 0.25 * _value_noise(rng, 16), 0, 1)
    if kind == 1:  # stripes of random colours, with noise
        period = int(rng.integers(6, 40))
        index = (xx + yy * int(rng.integers(0, 3))) // period
        palette = rng.random((int(index.max()) + 1, 3))
        return np.clip(0.7 * palette[index] + 0.3 * _value_noise(rng, 8), 0, 1)
    c1, c2 = rng.random(3), rng.random(3)
    if kind == 2:  # multi-octave noise
        a = sum(_value_noise(rng, c) / (i + 1) for i, c in enumerate((4, 8, 16, 32, 64)))
        a = (a - a.min()) / (a.max() - a.min())
        return a * 0.8 + 0.2 * c1
    # blobs of colour
    a = _value_noise(rng, 6)
    return np.where(a > 0.5, c1, c2) * 0.6 + 0.4 * _value_noise(rng, 32)


@functools.lru_cache(maxsize=1)
def texture_bank() -> tuple[np.ndarray, ...]:
    """All textures, (SIZE, SIZE, 3) float64 in [0, 1]: the photos first, then procedural ones."""
    return tuple([_photo(n) for n in PHOTOS] + [_procedural(k) for k in range(N_PROCEDURAL)])


def mip_pyramid(texture: np.ndarray) -> tuple[np.ndarray, ...]:
    """The texture and its 2x2 box-filtered reductions down to 1 x 1 (exact arithmetic)."""
    levels = [texture]
    while levels[-1].shape[0] > 1:
        a = levels[-1]
        levels.append((a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]) / 4)
    return tuple(levels)


@functools.lru_cache(maxsize=1)
def mip_bank() -> tuple[tuple[np.ndarray, ...], ...]:
    """:func:`mip_pyramid` of every texture of :func:`texture_bank`."""
    return tuple(mip_pyramid(t) for t in texture_bank())


def sample_texture(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around; u, v in texture periods (1 = one tile). (N,) -> (N, 3)."""
    size = texture.shape[0]
    x = u * size - 0.5
    y = v * size - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % size
    y0 = y0.astype(np.int64) % size
    x1, y1 = (x0 + 1) % size, (y0 + 1) % size
    return ((texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx) * (1 - fy)
            + (texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx) * fy)


def sample_filtered(pyramid: tuple[np.ndarray, ...], u: np.ndarray, v: np.ndarray,
                    footprint: np.ndarray) -> np.ndarray:
    """Trilinear mip-mapped lookup: ``footprint`` is the size of the pixel's footprint in texels
    of level 0 (N,); the lookup blends the two levels around it, linearly in the footprint, so a
    minified texture is averaged over the pixel instead of aliasing (which would make the two
    views of a surface disagree). Only +, -, *, / and comparisons: identical everywhere."""
    top = len(pyramid) - 1
    level = np.zeros(u.shape[0], dtype=np.int64)
    for k in range(1, top + 1):
        level += footprint >= 2.0 ** k
    frac = np.clip(footprint / 2.0 ** level - 1, 0.0, 1.0)[:, None]
    out = np.zeros((u.shape[0], 3))
    for lv in np.unique(level):
        m = level == lv
        lo = sample_texture(pyramid[lv], u[m], v[m])
        hi = sample_texture(pyramid[min(lv + 1, top)], u[m], v[m])
        out[m] = lo * (1 - frac[m]) + hi * frac[m]
    return out
