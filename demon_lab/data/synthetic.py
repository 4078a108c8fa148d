"""Procedural two-view scenes with perfect ground truth (in the spirit of Scenes11 and Blendswap).

A scene is a ground plane (outdoor presets) or a room (indoor preset) plus random boxes, slabs and
spheres, textured with scikit-image's photographs and procedural patterns and lit by one
directional light plus ambient light (Lambertian, so a surface looks the same from both views).
Images are rendered by exact ray casting (2x2 supersampling for colour; depth, normals and
visibility from the ray through each pixel centre), so depth of both views, motion, flow and
occlusion-aware visibility are exact.

Camera pairs follow presets whose rotation and triangulation-angle statistics reproduce the
supplementary's Table 1 (``python -m demon_lab.data_stats`` measures them). Pairs are filtered as
the supplementary describes: at least 50 % of view-1 pixels visible in view 2 and a minimum
baseline; and no view-1 point may come closer to camera 2 than a tenth of its view-1 depth (its
ground-truth flow would be unbounded).

Determinism: a sample is a pure function of (preset, seed, size). Per-pixel work uses only
correctly rounded IEEE operations (+, -, *, /, sqrt, floor) in float64 numpy, with no BLAS and
no transcendental functions; the scalar camera maths avoids BLAS too and draws from numpy's PCG64
generator. The only platform-dependent pieces are a few scalar calls of the C library's
sin/cos/exp/log (camera angles, numpy's gamma sampler), which can differ in the last bit between
C-library builds. With the same numpy and C library the same seed gives byte-identical samples on
any machine, in any process (tested across processes).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from demon_lab.core import geometry as geo
from demon_lab.data.raycast import Primitive, Scene, cast, matvec, matvec_t, shade
from demon_lab.data.sample import make_sample
from demon_lab.data.textures import texture_bank

GENERATOR_VERSION = 6
"""Bump when the scenes change: part of the data cache key, every stage key and every run key.
4: camera 2 orbits the target in either sense (before: always the same sense, so t_x < 0).
5: textures are mip-mapped to each pixel's footprint (before, a tile of 256 texels could cover 10
px: the views aliased differently), tiles span 0.6-1.5 camera distances (before 0.5-3 m in every
preset: tens of repeats), procedural tiles and stripes take a colour per cell (before: periodic)."""


def generator_version() -> int | str:
    """:data:`GENERATOR_VERSION`, where the generator's code is the code it names; else
    ``"<version>+<digest>"``: scenes of other code are cached and keyed apart
    (:func:`demon_lab.resources.versioned`)."""
    from demon_lab.resources import versioned

    return versioned(GENERATOR_VERSION, "generator")


def render_key(description: Mapping[str, Any]) -> str:
    """The cache folder key of a preset's rendering: the first 16 hex digits of the sha1 of its
    description (preset, size, supersampling, :func:`generator_version`) as sorted JSON."""
    blob = json.dumps(dict(description), sort_keys=True, default=str)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]


@dataclasses.dataclass(frozen=True)
class Preset:
    """How scenes and camera pairs are drawn. Angles in degrees, lengths in scene units (~metres)."""

    name: str
    indoor: bool
    tri_mean: float  # triangulation angle at the look-at point: gamma distribution
    tri_std: float
    convergence: float  # 1: camera 2 looks at the same point; 0: parallel to camera 1
    look_noise: float  # std of extra rotation of camera 2 (degrees, per axis)
    roll_std: float
    distance: tuple[float, float]  # camera 1 to look-at point
    n_objects: tuple[int, int]
    floating: float  # fraction of objects that float above the ground
    object_size: tuple[float, float]
    min_baseline: float = 0.05
    min_visible: float = 0.5
    min_depth_ratio: float = 0.1  # every valid view-1 point: depth in camera 2 >= this x depth in camera 1
    photorealistic: bool = False
    perfect_gt: bool = True


PRESETS = {
    p.name: p
    for p in (
        Preset("synthetic_scenes11", indoor=False, tri_mean=5.3, tri_std=4.4, convergence=0.55,
               look_noise=1.2, roll_std=0.8, distance=(3.0, 9.0), n_objects=(4, 10),
               floating=0.5, object_size=(0.4, 2.0)),
        Preset("synthetic_sun3d", indoor=True, tri_mean=5.7, tri_std=5.0, convergence=0.5,
               look_noise=7.0, roll_std=3.5, distance=(1.5, 4.0), n_objects=(3, 8),
               floating=0.0, object_size=(0.3, 1.2)),
        Preset("synthetic_mvs", indoor=False, tri_mean=38.0, tri_std=22.0, convergence=1.0,
               look_noise=10.0, roll_std=8.0, distance=(6.0, 14.0), n_objects=(6, 14),
               floating=0.0, object_size=(1.0, 4.0)),
    )
}


# ----------------------------------------------------------------------------- scenes


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# Scalar camera maths with explicit products: numpy's `@` and `linalg.norm` call BLAS, whose
# kernels (FMA or not) may round differently on other processors.


def _norm(v: np.ndarray) -> float:
    return math.sqrt(float(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / _norm(v)


def _mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3x3 @ 3x3, or 3x3 @ (3,)."""
    if b.ndim == 1:
        return np.array([a[i, 0] * b[0] + a[i, 1] * b[1] + a[i, 2] * b[2] for i in range(3)])
    return np.array([[a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j] for j in range(3)]
                     for i in range(3)])


def _rot_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about ``axis`` (Rodrigues, explicit)."""
    x, y, z = _unit(axis)
    c, s = math.cos(angle), math.sin(angle)
    C = 1 - c
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


def random_scene(rng: np.random.Generator, preset: Preset) -> Scene:
    n_tex = len(texture_bank())
    # A texture tile spans 0.6-1.5 camera distances: ~70-170 % of the image width at the look-at
    # point (about one texel per pixel there), so a surface repeats its tile a few times at most.
    tile = (preset.distance[0] + preset.distance[1]) / 2

    def material() -> dict:
        tint = 0.6 + 0.4 * rng.random(3)
        return {"texture": int(rng.integers(n_tex)), "texture_scale": float(rng.uniform(0.6, 1.5)) * tile,
                "tint": tint}

    prims: list[Primitive] = []
    room = None
    if preset.indoor:
        room = np.array([rng.uniform(2.0, 4.0), rng.uniform(2.0, 4.0), rng.uniform(1.3, 1.7)])
        prims.append(Primitive("room", np.array([0.0, 0.0, room[2]]), np.eye(3), room, **material()))
    else:
        prims.append(Primitive("plane", np.zeros(3), np.eye(3), np.zeros(3), **material()))
    lo, hi = preset.object_size
    extent = 0.8 * room[:2] if room is not None else np.array([4.0, 4.0])
    for _ in range(int(rng.integers(preset.n_objects[0], preset.n_objects[1] + 1))):
        kind = rng.choice(["box", "box", "slab", "sphere"])
        xy = (rng.random(2) * 2 - 1) * extent
        if kind == "sphere":
            r = rng.uniform(lo, hi) / 2
            size = np.array([r, r, r])
        elif kind == "slab":
            size = np.array([rng.uniform(lo, hi), rng.uniform(lo, hi), rng.uniform(0.03, 0.1)]) / 2
        else:
            size = rng.uniform(lo, hi, 3) / 2
        floating = rng.random() < preset.floating
        z = size[2] + (rng.uniform(0.2, 2.0) if floating else 0.0)
        rot = _rot_z(rng.uniform(0, 2 * math.pi))
        if floating or kind == "slab":
            axis = np.array([rng.normal(), rng.normal(), 0.0])
            rot = _mm(_rot_axis(axis, rng.uniform(-0.6, 0.6)), rot)
        prims.append(Primitive("sphere" if kind == "sphere" else "box",
                               np.array([xy[0], xy[1], z]), rot, size, **material()))
    elevation = rng.uniform(0.4, 1.2)
    azimuth = rng.uniform(0, 2 * math.pi)
    light = np.array([math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation),
                      math.sin(elevation)])
    return Scene(prims, light, float(rng.uniform(0.35, 0.55)), room)


# ----------------------------------------------------------------------------- cameras


@dataclasses.dataclass(frozen=True)
class Camera:
    rotation: np.ndarray  # world -> camera
    center: np.ndarray

    @property
    def translation(self) -> np.ndarray:
        return -_mm(self.rotation, self.center)


def look_at(center: np.ndarray, target: np.ndarray, roll: float = 0.0) -> Camera:
    forward = _unit(target - center)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    if _norm(right) < 1e-6:
        right = np.array([1.0, 0.0, 0.0])
    right = _unit(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    if roll:
        rotation = _mm(_rot_axis(np.array([0.0, 0.0, 1.0]), roll), rotation)
    return Camera(rotation, center)


def relative_motion(cam1: Camera, cam2: Camera) -> np.ndarray:
    """(6,) [r, t] with X2 = R X1 + t (camera coordinates)."""
    import torch

    r12 = _mm(cam2.rotation, cam1.rotation.T)
    t12 = cam2.translation - _mm(r12, cam1.translation)
    r = geo.matrix_to_angle_axis(torch.from_numpy(r12)[None])[0].numpy()
    return np.concatenate([r, t12])


def _gamma(rng: np.random.Generator, mean: float, std: float) -> float:
    shape = (mean / std) ** 2
    return float(rng.gamma(shape, mean / shape))


def sample_cameras(rng: np.random.Generator, scene: Scene, preset: Preset) -> tuple[Camera, Camera]:
    if preset.indoor:
        room = scene.room
        c1 = np.array([rng.uniform(-0.6, 0.6) * room[0], rng.uniform(-0.6, 0.6) * room[1],
                       rng.uniform(1.1, 1.8)])
        heading = rng.uniform(0, 2 * math.pi)
        pitch = rng.uniform(-0.45, 0.05)
        dist = rng.uniform(*preset.distance)
        target = c1 + dist * np.array([math.cos(heading) * math.cos(pitch),
                                       math.sin(heading) * math.cos(pitch), math.sin(pitch)])
    else:
        target = np.array([rng.normal() * 1.0, rng.normal() * 1.0, rng.uniform(0.2, 1.0)])
        dist = rng.uniform(*preset.distance)
        azimuth, elevation = rng.uniform(0, 2 * math.pi), rng.uniform(0.08, 0.5)
        c1 = target + dist * np.array([math.cos(azimuth) * math.cos(elevation),
                                       math.sin(azimuth) * math.cos(elevation), math.sin(elevation)])
    cam1 = look_at(c1, target, roll=math.radians(rng.normal() * preset.roll_std))
    # Camera 2 centre: rotate C1 about the target by the triangulation angle beta, about a random
    # axis perpendicular to the viewing ray (biased towards sideways motion), then move it along
    # its ray to the target (which keeps the angle at the target).
    beta = math.radians(min(_gamma(rng, preset.tri_mean, preset.tri_std), 85.0))
    ray = _unit(c1 - target)
    side = _unit(np.cross(ray, np.array([0.0, 0.0, 1.0])) + 1e-9)
    up = np.cross(side, ray)
    phi = rng.normal() * 0.5
    axis = math.cos(phi) * up + math.sin(phi) * side
    if rng.random() < 0.5:  # either orbit sense: camera 2 moves to the left or to the right
        axis = -axis
    c2 = target + _mm(_rot_axis(axis, beta), c1 - target) * rng.uniform(0.85, 1.15)
    if preset.indoor:
        c2 = np.clip(c2, -scene.room * 0.95 + np.array([0, 0, scene.room[2]]),
                     scene.room * 0.95 + np.array([0, 0, scene.room[2]]))
    # Camera 2 direction: between parallel to camera 1 and converging on the target, plus noise.
    f1 = cam1.rotation[2]
    converge = _unit(target - c2)
    direction = _unit(preset.convergence * converge + (1 - preset.convergence) * f1)
    noise = rng.normal(size=3) * math.radians(preset.look_noise)
    if _norm(noise) > 0:
        direction = _mm(_rot_axis(noise, _norm(noise)), direction)
    cam2 = look_at(c2, c2 + direction, roll=math.radians(rng.normal() * preset.roll_std))
    return cam1, cam2


# ----------------------------------------------------------------------------- rendering


INTRINSICS = np.array(geo.DEMON_INTRINSICS)


def _pixel_rays(camera: Camera, size: tuple[int, int], offsets: list[tuple[float, float]]):
    height, width = size
    fx, fy, cx, cy = INTRINSICS
    out = []
    for ox, oy in offsets:
        u = (np.arange(width) + ox) / width
        v = (np.arange(height) + oy) / height
        xs = np.broadcast_to(((u - cx) / fx)[None], (height, width)).reshape(-1)
        ys = np.broadcast_to(((v - cy) / fy)[:, None], (height, width)).reshape(-1)
        d_cam = np.stack([xs, ys, np.ones_like(xs)], 1)
        out.append(matvec_t(camera.rotation, d_cam))  # camera -> world: R^T d
    return out


def render_view(scene: Scene, camera: Camera, size: tuple[int, int], supersample: int = 2):
    """Image (H, W, 3) in [0, 1], camera-z depth (H, W) (inf where nothing is hit), world points."""
    height, width = size
    (centre,) = _pixel_rays(camera, size, [(0.5, 0.5)])
    t, index, normal, local = cast(scene, camera.center, centre)
    # Ray directions have camera-z component 1, so the ray parameter is the camera-z depth.
    depth = t.reshape(height, width)
    pixel = 1.0 / (INTRINSICS[0] * width * max(supersample, 1))  # sample spacing at depth 1
    if supersample <= 1:
        colour = shade(scene, centre, t, index, normal, local, pixel)
    else:
        offsets = [((i + 0.5) / supersample, (j + 0.5) / supersample)
                   for j in range(supersample) for i in range(supersample)]
        colour = np.zeros((height * width, 3))
        for dirs in _pixel_rays(camera, size, offsets):
            colour += shade(scene, dirs, *cast(scene, camera.center, dirs), pixel)
        colour /= len(offsets)
    points = camera.center[None] + np.where(np.isfinite(t), t, 0.0)[:, None] * centre
    return colour.reshape(height, width, 3), depth, points


def visibility(scene: Scene, points: np.ndarray, valid: np.ndarray, camera: Camera,
               size: tuple[int, int]) -> np.ndarray:
    """Exact visibility of world points from camera 2: inside image 2 and not occluded."""
    fx, fy, cx, cy = INTRINSICS
    p = matvec(camera.rotation, points - camera.center[None])
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * p[:, 0] / p[:, 2] + cx
        v = fy * p[:, 1] / p[:, 2] + cy
    inside = valid & (p[:, 2] > 0) & (u > 0) & (u < 1) & (v > 0) & (v < 1)
    out = np.zeros(points.shape[0], dtype=bool)
    if inside.any():
        dirs = points[inside] - camera.center[None]  # the point sits at ray parameter 1
        t = cast(scene, camera.center, dirs)[0]
        out[inside] = t >= 1 - 1e-6
    return out


def depth_ratio_ok(points: np.ndarray, depth1: np.ndarray, camera2: Camera, min_ratio: float) -> bool:
    """True when every world point's camera-2 depth is at least ``min_ratio`` times its camera-1
    depth ``depth1``. Ground-truth flow divides by the camera-2 depth, so a point near (or behind)
    camera 2 would give flow of hundreds of image widths."""
    z2 = matvec(camera2.rotation, points - camera2.center[None])[:, 2]
    return bool(np.all(z2 >= min_ratio * depth1))


def render_pair(preset: Preset | str, seed: int, size: tuple[int, int] = (96, 128),
                supersample: int = 2, max_tries: int = 50, return_scene: bool = False):
    """The synthetic sample of ``seed``: a scene and a camera pair that pass the pair filters.

    Returns a :mod:`demon_lab.data.sample` ``Sample`` (DeMoN's intrinsics, scene units ~ metres,
    translation not normalised) with ``meta`` holding the rejection count; with
    ``return_scene=True``, ``(sample, scene, camera1, camera2)``.
    """
    preset = PRESETS[preset] if isinstance(preset, str) else preset
    rng = np.random.default_rng(seed)
    height, width = size
    for attempt in range(max_tries):
        scene = random_scene(rng, preset)
        for _ in range(4):
            cam1, cam2 = sample_cameras(rng, scene, preset)
            motion = relative_motion(cam1, cam2)
            if _norm(motion[3:]) < preset.min_baseline:
                continue
            # Cheap filter at 1/4 resolution before the full render.
            small = (max(height // 4, 6), max(width // 4, 8))
            _, d_small, pts_small = render_view(scene, cam1, small, supersample=1)
            ok = np.isfinite(d_small).reshape(-1)
            vis = visibility(scene, pts_small, ok, cam2, small)
            if vis.mean() < preset.min_visible:
                continue
            image1, depth1, points1 = render_view(scene, cam1, size, supersample)
            valid = np.isfinite(depth1).reshape(-1)
            visible = visibility(scene, points1, valid, cam2, size)
            if visible.mean() < preset.min_visible:
                continue
            if not depth_ratio_ok(points1[valid], depth1.reshape(-1)[valid], cam2, preset.min_depth_ratio):
                continue
            image2, depth2, _ = render_view(scene, cam2, size, supersample)
            quantise = lambda im: np.floor(np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
            with np.errstate(divide="ignore"):
                inv1 = np.where(np.isfinite(depth1), 1.0 / depth1, np.nan)
                inv2 = np.where(np.isfinite(depth2), 1.0 / depth2, np.nan)
            sample = make_sample(
                f"{preset.name}/{seed}", quantise(image1), quantise(image2), INTRINSICS,
                inv1.astype(np.float32), motion, inv_depth2=inv2.astype(np.float32),
                visible=visible.reshape(height, width),
            )
            sample["meta"] = {"rejected": attempt}
            return (sample, scene, cam1, cam2) if return_scene else sample
    raise RuntimeError(f"{preset.name}: no camera pair passed the filters in {max_tries} scenes "
                       f"(seed {seed})")
