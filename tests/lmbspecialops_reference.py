"""lmbspecialops' kernels as DeMoN's v1 graph calls them, transcribed loop by loop in numpy from
their C++ sources (`src/warp2d.cc`, `src/depthtoflow.cc`, `src/flowtodepth.cc`,
`src/rotation_format.h` of lmbspecialops, the op library DeMoN's released code builds), in float32
as the kernels compute for float inputs. NCHW arrays; DeMoN's IterativeNet intrinsics. The tests
compare demon_lab's geometry (``model.compat=demon_original``) with these.
"""

from __future__ import annotations

import numpy as np

INTRINSICS = np.array([0.89115971, 1.18821287, 0.5, 0.5], dtype=np.float32)  # IterativeNet's constant


def warp2d(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """src/warp2d.cc, normalized=True, border_mode='value', border_value=0."""
    n, ch, h, w = image.shape
    out = np.zeros_like(image, dtype=np.float32)
    f32 = np.float32
    for b in range(n):
        for y in range(h):
            for x in range(w):
                vx, vy = f32(flow[b, 0, y, x]) * f32(w), f32(flow[b, 1, y, x]) * f32(h)
                px, py = f32(x) + vx, f32(y) + vy
                if not (np.isfinite(px) and np.isfinite(py)) or abs(px) > 2**30 or abs(py) > 2**30:
                    continue  # the int cast of these is undefined; it lands outside in practice
                x0, y0 = int(px), int(py)  # truncation toward zero, as Eigen's cast<int>
                a, bb = f32(px - f32(x0)), f32(py - f32(y0))
                x3, y3 = x0 + 1, y0 + 1
                if x0 >= 0 and x3 > 0 and x3 < w and y0 >= 0 and y3 > 0 and y3 < h:
                    wts = ((1 - a) * (1 - bb), a * (1 - bb), (1 - a) * bb, a * bb)
                    for c in range(ch):
                        vals = (image[b, c, y0, x0], image[b, c, y0, x3], image[b, c, y3, x0], image[b, c, y3, x3])
                        out[b, c, y, x] = sum(f32(v) * f32(wt) for v, wt in zip(vals, wts))
    return out


def rotation_matrix(r: np.ndarray) -> np.ndarray:
    """rotation_format.h ANGLEAXIS3: Eigen's AngleAxis, identity below 1e-6 rad."""
    r = r.astype(np.float64)
    angle = np.linalg.norm(r)
    if angle <= 1e-6:
        return np.eye(3)
    k = r / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def depth_to_flow(inv_depth: np.ndarray, rotation, translation) -> np.ndarray:
    """src/depthtoflow.cc, inverse_depth=True, normalize_flow=True (vectorised over pixels)."""
    rotation, translation = np.asarray(rotation), np.asarray(translation)
    n, _, h, w = inv_depth.shape
    out = np.empty((n, 2, h, w), np.float32)
    fx, fy, cx, cy = INTRINSICS[0] * w, INTRINSICS[1] * h, INTRINSICS[2] * w, INTRINSICS[3] * h
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    for b in range(n):
        with np.errstate(divide="ignore", invalid="ignore"):
            d = (1 / inv_depth[b, 0]).astype(np.float32)
            R = rotation_matrix(rotation[b]).astype(np.float32)
            ray = np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)]).astype(np.float32)
            p2 = np.einsum("ij,jhw->ihw", R, d * ray) + translation[b].astype(np.float32)[:, None, None]
            u = fx * (p2[0] / p2[2]) + cx
            v = fy * (p2[1] / p2[2]) + cy
            flow = np.stack([(u - xs) / w, (v - ys) / h])
        ok = (d > 0) & np.isfinite(d)
        out[b] = np.where(ok, flow, np.nan)
    return out


def flow_to_depth(flow: np.ndarray, rotation, translation, dtype=np.float64) -> np.ndarray:
    """src/flowtodepth.cc, normalized_flow=True, inverse_depth=True: linear triangulation of
    the two rays, solved by SVD (least squares) per pixel. The kernel solves in float32 with
    Eigen's JacobiSVD; ``dtype=np.float64`` gives the exact least-squares solution that both it
    and demon_lab (float64 normal equations) approximate, so a comparison of whole chains is not
    dominated by float32 rounding at ill-conditioned pixels."""
    rotation, translation = np.asarray(rotation), np.asarray(translation)
    n, _, h, w = flow.shape
    out = np.zeros((n, 1, h, w), np.float32)
    K = np.array([[INTRINSICS[0], 0, INTRINSICS[2]], [0, INTRINSICS[1], INTRINSICS[3]], [0, 0, 1]], dtype)
    for b in range(n):
        P1 = np.concatenate([K, np.zeros((3, 1), dtype)], 1)
        P2 = K @ np.concatenate([rotation_matrix(rotation[b]).astype(dtype), translation[b].astype(dtype)[:, None]], 1)
        for y in range(h):
            for x in range(w):
                x1 = np.array([(x + 0.5) / w, (y + 0.5) / h], dtype)
                x2 = x1 + flow[b, :, y, x].astype(dtype)
                rows, rhs = [], []
                for P, (u, v) in ((P1, x1), (P2, x2)):
                    rows += [v * P[2, :3] - P[1, :3], P[0, :3] - u * P[2, :3]]
                    rhs += [P[1, 3] - v * P[2, 3], u * P[2, 3] - P[0, 3]]
                A, r = np.array(rows, dtype), np.array(rhs, dtype)
                if not (np.isfinite(A).all() and np.isfinite(r).all()):
                    continue
                X = np.linalg.lstsq(A, r, rcond=None)[0]
                if np.isfinite(X).all() and X[2] > 0:
                    out[b, 0, y, x] = 1 / X[2]
    return out
