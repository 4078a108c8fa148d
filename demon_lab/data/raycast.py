"""Exact ray casting of the procedural scenes (:mod:`demon_lab.data.synthetic`): each ray's first
hit, its surface point and normal, and its Lambertian colour under the scene's light.

Per-pixel work uses only correctly rounded IEEE operations (+, -, *, /, sqrt, floor) in float64
numpy, with no BLAS (the determinism rule of :mod:`demon_lab.data.synthetic`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from demon_lab.data.textures import mip_bank, sample_filtered

EPS = 1e-9


@dataclasses.dataclass
class Primitive:
    kind: str  # "plane" (z = 0), "box", "room" (a box seen from inside), "sphere"
    center: np.ndarray
    rotation: np.ndarray  # local -> world
    size: np.ndarray  # box half-extents, or (radius, radius, radius)
    texture: int
    texture_scale: float  # scene units per texture tile
    tint: np.ndarray


@dataclasses.dataclass
class Scene:
    primitives: list[Primitive]
    light: np.ndarray  # unit vector towards the light
    ambient: float
    room: np.ndarray | None  # room half-extents (indoor)


def matvec_t(m: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(m^T d_i) for rows d_i of (N, 3), with explicit sums (no BLAS: identical everywhere)."""
    return np.stack([d[:, 0] * m[0, k] + d[:, 1] * m[1, k] + d[:, 2] * m[2, k] for k in range(3)], 1)


def matvec(m: np.ndarray, d: np.ndarray) -> np.ndarray:
    return np.stack([d[:, 0] * m[k, 0] + d[:, 1] * m[k, 1] + d[:, 2] * m[k, 2] for k in range(3)], 1)


def _local_rays(p: Primitive, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Ray origin (3,) and direction columns [(N,)] * 3 in the primitive's frame."""
    o = matvec_t(p.rotation, (origin - p.center)[None])[0]
    r = p.rotation
    d = [dirs[:, 0] * r[0, k] + dirs[:, 1] * r[1, k] + dirs[:, 2] * r[2, k] for k in range(3)]
    return o, d


def _hit_distance(p: Primitive, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray parameter of the nearest hit with t > EPS (inf if none), for every ray (N,)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if p.kind == "plane":
            t = -origin[2] / dirs[:, 2]
            return np.where(t > EPS, t, np.inf)  # NaN and -inf compare False
        o, d = _local_rays(p, origin, dirs)
        if p.kind == "sphere":
            r = p.size[0]
            a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
            b = d[0] * o[0] + d[1] * o[1] + d[2] * o[2]
            c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - r * r
            disc = b * b - a * c
            root = np.sqrt(np.maximum(disc, 0.0))
            t0, t1 = (-b - root) / a, (-b + root) / a
            t = np.where(t0 > EPS, t0, np.where(t1 > EPS, t1, np.inf))
            return np.where(disc >= 0, t, np.inf)
        # box / room: slab method; fmin/fmax skip the NaN of 0 * inf on a slab boundary
        t_near = np.full(dirs.shape[0], -np.inf)
        t_far = np.full(dirs.shape[0], np.inf)
        for k in range(3):
            inv = 1.0 / d[k]
            t1 = (-p.size[k] - o[k]) * inv
            t2 = (p.size[k] - o[k]) * inv
            t_near = np.fmax(t_near, np.fmin(t1, t2))
            t_far = np.fmin(t_far, np.fmax(t1, t2))
        hit = t_far >= np.maximum(t_near, EPS)
        t = t_far if p.kind == "room" else t_near  # a room is seen from inside
        return np.where(hit & (t > EPS), t, np.inf)


def _surface(p: Primitive, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World normal (facing the ray's side) and local hit point of rays that hit ``p`` at ``t``."""
    if p.kind == "plane":
        normal = np.zeros_like(dirs)
        normal[:, 2] = 1.0 if origin[2] >= 0 else -1.0
        return normal, origin[None] + t[:, None] * dirs
    o, d = _local_rays(p, origin, dirs)
    local = np.stack([o[k] + t * d[k] for k in range(3)], 1)
    if p.kind == "sphere":
        inside = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] < p.size[0] * p.size[0]
        normal = local / (-p.size[0] if inside else p.size[0])
    else:  # the face is the axis where the point lies on the box surface
        ratio = np.abs(local) / p.size[None]
        axis = np.where((ratio[:, 0] >= ratio[:, 1]) & (ratio[:, 0] >= ratio[:, 2]), 0,
                        np.where(ratio[:, 1] >= ratio[:, 2], 1, 2))
        rows = np.arange(local.shape[0])
        normal = np.zeros_like(local)
        side = np.sign(local[rows, axis])
        normal[rows, axis] = -side if p.kind == "room" else side  # rooms face inwards
    return matvec(p.rotation, normal), local


def cast(scene: Scene, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Nearest hit of every ray from ``origin`` along ``dirs`` (N, 3): ray parameter t (inf for
    no hit), primitive index (-1), world normal and the hit point in the primitive's frame."""
    n = dirs.shape[0]
    best = np.full(n, np.inf)
    index = np.full(n, -1, dtype=np.int64)
    for i, p in enumerate(scene.primitives):
        t = _hit_distance(p, origin, dirs)
        closer = t < best
        best = np.where(closer, t, best)
        index = np.where(closer, i, index)
    normal = np.zeros((n, 3))
    local = np.zeros((n, 3))
    for i in np.unique(index[index >= 0]):
        m = index == i
        normal[m], local[m] = _surface(scene.primitives[i], origin, dirs[m], best[m])
    return best, index, normal, local


def shade(scene: Scene, dirs: np.ndarray, t: np.ndarray, index: np.ndarray, normal: np.ndarray,
          local: np.ndarray, pixel: float) -> np.ndarray:
    """Lambertian colour of each hit (N, 3) in [0, 1]; rays that hit nothing see the sky.

    ``dirs`` have camera-z component 1 and ``t`` is the camera-z depth of the hit; ``pixel`` is the
    size of a pixel (of this sampling grid) at depth 1, so a pixel covers ``t * pixel`` across the
    ray, stretched by 1 / cos(incidence) along the surface. Textures are filtered to that
    footprint (the geometric mean of its two axes: sqrt(cos) in the denominator)."""
    bank = mip_bank()
    colour = np.zeros((dirs.shape[0], 3))
    norm = np.sqrt(dirs[:, 0] * dirs[:, 0] + dirs[:, 1] * dirs[:, 1] + dirs[:, 2] * dirs[:, 2])
    up = np.clip(dirs[:, 2] / norm, 0.0, 1.0)[:, None]
    colour[:] = np.array([0.78, 0.85, 0.95]) * (1 - up) + np.array([0.35, 0.55, 0.9]) * up
    lit = np.clip(normal[:, 0] * scene.light[0] + normal[:, 1] * scene.light[1]
                  + normal[:, 2] * scene.light[2], 0.0, 1.0)
    intensity = scene.ambient + (1 - scene.ambient) * lit
    for i, p in enumerate(scene.primitives):
        m = index == i
        if not m.any():
            continue
        loc, nrm = local[m], normal[m]
        # planar projection along the dominant axis of the local normal (exact, no trig)
        ln = np.abs(matvec_t(p.rotation, nrm))
        axis = ln.argmax(1)
        u = np.where(axis == 0, loc[:, 1], loc[:, 0])
        v = np.where(axis == 2, loc[:, 1], loc[:, 2])
        d = dirs[m]
        dn = np.abs(d[:, 0] * nrm[:, 0] + d[:, 1] * nrm[:, 1] + d[:, 2] * nrm[:, 2])
        cos = np.maximum(dn / norm[m], 1e-3)
        texels = t[m] * pixel / np.sqrt(cos) * (bank[p.texture][0].shape[0] / p.texture_scale)
        albedo = sample_filtered(bank[p.texture], u / p.texture_scale, v / p.texture_scale, texels) * p.tint
        colour[m] = albedo * intensity[m, None]
    return colour
