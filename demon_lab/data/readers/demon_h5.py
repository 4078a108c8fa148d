"""DeMoN's multi-view HDF5 files (``sun3d_test.h5``, ``mvs_test.h5``, ...; docs/reference.md §6; DeMoN's
`examples/create_dataset_and_use_readerop.py` writes this layout).

Layout: ``/<scene>/frames/t0/v<k>/{image, depth, camera}``; ``image`` is the bytes of a WebP file
(int8 array, attribute ``format="webp"``); ``depth`` is LZ4-compressed float16 absolute depth
(``format="lz4half"``, ``extents=[H, W]``, ``depth_metric`` ``camera_z`` or ``ray_length``,
0 = invalid); ``camera`` holds 17 float64 values ``[fx, fy, skew, cx, cy, R (column-major, 9),
t (3)]`` in pixels of the stored image, world-to-camera (R and t NaN where a source has no
poses). ``t0`` may carry ``viewpoint_pairs``, an int32 vector of consecutive ordered pairs.
Groups whose name starts with '.' are reserved.

:func:`write_demon_h5` writes exactly this layout (tests use it for tiny files; users can convert
their own data with it).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from demon_lab.data.readers.common import inverse, normalised_intrinsics, relative_motion
from demon_lab.data.sample import DataError, Sample, make_sample

MAX_VIEWS = 6  # DeMoN's reader loads at most 6 viewpoints per scene
UNKNOWN_MOTION = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
"""Stand-in motion while a pair without camera poses (NaN R, t: DeMoN's NYU test pairs) is prepared;
the dataset then reports its motion as NaN, and the evaluation scores depth only, with the unit
baseline DeMoN's ``evaluate`` assumes there."""


def _h5py():
    import h5py

    return h5py


def _open(path: Path):
    if not Path(path).is_file():
        raise DataError(f"{path}: file not found")
    try:
        return _h5py().File(path, "r")
    except OSError as e:
        raise DataError(f"{path}: not a readable HDF5 file ({e})") from None


def read_demon_h5_pairs(path: str | Path, test_phase: bool = True) -> list[tuple[str, int, int]]:
    """The usable ordered pairs ``(scene, a, b)`` of a file, as DeMoN's reader chooses them.

    With ``viewpoint_pairs`` the listed pairs (in test phase only the first); without it all
    ordered pairs of the first 6 views (train) or (0, 1) (test).
    """
    path = Path(path)
    with _open(path) as f:
        pairs = []
        for scene in sorted(f):
            if scene.startswith("."):
                continue
            t0 = f.get(f"{scene}/frames/t0")
            if t0 is None:
                raise DataError(f"{path}: scene {scene!r} has no frames/t0 group")
            views = sorted(int(k[1:]) for k in t0 if k.startswith("v") and k[1:].isdigit())[:MAX_VIEWS]
            if len(views) < 2:
                raise DataError(f"{path}: scene {scene!r} has fewer than 2 viewpoints")
            if "viewpoint_pairs" in t0.attrs:
                flat = np.asarray(t0.attrs["viewpoint_pairs"]).reshape(-1, 2)
                listed = [(int(a), int(b)) for a, b in flat if a in views and b in views]
            elif test_phase:
                listed = [(views[0], views[1])]
            else:
                listed = [(a, b) for a in views for b in views if a != b]
            pairs += [(scene, a, b) for a, b in (listed[:1] if test_phase else listed)]
        return pairs


def _view(path: Path, group, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One viewpoint: RGB uint8, absolute camera-z depth, pixel K, R, t (world-to-camera)."""
    missing = [k for k in ("image", "depth", "camera") if k not in group]
    if missing:
        raise DataError(f"{path}: {name} lacks the dataset(s) {', '.join(missing)}")
    image_ds, depth_ds, camera_ds = group["image"], group["depth"], group["camera"]
    raw = np.asarray(image_ds).astype(np.int8).tobytes()
    bgr = cv2.imdecode(np.frombuffer(raw, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DataError(f"{path}: {name}/image is not a decodable {image_ds.attrs.get('format', '?')} image")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    fmt = depth_ds.attrs.get("format", "lz4half")
    fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
    if fmt != "lz4half":
        raise DataError(f"{path}: {name}/depth has format {fmt!r}; only 'lz4half' is supported")
    h, w = (int(x) for x in depth_ds.attrs["extents"])
    try:
        import lz4.block

        data = lz4.block.decompress(np.asarray(depth_ds).astype(np.int8).tobytes(),
                                    uncompressed_size=h * w * 2)
    except Exception as e:  # lz4 raises its own error types for corrupt blocks
        raise DataError(f"{path}: {name}/depth is not valid LZ4 float16 data ({e})") from None
    depth = np.frombuffer(data, dtype=np.float16).reshape(h, w).astype(np.float64)
    cam = np.asarray(camera_ds, dtype=np.float64).reshape(-1)
    if cam.size != 17:
        raise DataError(f"{path}: {name}/camera has {cam.size} values, expected 17")
    fx, fy, skew, cx, cy = cam[:5]
    if skew != 0:
        raise DataError(f"{path}: {name}/camera has skew {skew}; only skew 0 is supported")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    R = cam[5:14].reshape(3, 3).T  # stored column-major
    t = cam[14:17]
    metric = depth_ds.attrs.get("depth_metric", "camera_z")
    metric = metric.decode() if isinstance(metric, bytes) else metric
    if metric == "ray_length":
        # camera z = ray length / |K^-1 (x + 0.5, y + 0.5, 1)|
        xs = ((np.arange(w) + 0.5) * rgb.shape[1] / w - cx) / fx
        ys = ((np.arange(h) + 0.5) * rgb.shape[0] / h - cy) / fy
        depth = depth / np.sqrt(xs[None] ** 2 + ys[:, None] ** 2 + 1)
    elif metric != "camera_z":
        raise DataError(f"{path}: {name}/depth has depth_metric {metric!r}")
    return rgb, depth, K, R, t


def load_demon_h5_pair(f, path: Path, scene: str, a: int, b: int, derived: bool = True) -> Sample:
    """The sample of pair (a, b) of ``scene`` from an open file ``f`` (native resolution);
    ``derived=False``: without flow, normals and masks (``make_sample``)."""
    views = []
    for k in (a, b):
        name = f"{scene}/frames/t0/v{k}"
        if name not in f:
            raise DataError(f"{path}: {name} not found")
        views.append(_view(path, f[name], name))
    (im1, d1, K1, R1, t1), (im2, d2, K2, R2, t2) = views
    height, width = im1.shape[:2]
    if im2.shape != im1.shape:
        raise DataError(f"{path}: {scene} views {a} and {b} have different image sizes")
    if d1.shape != (height, width):
        # DeMoN stores depth at the image resolution; resize nearest if not.
        d1 = cv2.resize(d1, (width, height), interpolation=cv2.INTER_NEAREST)
        d2 = cv2.resize(d2, (width, height), interpolation=cv2.INTER_NEAREST)
    motion = relative_motion(R1, t1, R2, t2) if np.isfinite(np.concatenate([R1.ravel(), t1, R2.ravel(), t2])).all() \
        else None
    sample = make_sample(
        f"{path.stem}/{scene}/frames/t0/v{a},v{b}", im1, im2,
        normalised_intrinsics(K1, width, height), inverse(d1), UNKNOWN_MOTION if motion is None else motion,
        intrinsics2=normalised_intrinsics(K2, width, height), inv_depth2=inverse(d2), derived=derived,
    )
    if motion is None:
        sample["motion_unknown"] = True  # the dataset reports NaN motion and flow (DeMoN's nyu2_test.h5)
    return sample


def write_demon_h5(path: str | Path, scenes: Iterable[dict], webp_quality: int = 90) -> None:
    """Write scenes in DeMoN's layout.

    Each scene is a dict: ``name``; ``views``, a list of dicts with ``image`` (H, W, 3) uint8 RGB,
    ``depth`` (H, W) absolute camera-z depth (0 = invalid), ``K`` (3, 3) pixel intrinsics, ``R``
    (3, 3) and ``t`` (3,) world-to-camera; optional ``viewpoint_pairs`` (list of (a, b)).
    """
    import lz4.block

    with _h5py().File(path, "w") as f:
        for scene in scenes:
            t0 = f.create_group(f"{scene['name']}/frames/t0")
            if "viewpoint_pairs" in scene:
                t0.attrs["viewpoint_pairs"] = np.asarray(scene["viewpoint_pairs"], dtype=np.int32).reshape(-1)
            for k, view in enumerate(scene["views"]):
                g = t0.create_group(f"v{k}")
                ok, webp = cv2.imencode(".webp", cv2.cvtColor(view["image"], cv2.COLOR_RGB2BGR),
                                        [cv2.IMWRITE_WEBP_QUALITY, webp_quality])
                if not ok:
                    raise DataError(f"{path}: could not encode view {k} of {scene['name']} as WebP")
                img = g.create_dataset("image", data=np.frombuffer(webp.tobytes(), dtype=np.int8))
                img.attrs["format"] = "webp"
                depth = np.asarray(view["depth"], dtype=np.float16)
                packed = lz4.block.compress(depth.tobytes(), mode="high_compression", store_size=False)
                d = g.create_dataset("depth", data=np.frombuffer(packed, dtype=np.int8))
                d.attrs["format"] = "lz4half"
                d.attrs["extents"] = np.asarray(depth.shape, dtype=np.int32)
                d.attrs["depth_metric"] = view.get("depth_metric", "camera_z")
                K, R, t = (np.asarray(view[x], dtype=np.float64) for x in ("K", "R", "t"))
                camera = np.concatenate([[K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]],
                                         R.T.reshape(-1), t])
                c = g.create_dataset("camera", data=camera)
                c.attrs["format"] = "pinhole"
