"""Epipolar geometry of a flow field, differentiable: the camera motion as the solution of a weighted
fit to the flow (the chain's motion layer under ``model.motion_fit``; not DeMoN's design, whose motion
is a fully connected head), and the geometric residual of a motion.

Under ``model.motion_fit`` the depth-motion net predicts a weight per level-2 pixel beside its depth, and
:func:`fit_motion` reads the motion from the flow those pixels carry, as DeMoN's own flow-from-depth and
depth-from-flow layers read one quantity from another (:mod:`demon_lab.core.geometry`):

1. every flow vector is a correspondence of two bearings, ``x1 = K^-1 p`` and ``x2 = K^-1 (p + flow)``,
   which the motion ``X2 = R X1 + t`` relates by the epipolar constraint ``x2^T [t]x R x1 = 0``;
2. a start: the essential matrix of the weighted 8-point algorithm (the eigenvector of the smallest
   eigenvalue of ``sum_i w_i a_i a_i^T``, ``a_i = x2_i (x) x1_i``; Ranftl & Koltun, ECCV 2018, "Deep
   Fundamental Matrix Estimation", without their learned reweighting nets), split into the rotation and
   translation that put the weighted points in front of both cameras. No gradient flows through the start
   (the derivative of an eigenvector or a singular vector is ill-defined where eigenvalues repeat, as an
   essential matrix's two equal singular values do);
3. ``steps`` Gauss-Newton steps on the rotation (3 parameters, applied as ``exp([d]x) R``) and the
   translation direction (2 parameters on the tangent plane of the unit sphere) that minimise the
   weighted squared Sampson distances of the correspondences (Hartley & Zisserman, Multiple View Geometry,
   section 11.4.3); from the second step on, each correspondence's weight is multiplied by the Cauchy
   weight of its Sampson distance at the current motion (``ROBUST_PX``): iteratively reweighted least
   squares. These steps are differentiable: the motion's gradient reaches the weights and the flow
   (as in DeepV2D's motion module, Teed & Deng, ICLR 2020, a Gauss-Newton update on learned flow and
   weights);
4. with ``starts`` > 0, the steps run from the 8-point start and from ``starts`` more, its rotation with
   translation directions spread over a hemisphere (:func:`hemisphere`), all at once; the fit with the
   lowest robust cost (:func:`robust_cost`) is the layer's motion, its translation's sign the one that
   puts more weight in front of both cameras. On a flow whose error is spread over every vector, the
   Sampson cost has minima the 8-point start falls into (a small baseline, planar rooms); the other
   starts find the deeper one (docs/notes/2026-12-learned-motion.md). The choice is discrete, as
   RANSAC's is, but deterministic and of the whole flow; the gradient flows through the chosen fit.

:func:`sampson_px` is the geometric residual the layer is trained with beside DeMoN's motion losses: the
Sampson distance of the ground-truth flow's correspondences under the predicted motion, in pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor

from demon_lab.core import geometry as geo

ROBUST_PX = 1.0
"""The scale (pixels of the flow's grid) of the Cauchy weights of the reweighting steps: a
correspondence 1 px off the epipolar line keeps half its weight."""
DAMPING = 1e-6
"""Levenberg's damping of each Gauss-Newton step, relative to the mean of the normal matrix's diagonal."""


def bearings(flow: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The correspondences a flow gives: ``x1``, ``x2`` (B, N, 3) the bearings ``K^-1 (u, v, 1)`` of
    each level's pixel centre and of its end point (``flow`` (B, 2, h, w) normalised, ``intrinsics``
    (B, 4) normalised, one camera), and ``valid`` (B, N): the vectors that are finite."""
    b, _, h, w = flow.shape
    u, v = geo.normalised_grid(h, w, flow)
    fx, fy, cx, cy = (k.view(-1, 1, 1) for k in intrinsics.to(flow.dtype).unbind(1))
    valid = torch.isfinite(flow).all(1)
    f = torch.where(valid[:, None], flow, torch.zeros_like(flow))
    x1 = torch.stack([((u - cx) / fx).expand(b, h, w), ((v - cy) / fy).expand(b, h, w),
                      torch.ones(b, h, w, dtype=flow.dtype, device=flow.device)], -1)
    x2 = torch.stack([(u + f[:, 0] - cx) / fx, (v + f[:, 1] - cy) / fy, x1[..., 2]], -1)
    return x1.flatten(1, 2), x2.flatten(1, 2), valid.flatten(1)


def eight_point(x1: Tensor, x2: Tensor, weights: Tensor) -> Tensor:
    """The essential matrices (B, 3, 3) of the weighted 8-point algorithm: the unit vector ``e``
    minimising ``sum_i w_i (x2_i^T E x1_i)^2`` (no gradient; in float64)."""
    with torch.no_grad():
        a = (x2[..., :, None] * x1[..., None, :]).flatten(2).double()
        w = weights.double()
        m = torch.einsum("bn,bni,bnj->bij", w, a, a) / w.sum(1).clamp_min(1e-12)[:, None, None]
        _, vectors = torch.linalg.eigh(m)
        return vectors[..., 0].reshape(-1, 3, 3)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def depths(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor) -> tuple[Tensor, Tensor]:
    """The depths ``z1``, ``z2`` (B, N) of each correspondence's point in the two cameras under the
    motion ``R`` (B, 3, 3), ``t`` (B, 3): ``z2 x2 = z1 R x1 + t`` solved by cross products."""
    y = torch.einsum("bij,bnj->bni", R, x1)
    c = _cross(x2, y)
    norm = (c * c).sum(-1).clamp_min(1e-18)
    tb = t[:, None].expand_as(y)
    z1 = -(_cross(x2, tb) * c).sum(-1) / norm
    z2 = (_cross(tb, y) * c).sum(-1) / norm
    return z1, z2


def decompose(E: Tensor, x1: Tensor, x2: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """The rotation (B, 3, 3) and unit translation (B, 3) of essential matrices ``E``: of the four
    that ``E`` allows, the one that puts the most weight of the correspondences in front of both
    cameras (no gradient)."""
    with torch.no_grad():
        U, _, Vh = torch.linalg.svd(E)
        U = U * torch.linalg.det(U).sign()[:, None, None]
        Vh = Vh * torch.linalg.det(Vh).sign()[:, None, None]
        W = E.new_tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        rotations = (U @ W @ Vh, U @ W.T @ Vh)
        t = U[..., 2]
        candidates = [(R, s * t) for R in rotations for s in (1.0, -1.0)]
        x1d, x2d, wd = x1.double(), x2.double(), weights.double()
        scores = []
        for R, tc in candidates:
            z1, z2 = depths(R, tc, x1d, x2d)
            scores.append((wd * ((z1 > 0) & (z2 > 0))).sum(1))
        best = torch.stack(scores, 1).argmax(1)
        R = torch.stack([c[0] for c in candidates], 1)[torch.arange(len(best)), best]
        t = torch.stack([c[1] for c in candidates], 1)[torch.arange(len(best)), best]
        return R, t


def _tangent_basis(t: Tensor) -> Tensor:
    """Two unit vectors (B, 3, 2) orthogonal to the unit ``t`` and to each other."""
    axis = torch.zeros_like(t)
    axis[torch.arange(len(t)), t.detach().abs().argmin(1)] = 1.0  # the axis least parallel to t
    b1 = _cross(t, axis)
    b1 = b1 / b1.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return torch.stack([b1, _cross(t, b1)], -1)


def residuals(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The algebraic epipolar residuals ``x2^T [t]x R x1`` (B, N), their Sampson denominators
    ``|(E x1)_12|^2 + |(E^T x2)_12|^2`` (the squared Sampson distance is their ratio) and the rotated
    bearings ``R x1`` (B, N, 3)."""
    y = torch.einsum("bij,bnj->bni", R, x1)
    tb = t[:, None].expand_as(y)
    e_x1 = _cross(tb, y)  # E x1 = [t]x R x1
    et_x2 = -torch.einsum("bji,bnj->bni", R, _cross(tb, x2))  # E^T x2 = R^T [t]x^T x2
    e = (x2 * e_x1).sum(-1)
    denominator = (e_x1[..., :2] ** 2).sum(-1) + (et_x2[..., :2] ** 2).sum(-1)
    return e, denominator.clamp_min(1e-18), y


def gauss_newton_step(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, weights: Tensor,
                      robust_scale: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """One Gauss-Newton step on the weighted squared Sampson distances; ``robust_scale`` (B,): the
    Cauchy scale in the bearings' units, which reweights each correspondence at the current motion
    (None: the weights as given)."""
    e, denominator, y = residuals(R, t, x1, x2)
    tb = t[:, None].expand_as(y)
    omega = weights / denominator
    if robust_scale is not None:
        squared = e * e / denominator
        omega = omega / (1 + squared / robust_scale[:, None] ** 2)
    basis = _tangent_basis(t)
    jacobian = torch.cat([_cross(y, _cross(x2, tb)),  # d e / d w for R <- exp([w]x) R
                          torch.einsum("bni,bik->bnk", _cross(y, x2), basis)], -1)  # d e / d s, t <- t + B s
    normal = torch.einsum("bn,bni,bnj->bij", omega, jacobian, jacobian)
    gradient = torch.einsum("bn,bni,bn->bi", omega, jacobian, e)
    damping = DAMPING * normal.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-18)
    normal = normal + damping[:, None, None] * torch.eye(5, dtype=normal.dtype, device=normal.device)
    delta = -torch.linalg.solve(normal, gradient)
    R = geo.angle_axis_to_matrix(delta[:, :3]) @ R
    t = t + torch.einsum("bik,bk->bi", basis, delta[:, 3:])
    return R, t / t.norm(dim=1, keepdim=True).clamp_min(1e-12)


def hemisphere(n: int, like: Tensor) -> Tensor:
    """``n`` unit directions (n, 3) spread evenly over the hemisphere z > 0 (a Fibonacci spiral): the
    translation directions of the fit's further starts (a direction and its opposite have one Sampson
    cost)."""
    k = torch.arange(n, dtype=like.dtype, device=like.device) + 0.5
    z = k / n
    angle = torch.pi * (1 + 5 ** 0.5) * k
    r = (1 - z * z).sqrt()
    return torch.stack([r * angle.cos(), r * angle.sin(), z], 1)


def robust_cost(R: Tensor, t: Tensor, x1: Tensor, x2: Tensor, weights: Tensor, scale: Tensor) -> Tensor:
    """The Cauchy cost (B,) that the reweighted steps lower: the weighted sum over the correspondences of
    ``log(1 + d^2 / scale^2)``, ``d`` the Sampson distance; ``scale`` (B,) in the bearings' units."""
    e, denominator, _ = residuals(R, t, x1, x2)
    return (weights * torch.log1p(e * e / denominator / scale[:, None] ** 2)).sum(1)


def fit_motion(flow: Tensor, weights: Tensor, intrinsics: Tensor, steps: int = 3, starts: int = 0) -> Tensor:
    """The camera motion (B, 6) ``[r, t]`` (angle-axis, unit t; ``X2 = R X1 + t``) that fits ``flow``
    (B, 2, h, w) normalised with the per-pixel ``weights`` (B, 1, h, w), >= 0: the weighted 8-point
    start, then ``steps`` Gauss-Newton steps, reweighted from the second on; with ``starts`` > 0 the
    steps also run from that many more starts, and the fit of the lowest robust cost is kept (module
    docstring). Non-finite flow vectors get no weight. Computed in float64, returned in float32 (float64
    for a float64 flow); differentiable in ``flow`` and ``weights`` through the Gauss-Newton steps."""
    if steps < 1:
        raise ValueError(f"motion_fit: expected at least 1 Gauss-Newton step, got {steps}")
    flow64, w64 = flow.double(), weights.double()
    x1, x2, valid = bearings(flow64, intrinsics.double())
    w = torch.where(valid, w64.flatten(1), torch.zeros_like(w64.flatten(1)))
    R, t = decompose(eight_point(x1, x2, w), x1, x2, w)
    pixel = 1.0 / (intrinsics.double()[:, 0] * flow.shape[3])  # one pixel of the grid in the bearings' units
    batch, hypotheses = len(R), 1 + starts
    if starts:  # every start as a batch element of its own: (hypothesis, batch) flattened
        t = torch.cat([t, hemisphere(starts, t).repeat_interleave(batch, 0)])
        R, x1, x2, w, pixel = (v.repeat((hypotheses,) + (1,) * (v.dim() - 1)) for v in (R, x1, x2, w, pixel))
    for step in range(steps):
        R, t = gauss_newton_step(R, t, x1, x2, w, ROBUST_PX * pixel if step > 0 else None)
    if starts:
        with torch.no_grad():
            cost = robust_cost(R, t, x1, x2, w, ROBUST_PX * pixel).view(hypotheses, batch)
            best = cost.argmin(0) * batch + torch.arange(batch, device=cost.device)
            z1, z2 = depths(R[best], t[best], x1[best], x2[best])
            behind = (w[best] * ((z1 < 0) & (z2 < 0))).sum(1) > (w[best] * ((z1 > 0) & (z2 > 0))).sum(1)
        R, t = R[best], torch.where(behind[:, None], -t[best], t[best])
    motion = torch.cat([geo.matrix_to_angle_axis(R), t], 1)
    return motion.to(torch.promote_types(flow.dtype, torch.float32))


def sampson_px(flow: Tensor, motion: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor]:
    """The Sampson distance (B, N), in pixels of the flow's grid, of each correspondence of ``flow``
    (B, 2, h, w; the ground truth) to the epipolar geometry of ``motion`` (B, 6), and where the flow
    is finite (B, N): the geometric residual of a fitted motion."""
    x1, x2, valid = bearings(flow.double(), intrinsics.double())
    R = geo.angle_axis_to_matrix(motion[:, :3].double())
    t = motion[:, 3:].double()
    t = t / t.norm(dim=1, keepdim=True).clamp_min(1e-12)
    e, denominator, _ = residuals(R, t, x1, x2)
    pixels = intrinsics.double()[:, 0:1] * flow.shape[3]
    distance = torch.sqrt(e * e / denominator + 1e-18) * pixels
    return torch.where(valid, distance, torch.zeros_like(distance)).float(), valid
