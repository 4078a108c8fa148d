"""Two-view geometry for the classical baselines: dense flow, forward-backward filtering, the
normalised 8-point algorithm inside RANSAC, pose from the essential matrix, dense depth.

Conventions follow demon_lab.core.geometry: motion ``[r, t]`` with ``X2 = R X1 + t``; intrinsics are
normalised ``(fx, fy, cx, cy)`` with pixel centres at ``(x + 0.5) / W``. OpenCV works in pixel
indices, so :func:`pixel_intrinsics` shifts the principal point by half a pixel. The geometry takes
one camera matrix, view 1's: view-2 points are first mapped to view 1's camera
(:func:`view1_pixels`), so pairs whose views have intrinsics of their own are exact too.

Pixel thresholds are given for a 256-pixel-wide image (the network's paper resolution) and scale
linearly with the width of the image they are applied to (:func:`scaled_threshold`).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from demon_lab.core import geometry as geo

REFERENCE_WIDTH = 256


class BaselineFailure(RuntimeError):
    """A baseline could not produce an estimate for a sample (e.g. too few matches).

    Recorded as that sample's failure and counted in reports; never a crash of the job."""


def scaled_threshold(pixels_at_256: float, width: int) -> float:
    return float(pixels_at_256) * width / REFERENCE_WIDTH


def pixel_intrinsics(intrinsics: np.ndarray | torch.Tensor, height: int, width: int) -> np.ndarray:
    """3x3 pixel-index camera matrix from normalised intrinsics."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(intrinsics, dtype=np.float64))
    return np.array([[fx * width, 0.0, cx * width - 0.5], [0.0, fy * height, cy * height - 0.5], [0.0, 0.0, 1.0]])


def view1_pixels(points: np.ndarray, intrinsics, intrinsics2, height: int, width: int) -> np.ndarray:
    """View-2 pixel points (..., 2) where view 1's camera would image the same rays: K1 K2^-1 x.

    OpenCV's ``findEssentialMat`` and ``recoverPose`` take one camera matrix; the Middlebury pair's
    principal points differ by 31 pixels and DeMoN's MVS pairs come from different cameras.
    """
    k1, k2 = (np.asarray(k, dtype=np.float64) for k in (intrinsics, intrinsics2))
    if np.array_equal(k1, k2):
        return points  # one camera: the points as they are, to the last bit
    A = pixel_intrinsics(k1, height, width) @ np.linalg.inv(pixel_intrinsics(k2, height, width))
    return points @ A[:2, :2].T + A[:2, 2]


def to_gray_u8(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) image in [-0.5, 0.5] -> (H, W) uint8 grey."""
    rgb = ((image.permute(1, 2, 0).numpy() + 0.5) * 255).clip(0, 255).astype(np.uint8)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def dense_flow(gray1: np.ndarray, gray2: np.ndarray, preset: str = "medium", finest_scale: int = 0,
               iterations: int = 25) -> np.ndarray:
    """OpenCV DIS optical flow (the stand-in for FlowFields) in pixels, (H, W, 2).

    ``finest_scale`` 0 (full resolution) and more gradient-descent iterations than the preset's
    matter on small images: at 128x96 they halve the median error on large displacements.
    """
    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    dis = cv2.DISOpticalFlow_create(presets[preset])
    dis.setFinestScale(int(finest_scale))
    dis.setGradientDescentIterations(int(iterations))
    return dis.calc(gray1, gray2, None)


def forward_backward_mask(forward: np.ndarray, backward: np.ndarray, threshold: float) -> np.ndarray:
    """Pixels whose forward flow, followed by the backward flow at its end point, returns within
    ``threshold`` pixels, and whose end point lies inside image 2."""
    h, w = forward.shape[:2]
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x2, y2 = xs + forward[..., 0], ys + forward[..., 1]
    back = cv2.remap(backward, x2, y2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    error = np.hypot(forward[..., 0] + back[..., 0], forward[..., 1] + back[..., 1])
    inside = (x2 >= 0) & (x2 <= w - 1) & (y2 >= 0) & (y2 <= h - 1)
    return inside & np.isfinite(error) & (error < threshold)


def _hartley(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hartley normalisation of (..., N, 2) points: centroid at 0, mean distance sqrt(2)."""
    centre = points.mean(-2, keepdims=True)
    d = np.linalg.norm(points - centre, axis=-1).mean(-1)
    s = np.sqrt(2) / np.maximum(d, 1e-12)
    T = np.zeros((*points.shape[:-2], 3, 3))
    T[..., 0, 0] = T[..., 1, 1] = s
    T[..., 0, 2] = -s * centre[..., 0, 0]
    T[..., 1, 2] = -s * centre[..., 0, 1]
    T[..., 2, 2] = 1.0
    homogeneous = np.concatenate([points, np.ones((*points.shape[:-1], 1))], -1)
    return np.einsum("...ij,...nj->...ni", T, homogeneous), T


def eight_point(x1: np.ndarray, x2: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Normalised 8-point fundamental matrices (Hartley): x2^T F x1 = 0, rank 2.

    ``x1``, ``x2``: (..., N, 2) pixel points with N >= 8; batched over leading dimensions.
    ``weights`` (N,) scale the rows of the linear system (the re-weighted refit of
    :func:`ransac_fundamental`).
    """
    p1, T1 = _hartley(x1)
    p2, T2 = _hartley(x2)
    A = np.einsum("...ni,...nj->...nij", p2, p1).reshape(*p1.shape[:-1], 9)
    if weights is not None:
        A = A * weights[..., None]
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    F = vt[..., -1, :].reshape(*A.shape[:-2], 3, 3)
    u, s, vt = np.linalg.svd(F)
    s[..., 2] = 0.0
    F = u @ (s[..., :, None] * vt)
    F = np.swapaxes(T2, -1, -2) @ F @ T1
    return F / np.maximum(np.linalg.norm(F, axis=(-2, -1), keepdims=True), 1e-12)


def _sampson_weights(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """1 / (gradient norm of the epipolar residual): turns the algebraic residual of the 8-point
    system into the Sampson distance (iteratively re-weighted least squares)."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], 1)
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return 1.0 / np.sqrt(np.maximum(den, 1e-30))


def sampson_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error (pixels) of correspondences under F; F (..., 3, 3), x (N, 2)."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], 1)
    Fx1 = np.einsum("...ij,nj->...ni", F, h1)
    Ftx2 = np.einsum("...ji,nj->...ni", F, h2)
    num = np.einsum("ni,...ni->...n", h2, Fx1) ** 2
    den = Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


def ransac_fundamental(x1: np.ndarray, x2: np.ndarray, threshold: float, iterations: int = 1000,
                       seed: int = 0, min_inliers: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The 8-point algorithm in a RANSAC loop (OpenCV's ``FM_RANSAC`` samples 7 points).

    Hypotheses from random 8-point samples (all evaluated at once), scored by the number of
    correspondences with Sampson distance below ``threshold`` pixels; the best is re-fitted on
    its inliers with the 8-point system re-weighted to approximate the Sampson error (up to three
    times, while the support stays within 5 %; the unweighted algebraic fit costs degrees of
    translation). Returns F and the inlier mask; raises BaselineFailure when fewer than
    ``min_inliers`` points support any hypothesis.
    """
    n = len(x1)
    if n < 8:
        raise BaselineFailure(f"only {n} correspondences (the 8-point algorithm needs 8)")
    rng = np.random.default_rng(seed)
    samples = np.argsort(rng.random((iterations, n)), axis=1)[:, :8] if n < 64 else rng.integers(0, n, (iterations, 8))
    with np.errstate(all="ignore"):
        F = eight_point(x1[samples], x2[samples])
        counts = (sampson_distance(F, x1, x2) < threshold).sum(-1)
    best = int(np.argmax(counts))
    F_best = F[best]
    inliers = sampson_distance(F_best, x1, x2) < threshold
    for _ in range(3):  # re-fit on the inliers, Sampson-weighted
        if inliers.sum() < min_inliers:
            break
        with np.errstate(all="ignore"):
            # Fit on the tighter half of the threshold band: chance outliers that sit within the
            # band of their epipolar line pull an algebraic fit by degrees.
            core = sampson_distance(F_best, x1, x2) < threshold / 2
            fit = core if core.sum() >= max(min_inliers, inliers.sum() // 2) else inliers
            weights = _sampson_weights(F_best, x1[fit], x2[fit])
            weights = np.minimum(weights, 3 * np.median(weights))  # no point dominates the fit
            F_refit = eight_point(x1[fit], x2[fit], weights / weights.max())
            refit_inliers = sampson_distance(F_refit, x1, x2) < threshold
        # A least-squares fit on the inliers beats the minimal sample's even at a slightly lower
        # count; a clearly smaller support means the refit went astray.
        if not np.isfinite(F_refit).all() or refit_inliers.sum() < 0.95 * inliers.sum():
            break
        F_best, inliers = F_refit, refit_inliers
    if inliers.sum() < min_inliers:
        raise BaselineFailure(f"RANSAC found {int(inliers.sum())} inliers of {n} (needs {min_inliers})")
    return F_best, inliers


def ransac_essential(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold: float, min_inliers: int = 8,
                     seed: int = 0, attempts: int = 3, method: int = cv2.RANSAC) -> tuple[np.ndarray, np.ndarray]:
    """Nister's 5-point algorithm in RANSAC (OpenCV's ``findEssentialMat``, confidence 0.999):
    E and the inlier mask for pixel points of one camera ``K``, ``threshold`` in pixels.
    ``method=cv2.LMEDS``: in least median of squares instead (``threshold`` unused).

    OpenCV draws its samples from a fixed generator. Its solver aborts the whole run on some
    degenerate minimal samples (an assertion in OpenCV 5's ``solvePoly``); the run is then repeated
    on the correspondences in another order (drawn from ``seed``), which draws other samples, up to
    ``attempts`` runs in all. Raises BaselineFailure without a unique E, with fewer than
    ``min_inliers`` inliers, or when every run aborts.
    """
    n = len(x1)
    what = "RANSAC" if method == cv2.RANSAC else "least median of squares"
    if n < 5:
        raise BaselineFailure(f"only {n} correspondences (the 5-point algorithm needs 5)")
    rng = np.random.default_rng(seed)
    order = np.arange(n)
    for attempt in range(attempts):
        try:
            E, mask = cv2.findEssentialMat(x1[order].astype(np.float64), x2[order].astype(np.float64), K,
                                           method=method, prob=0.999, threshold=float(threshold))
            break
        except cv2.error as e:
            if attempt == attempts - 1:
                raise BaselineFailure(f"OpenCV's 5-point {what} aborted {attempts} times: "
                                      f"{str(e).strip().splitlines()[-1]}") from e
            order = rng.permutation(n)
    if E is None or E.shape != (3, 3):
        raise BaselineFailure(f"the 5-point {what} found no (unique) essential matrix")
    inliers = np.zeros(n, bool)
    inliers[order] = mask[:, 0].astype(bool)
    if inliers.sum() < min_inliers:
        raise BaselineFailure(f"the 5-point {what} kept {int(inliers.sum())} inliers (needs {min_inliers})")
    return E, inliers


def pose_from_essential(E: np.ndarray, x1: np.ndarray, x2: np.ndarray, K: np.ndarray,
                        mask: np.ndarray | None = None) -> np.ndarray:
    """Motion ``[r, t]`` (6,), unit t, from an essential matrix by OpenCV's cheirality check."""
    m = None if mask is None else mask.astype(np.uint8)[:, None]
    count, R, t, _ = cv2.recoverPose(E, x1.astype(np.float64), x2.astype(np.float64), K, mask=m)
    if count == 0:
        raise BaselineFailure("no correspondence in front of both cameras for any pose of E")
    r = geo.matrix_to_angle_axis(torch.from_numpy(R)[None])[0].numpy()
    t = t[:, 0] / max(np.linalg.norm(t), 1e-12)
    return np.concatenate([r, t])


def motion_from_fundamental(F: np.ndarray, x1: np.ndarray, x2: np.ndarray, K: np.ndarray,
                            inliers: np.ndarray) -> np.ndarray:
    E = K.T @ F @ K
    return pose_from_essential(E, x1, x2, K, inliers)


def depth_from_pixel_flow(flow_px: np.ndarray, mask: np.ndarray, motion: np.ndarray,
                          intrinsics: np.ndarray | torch.Tensor) -> np.ndarray:
    """Dense inverse depth (unit-length t) by triangulating a pixel flow with a motion.

    Pixels outside ``mask``, behind a camera or at a vanishing triangulation angle are filled
    from their nearest triangulated neighbour (so the method is scored on every pixel, like the
    networks); raises BaselineFailure when no pixel triangulates.
    """
    from scipy import ndimage

    h, w = flow_px.shape[:2]
    flow = torch.from_numpy(np.stack([flow_px[..., 0] / w, flow_px[..., 1] / h]).astype(np.float64))[None]
    k = torch.as_tensor(np.asarray(intrinsics, dtype=np.float64))[None]
    inv = geo.depth_from_flow_motion(flow, torch.from_numpy(motion.astype(np.float64))[None], k)[0, 0].numpy()
    good = mask & np.isfinite(inv) & (inv > 0)
    if not good.any():
        raise BaselineFailure("no pixel triangulates in front of both cameras")
    _, (iy, ix) = ndimage.distance_transform_edt(~good, return_indices=True)
    return inv[iy, ix]
