"""The paper's classical baselines (supplementary section F; main paper Table 2).

Each method maps one sample (an image pair with intrinsics, as ``demon_lab.data`` produces it) to
``{"inv_depth": (h, w), "motion": (6,)}`` (inverse depth for a unit-length translation) and is
scored by ``demon_lab.core.metrics.evaluate_sample`` exactly like the networks:

* ``base_ff`` — dense DIS flow (OpenCV; the stand-in for FlowFields), forward-backward filtering,
  normalised 8-point in RANSAC, pose from the essential matrix, depth by triangulating the flow;
* ``base_sift`` — SIFT matches with the ratio test, 8-point in RANSAC, depth as ``base_ff``;
* ``base_5pt`` — the same SIFT matches, Nister's 5-point in RANSAC (``cv2.findEssentialMat``,
  1-pixel threshold), depth as ``base_ff``: a classical reference stronger than the paper's;
* ``base_mat_f`` — Nister's 5-point in RANSAC (``cv2.findEssentialMat``) on the flow predicted by
  the trained DeMoN chain, depth by triangulating that flow;
* ``base_oracle`` — ground-truth motion and plane-sweep stereo.

Each view's own intrinsics are used: view-2 points are brought to view 1's camera before the
geometry, which takes one. ``demon_lab.pipeline.evaluate`` gives the methods each pair at ``baseline.size``
(by default the source's own resolution, whatever the network reads: the paper's baselines ran at
640x480 where DeMoN read 256x192).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from demon_lab.baselines.twoview import (
    BaselineFailure,
    dense_flow,
    depth_from_pixel_flow,
    forward_backward_mask,
    motion_from_fundamental,
    pixel_intrinsics,
    pose_from_essential,
    ransac_essential,
    ransac_fundamental,
    scaled_threshold,
    to_gray_u8,
    view1_pixels,
)
from demon_lab.core import geometry as geo
from demon_lab.core import warping

METHODS = ("base_ff", "base_sift", "base_5pt", "base_mat_f", "base_oracle")

FIVE_POINT_THRESHOLD_PX = 1.0
"""Base-5pt's RANSAC threshold in pixels of the image it reads, at any size: SIFT locates a keypoint
to about a pixel whatever the resolution (docs/notes/2026-12-baselines-own-camera.md measures 2.5 pixels,
the 8-point methods' threshold at 640x480, against it)."""


@dataclass(frozen=True)
class BaselineConfig:
    """Parameters of the baselines; pixel values at width 256. Their defaults are written once, in
    ``conf/baseline/default.yaml`` (:meth:`default`); a value out of its range is a ValueError naming
    the key (``baseline.KEY: ...``, the job's one line)."""

    dis_preset: str
    dis_finest_scale: int
    dis_iterations: int
    fb_threshold_px: float
    ransac_threshold_px: float
    ransac_iterations: int
    max_correspondences: int
    sift_ratio: float
    min_matches: int
    sweep_hypotheses: int
    sweep_window: int
    sweep_max_disparity: float
    size: Any  # "native" or [H, W]: the resolution the pairs are read at (demon_lab.pipeline.evaluate reads them)
    seed: int = 0  # the job's seed (RANSAC's and the correspondences' draws)

    @classmethod
    def default(cls, **values: Any) -> BaselineConfig:
        """The defaults of ``conf/baseline/default.yaml``, with ``values`` instead where given."""
        from omegaconf import OmegaConf

        from demon_lab.resources import CONF

        return cls(**{**OmegaConf.to_container(OmegaConf.load(CONF / "baseline" / "default.yaml")), **values})

    def __post_init__(self) -> None:
        def integer(key: str, minimum: int) -> int:
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
                raise ValueError(f"baseline.{key}: expected an integer >= {minimum}, got {value!r}")
            return value

        if self.dis_preset not in DIS_PRESETS:
            raise ValueError(f"baseline.dis_preset: expected one of {', '.join(DIS_PRESETS)}, got {self.dis_preset!r}")
        for key in ("fb_threshold_px", "ransac_threshold_px", "sift_ratio", "sweep_max_disparity"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
                raise ValueError(f"baseline.{key}: expected a positive number, got {value!r}")
        if self.sift_ratio >= 1:
            raise ValueError(f"baseline.sift_ratio: expected a number in (0, 1), got {self.sift_ratio}")
        for key, minimum in (("dis_finest_scale", 0), ("dis_iterations", 1), ("ransac_iterations", 1),
                             ("max_correspondences", 8), ("min_matches", 8), ("sweep_hypotheses", 2)):
            integer(key, minimum)
        size = self.size
        if size != "native" and not (isinstance(size, list | tuple) and len(size) == 2
                                     and all(isinstance(v, int) and not isinstance(v, bool) and v >= 32 for v in size)):
            raise ValueError(f"baseline.size: expected native or [H, W] with sides >= 32 pixels, got {size}")
        if integer("sweep_window", 1) % 2 == 0:
            raise ValueError(f"baseline.sweep_window: expected an odd integer, got {self.sweep_window}")


DIS_PRESETS = ("ultrafast", "fast", "medium")
"""OpenCV's DIS optical flow presets (``baseline.dis_preset``)."""


def _subsample(n: int, limit: int, seed: int) -> np.ndarray:
    if n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, limit, replace=False))


def _in_view1(points: np.ndarray, sample: Mapping[str, Any], height: int, width: int) -> np.ndarray:
    """View-2 pixel points brought to view 1's camera (a sample without ``intrinsics2`` has one camera)."""
    return view1_pixels(points, sample["intrinsics"], sample.get("intrinsics2", sample["intrinsics"]), height, width)


def _flow_in_view1(flow_px: np.ndarray, sample: Mapping[str, Any]) -> np.ndarray:
    """A (H, W, 2) pixel flow whose end points are brought to view 1's camera (with one camera: the
    flow itself, to the last bit)."""
    h, w = flow_px.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
    end = grid + flow_px
    moved = _in_view1(end, sample, h, w)
    return flow_px if moved is end else moved - grid


def _consistent_flow(g1: np.ndarray, g2: np.ndarray, sample: Mapping[str, Any],
                     cfg: BaselineConfig) -> tuple[np.ndarray, np.ndarray]:
    """DIS flow in pixels (end points in view 1's camera) and its forward-backward consistent pixels."""
    args = (cfg.dis_preset, cfg.dis_finest_scale, cfg.dis_iterations)
    forward, backward = dense_flow(g1, g2, *args), dense_flow(g2, g1, *args)
    mask = forward_backward_mask(forward, backward, scaled_threshold(cfg.fb_threshold_px, g1.shape[1]))
    return _flow_in_view1(forward, sample), mask


def _sift_matches(g1: np.ndarray, g2: np.ndarray, sample: Mapping[str, Any],
                  cfg: BaselineConfig) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches that pass Lowe's ratio test, in pixels (view 2's in view 1's camera)."""
    sift = cv2.SIFT_create()
    k1, d1 = sift.detectAndCompute(g1, None)
    k2, d2 = sift.detectAndCompute(g2, None)
    if d1 is None or d2 is None or len(k1) < 2 or len(k2) < 2:
        raise BaselineFailure(f"too few SIFT keypoints ({len(k1)}, {len(k2)})")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < cfg.sift_ratio * p[1].distance]
    if len(good) < cfg.min_matches:
        raise BaselineFailure(f"{len(good)} SIFT matches pass the ratio test (needs {cfg.min_matches})")
    x1 = np.array([k1[m.queryIdx].pt for m in good], dtype=np.float64)
    x2 = np.array([k2[m.trainIdx].pt for m in good], dtype=np.float64)
    return x1, _in_view1(x2, sample, *g1.shape)


def _pose_8point(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold: float,
                 cfg: BaselineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Motion and inliers by the 8-point algorithm in RANSAC, then E = K^T F K (Base-FF, Base-SIFT)."""
    Fm, inliers = ransac_fundamental(x1, x2, threshold, cfg.ransac_iterations, cfg.seed, cfg.min_matches)
    return motion_from_fundamental(Fm, x1, x2, K, inliers), inliers


def _pose_5point(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold: float,
                 cfg: BaselineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Motion and inliers by the 5-point algorithm in RANSAC (Base-5pt, Base-Mat-F)."""
    E, inliers = ransac_essential(x1, x2, K, threshold, cfg.min_matches, cfg.seed)
    return pose_from_essential(E, x1, x2, K, inliers), inliers


def base_ff(sample: Mapping[str, Any], cfg: BaselineConfig) -> dict[str, np.ndarray]:
    g1, g2 = to_gray_u8(sample["image1"]), to_gray_u8(sample["image2"])
    h, w = g1.shape
    flow, mask = _consistent_flow(g1, g2, sample, cfg)
    ys, xs = np.nonzero(mask)
    if len(xs) < cfg.min_matches:
        raise BaselineFailure(f"{len(xs)} forward-backward consistent pixels (needs {cfg.min_matches})")
    pick = _subsample(len(xs), cfg.max_correspondences, cfg.seed)
    x1 = np.stack([xs[pick], ys[pick]], 1).astype(np.float64)
    x2 = x1 + flow[ys[pick], xs[pick]].astype(np.float64)
    K = pixel_intrinsics(sample["intrinsics"], h, w)
    motion, inliers = _pose_8point(x1, x2, K, scaled_threshold(cfg.ransac_threshold_px, w), cfg)
    return {"inv_depth": depth_from_pixel_flow(flow, mask, motion, sample["intrinsics"]), "motion": motion,
            "support": np.array(float(inliers.sum()))}


def _sift_method(sample: Mapping[str, Any], cfg: BaselineConfig, pose, threshold: float) -> dict[str, np.ndarray]:
    """SIFT matches, motion by ``pose`` with a RANSAC ``threshold`` in pixels, depth by triangulating
    the DIS flow (Base-SIFT, Base-5pt)."""
    g1, g2 = to_gray_u8(sample["image1"]), to_gray_u8(sample["image2"])
    h, w = g1.shape
    x1, x2 = _sift_matches(g1, g2, sample, cfg)
    K = pixel_intrinsics(sample["intrinsics"], h, w)
    motion, inliers = pose(x1, x2, K, threshold, cfg)
    flow, mask = _consistent_flow(g1, g2, sample, cfg)
    return {"inv_depth": depth_from_pixel_flow(flow, mask, motion, sample["intrinsics"]), "motion": motion,
            "support": np.array(float(inliers.sum()))}


def base_sift(sample: Mapping[str, Any], cfg: BaselineConfig) -> dict[str, np.ndarray]:
    threshold = scaled_threshold(cfg.ransac_threshold_px, sample["image1"].shape[-1])
    return _sift_method(sample, cfg, _pose_8point, threshold)


def base_5pt(sample: Mapping[str, Any], cfg: BaselineConfig) -> dict[str, np.ndarray]:
    return _sift_method(sample, cfg, _pose_5point, FIVE_POINT_THRESHOLD_PX)


def base_mat_f(sample: Mapping[str, Any], cfg: BaselineConfig, flow: torch.Tensor) -> dict[str, np.ndarray]:
    """``flow``: (2, h, w) normalised flow predicted by the DeMoN chain for this sample."""
    f = flow.detach().double().cpu().numpy()
    _, h, w = f.shape
    flow_px = _flow_in_view1(np.stack([f[0] * w, f[1] * h], -1), sample)
    valid = np.isfinite(flow_px).all(-1)
    ys, xs = np.nonzero(valid)
    if len(xs) < cfg.min_matches:
        raise BaselineFailure(f"{len(xs)} finite flow vectors (needs {cfg.min_matches})")
    x1 = np.stack([xs, ys], 1).astype(np.float64)
    x2 = x1 + flow_px[ys, xs]
    K = pixel_intrinsics(sample["intrinsics"], h, w)
    motion, inliers = _pose_5point(x1, x2, K, scaled_threshold(cfg.ransac_threshold_px, w), cfg)
    return {"inv_depth": depth_from_pixel_flow(flow_px, valid, motion, sample["intrinsics"]), "motion": motion,
            "support": np.array(float(inliers.sum()))}


def plane_sweep(image1: torch.Tensor, image2: torch.Tensor, intrinsics: torch.Tensor, motion: torch.Tensor,
                hypotheses: int = 160, window: int = 7, max_disparity: float = 0.6,
                intrinsics2: torch.Tensor | None = None) -> torch.Tensor:
    """Fronto-parallel plane-sweep stereo with a known motion; returns inverse depth (H, W).

    ``intrinsics2``: view 2's (default: view 1's).

    Hypotheses are uniform in inverse depth (unit-length t) between the values whose induced
    parallax has a median of one pixel and ``max_disparity`` of the image size; the cost is the window-averaged absolute
    colour difference between image 1 and image 2 warped by each hypothesis (pixels warped from
    outside image 2 cost the most); the arg-min is refined by a parabola through its neighbours.
    """
    _, h, w = image1.shape
    k, m = intrinsics[None].double(), motion[None].double()
    k2 = k if intrinsics2 is None else intrinsics2[None].double()
    delta = 1e-4  # parallax is linear in small inverse depths: measure its rate there
    at_infinity = geo.flow_from_depth_motion(torch.full((1, 1, h, w), 1e-12, dtype=torch.float64), m, k, k2)
    at_delta = geo.flow_from_depth_motion(torch.full((1, 1, h, w), delta, dtype=torch.float64), m, k, k2)
    shift = ((at_delta - at_infinity).norm(dim=1).median() / delta).item()  # normalised flow per unit xi
    if not np.isfinite(shift) or shift < 1e-9:
        raise BaselineFailure("the motion induces no parallax (zero baseline)")
    xi = torch.linspace(1.0 / max(w, h) / shift, max_disparity / shift, hypotheses, dtype=torch.float64)
    costs = []
    for chunk in xi.split(16):
        n = len(chunk)
        inv = chunk.view(n, 1, 1, 1).expand(n, 1, h, w)
        flow = geo.flow_from_depth_motion(inv, m.expand(n, 6), k.expand(n, 4), k2.expand(n, 4)).float()
        warped = warping.warp_image(image2[None].expand(n, -1, -1, -1).float(), flow)
        inside = (warped != 0).any(1, keepdim=True)
        diff = (warped - image1[None].float()).abs().mean(1, keepdim=True)
        diff = torch.where(inside, diff, torch.ones_like(diff))
        costs.append(F.avg_pool2d(diff, window, stride=1, padding=window // 2, count_include_pad=False)[:, 0])
    cost = torch.cat(costs)  # (hypotheses, H, W)
    best = cost.argmin(0)
    lo, hi = (best - 1).clamp(min=0), (best + 1).clamp(max=hypotheses - 1)
    c0, c1, c2 = (cost.gather(0, i[None])[0] for i in (lo, best, hi))
    denom = c0 - 2 * c1 + c2
    offset = torch.where((denom > 1e-9) & (lo < best) & (best < hi), 0.5 * (c0 - c2) / denom.clamp(min=1e-9),
                         torch.zeros_like(c1)).clamp(-0.5, 0.5)
    step = float(xi[1] - xi[0]) if hypotheses > 1 else float(xi[0])
    return (xi[best].float() + offset * step).clamp(min=float(xi[0]))


def base_oracle(sample: Mapping[str, Any], cfg: BaselineConfig) -> dict[str, np.ndarray]:
    """A plane sweep of the pair with its ground-truth motion (the paper's Base-Oracle)."""
    motion = sample["motion"].double()
    t = motion[3:].norm()
    if t < 1e-9:
        raise BaselineFailure("zero-baseline pair: plane sweep has no parallax")
    unit = torch.cat([motion[:3], motion[3:] / t])
    inv = plane_sweep(sample["image1"], sample["image2"], sample["intrinsics"], unit, cfg.sweep_hypotheses,
                      cfg.sweep_window, cfg.sweep_max_disparity, sample.get("intrinsics2"))
    return {"inv_depth": inv.numpy(), "motion": unit.numpy()}
