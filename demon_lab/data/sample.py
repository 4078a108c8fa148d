"""``Sample``: one two-view training/evaluation example, the same for every data source.

A sample is a plain ``dict`` (so PyTorch's default collate batches it) with these keys; maps are
float32 torch tensors unless stated, conventions as in :mod:`demon_lab.core.geometry`:

=============== ================ ==============================================================
key             shape / type     meaning
=============== ================ ==============================================================
``id``          str              ``<source>/<name>``, unique within a source
``image1``      (3, H, W)        RGB of view 1 in [-0.5, 0.5] (x / 255 - 0.5)
``image2``      (3, H, W)        RGB of view 2
``intrinsics``  (4,)             normalised intrinsics of view 1 (fx/W, fy/H, cx/W, cy/H)
``intrinsics2`` (4,)             normalised intrinsics of view 2 (equal to view 1's for most
                                 sources; Middlebury's principal points differ)
``inv_depth``   (1, H, W)        GT inverse camera-z depth of view 1, NaN = invalid; the unit is
                                 the source's (metres for real data) unless the translation was
                                 normalised, then it is the unit-baseline scale
``inv_depth2``  (1, H, W)        the same for view 2; all NaN when the source has none
``motion``      (6,)             GT [r, t], X2 = R(r) X1 + t, t in the unit of the depth
``flow``        (2, H, W)        GT flow from depth + motion (normalised), NaN where invalid
``normals``     (3, H, W)        GT normals of view 1 from its depth, NaN where undefined
``valid``       (1, H, W) bool   view-1 depth is valid (finite, > 0)
``visible``     (1, H, W) bool   valid and visible in view 2: for synthetic scenes exact
                                 (occlusion-aware ray casting); for real data the 3-D point
                                 projects inside image 2 and, where view-2 depth exists, agrees
                                 with it within 10 %
``baseline``    float            |t| in the source's unit before any translation normalisation
=============== ================ ==============================================================

:func:`make_sample` builds a sample from the raw fields and derives the rest; :func:`resample`
changes resolution and, optionally, the intrinsics (crop + scale as one exact affine map);
:func:`normalize_translation` applies DeMoN's ``norm_trans_scale_depth``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import torch

from demon_lab.core import geometry as geo

Sample = dict[str, Any]
MAP_KEYS = ("image1", "image2", "inv_depth", "inv_depth2", "flow", "normals", "valid", "visible")
REPROJECTION_TOLERANCE = 0.1  # relative depth agreement for "visible" on real data


class DataError(ValueError):
    """Bad input data: the message names the file or sample and the problem (one line)."""


def _tensor(x: Any, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def make_sample(
    id: str,
    image1: Any,
    image2: Any,
    intrinsics: Sequence[float],
    inv_depth: Any,
    motion: Sequence[float],
    intrinsics2: Sequence[float] | None = None,
    inv_depth2: Any | None = None,
    visible: Any | None = None,
    baseline: float | None = None,
    derived: bool = True,
) -> Sample:
    """Validate the raw fields of a pair and derive flow, normals and masks.

    Args:
        id: sample id (used in error messages).
        image1, image2: (3, H, W) float in [-0.5, 0.5] or (H, W, 3) uint8 RGB.
        intrinsics: (4,) normalised intrinsics of view 1; ``intrinsics2`` of view 2 (default: same).
        inv_depth: (H, W) or (1, H, W) inverse depth of view 1; NaN, 0, inf or negative = invalid.
        motion: (6,) [r, t] with X2 = R X1 + t.
        inv_depth2: optional inverse depth of view 2.
        visible: optional (H, W) bool visibility of view-1 pixels in view 2 (exact, e.g. from a
            renderer); by default it is computed geometrically (see the module docstring).
        baseline: |t| before normalisation (default: |t|).
        derived: add flow, normals, valid and visible (:func:`derive`); False leaves them out (a
            training draw reads none of them: its loss derives its targets from depth and motion).

    Raises:
        DataError: wrong shapes, non-finite motion or intrinsics, or no valid depth at all.
    """
    im1, im2 = _image(id, "image1", image1), _image(id, "image2", image2)
    if im1.shape != im2.shape:
        raise DataError(f"{id}: image2 has shape {tuple(im2.shape)}, image1 {tuple(im1.shape)}")
    height, width = im1.shape[1:]
    k1 = _vector(id, "intrinsics", intrinsics, 4)
    k2 = k1.clone() if intrinsics2 is None else _vector(id, "intrinsics2", intrinsics2, 4)
    if (k1[:2] <= 0).any() or (k2[:2] <= 0).any():
        raise DataError(f"{id}: focal lengths must be positive, got {k1.tolist()} / {k2.tolist()}")
    m = _vector(id, "motion", motion, 6)
    d1 = _depth_map(id, "inv_depth", inv_depth, height, width)
    d2 = (torch.full_like(d1, math.nan) if inv_depth2 is None
          else _depth_map(id, "inv_depth2", inv_depth2, height, width))
    valid = geo.valid_depth(d1)
    if not bool(valid.any()):
        raise DataError(f"{id}: view-1 depth has no valid pixel (all NaN, zero, negative or inf)")
    d1 = torch.where(valid, d1, torch.full_like(d1, math.nan))
    d2 = torch.where(geo.valid_depth(d2), d2, torch.full_like(d2, math.nan))
    norm = float(m[3:].norm())
    sample: Sample = {
        "id": id, "image1": im1, "image2": im2, "intrinsics": k1, "intrinsics2": k2,
        "inv_depth": d1, "inv_depth2": d2, "motion": m,
        "baseline": float(norm if baseline is None else baseline),
    }
    if visible is not None:
        vis = torch.as_tensor(np.asarray(visible), dtype=torch.bool).reshape(1, height, width)
        sample["visible"] = vis & valid
    return derive(sample) if derived else sample


def derive(sample: Sample) -> Sample:
    """(Re)compute flow, normals, valid and, when absent, visible from depth and motion."""
    d1, m = sample["inv_depth"][None], sample["motion"][None]
    k1, k2 = sample["intrinsics"][None], sample["intrinsics2"][None]
    sample["valid"] = geo.valid_depth(sample["inv_depth"])
    sample["flow"] = geo.flow_from_depth_motion(d1, m, k1, k2)[0]
    sample["normals"] = geo.normals_from_depth(d1, k1)[0]
    if "visible" not in sample:
        sample["visible"] = geometric_visibility(sample)
    return sample


def geometric_visibility(sample: Sample) -> torch.Tensor:
    """Visibility for sources without an exact one: inside image 2, in front of camera 2, and,
    where view-2 depth exists at the landing pixel, a depth agreeing within 10 %."""
    d1, m = sample["inv_depth"][None], sample["motion"][None]
    k1, k2 = sample["intrinsics"][None], sample["intrinsics2"][None]
    visible = geo.visibility_mask(d1, m, k1, k2)[0]
    d2 = sample["inv_depth2"][0]
    if not bool(torch.isfinite(d2).any()):
        return visible
    coords, inv2 = geo.reproject(d1, m, k1, k2)
    height, width = d2.shape
    coords = torch.nan_to_num(coords, nan=0.0)  # invalid pixels are not visible anyway
    x = (coords[0, 0] * width).floor().clamp(0, width - 1).long()
    y = (coords[0, 1] * height).floor().clamp(0, height - 1).long()
    target = d2[y, x]
    ratio = target / inv2[0, 0]
    agree = torch.isfinite(ratio) & ((ratio - 1).abs() <= REPROJECTION_TOLERANCE)
    unknown = ~torch.isfinite(target)
    return visible & (agree | unknown)[None]


def _image(id: str, name: str, x: Any) -> torch.Tensor:
    if isinstance(x, np.ndarray) and x.dtype == np.uint8:
        if x.ndim != 3 or x.shape[2] != 3:
            raise DataError(f"{id}: {name} must be (H, W, 3) RGB, got shape {x.shape}")
        return torch.from_numpy(x.astype(np.float32) / 255.0 - 0.5).permute(2, 0, 1).contiguous()
    t = _tensor(x)
    if t.dim() != 3 or t.shape[0] != 3:
        raise DataError(f"{id}: {name} must be (3, H, W) float or (H, W, 3) uint8, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise DataError(f"{id}: {name} has non-finite values")
    return t.contiguous()


def _vector(id: str, name: str, x: Any, size: int) -> torch.Tensor:
    t = _tensor(x).reshape(-1)
    if t.numel() != size:
        raise DataError(f"{id}: {name} must have {size} values, got {t.numel()}")
    if not bool(torch.isfinite(t).all()):
        raise DataError(f"{id}: {name} has non-finite values: {t.tolist()}")
    return t


def _depth_map(id: str, name: str, x: Any, height: int, width: int) -> torch.Tensor:
    t = _tensor(x)
    if t.dim() == 2:
        t = t[None]
    if tuple(t.shape) != (1, height, width):
        raise DataError(f"{id}: {name} must be ({height}, {width}) like the images, "
                        f"got {tuple(t.shape)}")
    return t.contiguous()


# ----------------------------------------------------------------------------- transforms


def normalize_translation(sample: Sample) -> Sample:
    """DeMoN's ``norm_trans_scale_depth``: |t| = 1, depths divided by the old |t| alike."""
    norm = float(sample["motion"][3:].norm())
    if not norm > 1e-6:
        raise DataError(f"{sample['id']}: zero baseline (|t| = {norm:.3g}): cannot normalise")
    out = dict(sample)
    out["motion"] = torch.cat([sample["motion"][:3], sample["motion"][3:] / norm])
    out["inv_depth"] = sample["inv_depth"] * norm
    out["inv_depth2"] = sample["inv_depth2"] * norm
    return out  # flow, normals and masks do not change


def resample(
    sample: Sample,
    size: tuple[int, int],
    intrinsics: Sequence[float] | None = None,
    derived: bool = True,
) -> Sample:
    """Change the resolution to ``size = (H, W)`` and, optionally, the intrinsics of both views.

    Without ``intrinsics`` this is a plain resize (area averaging for images, nearest neighbour
    for depth and masks): normalised intrinsics do not change. With ``intrinsics`` (normalised,
    e.g. :data:`demon_lab.core.geometry.DEMON_INTRINSICS`) each view is resampled through the exact
    affine map between its own pinhole camera and the target one (a crop plus a scale), so the
    result is the image that camera would have seen; pixels with no source become mid grey
    (images) and invalid (depth). Flow and normals are recomputed from depth and motion
    (``derived=False``: left out, and ``visible`` resampled only if the sample has it).
    """
    height, width = size
    out = dict(sample)
    views = [("image1", "inv_depth", "intrinsics"), ("image2", "inv_depth2", "intrinsics2")]
    for image_key, depth_key, k_key in views:
        k_in = sample[k_key].double().numpy()
        k_out = k_in if intrinsics is None else np.asarray(intrinsics, dtype=np.float64)
        out[image_key] = _resample_map(sample[image_key], k_in, k_out, size, "image")
        out[depth_key] = _resample_map(sample[depth_key], k_in, k_out, size, "depth")
        out[k_key] = torch.tensor(k_out, dtype=torch.float32)
    if "visible" in sample:
        visible = _resample_map(sample["visible"].float(), sample["intrinsics"].double().numpy(),
                                out["intrinsics"].double().numpy(), size, "depth")
        out["visible"] = (visible > 0.5) & geo.valid_depth(out["inv_depth"])
    for key in ("flow", "normals", "valid"):
        out.pop(key, None)
    if not bool(geo.valid_depth(out["inv_depth"]).any()):
        raise DataError(f"{sample['id']}: no valid depth left after resampling to {width}x{height}")
    return derive(out) if derived else out


def _resample_map(x: torch.Tensor, k_in: np.ndarray, k_out: np.ndarray,
                  size: tuple[int, int], kind: str) -> torch.Tensor:
    """Resample a (C, h, w) map from camera k_in to camera k_out at ``size``."""
    height, width = size
    c, h, w = x.shape
    a = x.permute(1, 2, 0).numpy().astype(np.float32)
    same_camera = np.allclose(k_in, k_out, rtol=0, atol=1e-12)
    if kind == "image":
        # Area-average first when shrinking, then the exact affine map in one bilinear pass.
        scale_x = k_out[0] * width / (k_in[0] * w)
        scale_y = k_out[1] * height / (k_in[1] * h)
        if same_camera:
            interp = cv2.INTER_AREA if (width < w or height < h) else cv2.INTER_LINEAR
            a = cv2.resize(a, (width, height), interpolation=interp)
            return torch.from_numpy(a.reshape(height, width, c)).permute(2, 0, 1).contiguous()
        if scale_x < 1 or scale_y < 1:
            w2, h2 = max(1, round(w * min(scale_x, 1.0))), max(1, round(h * min(scale_y, 1.0)))
            a = cv2.resize(a, (w2, h2), interpolation=cv2.INTER_AREA).reshape(h2, w2, c)
            h, w = h2, w2  # normalised intrinsics are unchanged by a full-image resize
    map_x, map_y = _affine_maps(k_in, k_out, (h, w), size)
    if kind == "image":
        a = cv2.remap(a, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=0)
    else:  # nearest neighbour; outside -> NaN
        xi, yi = np.floor(map_x + 0.5).astype(np.int64), np.floor(map_y + 0.5).astype(np.int64)
        inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        a = np.where(inside[..., None], a[yi.clip(0, h - 1), xi.clip(0, w - 1)], np.nan)
    return torch.from_numpy(np.ascontiguousarray(a.reshape(height, width, c))).permute(2, 0, 1).contiguous()


def _affine_maps(k_in: np.ndarray, k_out: np.ndarray, shape_in: tuple[int, int],
                 size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Source pixel coordinates (cv2.remap convention: pixel centre j at j) of each output pixel."""
    h, w = shape_in
    height, width = size
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    u_in = (u - k_out[2]) / k_out[0] * k_in[0] + k_in[2]
    v_in = (v - k_out[3]) / k_out[1] * k_in[1] + k_in[3]
    map_x = np.broadcast_to((u_in * w - 0.5)[None, :], (height, width)).astype(np.float32)
    map_y = np.broadcast_to((v_in * h - 0.5)[:, None], (height, width)).astype(np.float32)
    return np.ascontiguousarray(map_x), np.ascontiguousarray(map_y)


# ----------------------------------------------------------------------------- augmentation


def rotate_180(sample: Sample, normals: bool = True) -> Sample:
    """Both images turned by 180 degrees: both cameras rotate by pi about their z axes.

    X' = Rz X with Rz = diag(-1, -1, 1): R' = Rz R Rz, i.e. r' = (-rx, -ry, rz); t' = (-tx, -ty, tz);
    cx -> 1 - cx, cy -> 1 - cy; maps flipped on both axes; flow x, y negated.
    """
    return _flip_sample(sample, (-2, -1), [ROTATE], normals)


def mirror(sample: Sample, normals: bool = True) -> Sample:
    """Horizontal mirror: X' = M X with M = diag(-1, 1, 1) in both cameras.

    R' = M R M, i.e. r' = (rx, -ry, -rz) (a reflection flips the rotation sense); t' = (-tx, ty, tz);
    cx -> 1 - cx; maps flipped left-right; flow x negated.
    """
    return _flip_sample(sample, (-1,), [MIRROR], normals)


ROTATE = ((-1.0, -1.0, 1.0), (2, 3))
"""The 180-degree turn's signs of the motion's axes and the intrinsics it mirrors (cx, cy): :func:`rotate_180`."""
MIRROR = ((-1.0, 1.0, 1.0), (2,))
"""The mirror's signs and mirrored intrinsics (cx): :func:`mirror`."""


def _flip_sample(sample: Sample, dims: tuple[int, ...], cameras: list[tuple], normals: bool = True) -> Sample:
    """``sample``'s maps flipped along ``dims`` once, and its flow, motion and intrinsics changed by each
    of ``cameras`` (:data:`ROTATE`, :data:`MIRROR`) in turn: the maps of a turn then a mirror are one
    vertical flip, each value moved exactly, while the cameras' arithmetic stays the same steps."""
    out = dict(sample)
    for key in MAP_KEYS:
        if key in sample:  # a training draw carries only what the losses read
            out[key] = sample[key].flip(dims)
    for signs, principal in cameras:
        sign = torch.tensor(signs)
        if "flow" in out:
            out["flow"] = out["flow"] * sign[:2, None, None]
        det = float(sign.prod())  # -1 for a reflection
        r, t = out["motion"][:3], out["motion"][3:]
        out["motion"] = torch.cat([det * sign * r, sign * t])
        for key in ("intrinsics", "intrinsics2"):
            k = out[key].clone()
            for i in principal:
                k[i] = 1 - k[i]
            out[key] = k
    # Like DeMoN, GT normals come from the augmented depth: its pixel stencil (right/down and
    # left/up neighbours) is not mirror-symmetric at creases, so flipping the old map would differ.
    if normals:
        out["normals"] = geo.normals_from_depth(out["inv_depth"][None], out["intrinsics"][None])[0]
    return out


AUGMENTATIONS = ((False, False), (False, True), (True, False), (True, True))
"""Every ``(rotate, mirror)`` choice of DeMoN's augmentation (:func:`augment`): a training pair is one
of its scene's four."""


def augmentation_choice(rng: np.random.Generator) -> tuple[bool, bool]:
    """The ``(rotate, mirror)`` choice of one draw of DeMoN's augmentation, each with p = 0.5."""
    rotate, flip = rng.random() < 0.5, rng.random() < 0.5
    return bool(rotate), bool(flip)


def augmented(sample: Sample, rotate: bool, flip: bool, normals: bool = True) -> Sample:
    """``sample`` turned by 180 degrees (``rotate``), then mirrored (``flip``): one of
    :data:`AUGMENTATIONS`. ``normals=False`` returns the sample without its ``normals`` map instead of
    recomputing it from the augmented depth: the training losses derive their normals from the depth
    pyramid (:class:`demon_lab.core.losses.GroundTruth`), so training skips a map nobody reads (its
    cost: docs/notes/2026-11-cpu-profile.md, "Time and memory")."""
    if rotate or flip:
        dims = (-2,) if rotate and flip else (-2, -1) if rotate else (-1,)
        sample = _flip_sample(sample, dims, [ROTATE] * rotate + [MIRROR] * flip, normals)
    if not normals:
        sample = {k: v for k, v in sample.items() if k != "normals"}
    return sample


def augment(sample: Sample, rng: np.random.Generator, normals: bool = True) -> Sample:
    """DeMoN's augmentation: 180-degree rotation and horizontal mirror, each with p = 0.5
    (:func:`augmentation_choice`, then :func:`augmented`)."""
    return augmented(sample, *augmentation_choice(rng), normals=normals)
