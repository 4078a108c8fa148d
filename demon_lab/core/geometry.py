"""Two-view geometry: the layers that tie optical flow, depth and camera motion together.

Pure, batched, differentiable tensor functions (float32 or float64, CPU or CUDA). The
conventions are DeMoN's (docs/reference.md §2-§3: its lmbspecialops ops ``depth_to_flow``,
``flow_to_depth``, ``warp2d``, ``depth_to_normals``) and hold for every function in this module:

* ``intrinsics``: ``(B, 4)`` normalised pinhole parameters ``(fx/W, fy/H, cx/W, cy/H)``, so they
  are the same at every resolution of an image. DeMoN's fixed value is
  :data:`DEMON_INTRINSICS`.
* Pixel ``(x, y)`` (0-based column, row) has its centre at ``(x + 0.5, y + 0.5)``; its normalised
  image coordinates are ``u = (x + 0.5) / W``, ``v = (y + 0.5) / H``.
* ``inv_depth``: ``(B, 1, H, W)`` inverse camera-z depth ``1/z`` of view 1. A pixel is valid iff
  its value is finite and ``> 0``; NaN or 0 mark invalid pixels. Invalid pixels are data, not
  errors: each function says what it outputs there.
* ``motion``: ``(B, 6)`` = angle-axis rotation ``r`` (angle ``|r|`` in radians) and translation
  ``t``, mapping camera-1 coordinates to camera-2 coordinates: ``X2 = R(r) X1 + t``.
* ``flow``: ``(B, 2, H, W)`` from image 1 to image 2, channel 0 = x, normalised by the width and
  height of its own resolution (pixel flow ``/ (W, H)``).
* Camera coordinates: x right, y down, z forward.

Shape errors raise ``ValueError`` naming the argument and the expected shape.
"""

from __future__ import annotations

import math

import torch

from demon_lab.core.execution import float32

DEMON_INTRINSICS = (0.89115971, 1.18821287, 0.5, 0.5)
"""DeMoN's fixed normalised intrinsics (SUN3D: f = 570.342 px at 640x480)."""

Tensor = torch.Tensor


# ----------------------------------------------------------------------------- argument checks


def check_map(name: str, x: Tensor, channels: int) -> None:
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor of shape (B, {channels}, H, W), "
                         f"got {type(x).__name__}")
    if x.dim() != 4 or x.shape[1] != channels:
        raise ValueError(f"{name}: expected shape (B, {channels}, H, W), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a float32 or float64 tensor, got {x.dtype}")


def _check_vectors(name: str, x: Tensor, size: int, batch: int | None = None) -> None:
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor of shape (B, {size}), "
                         f"got {type(x).__name__}")
    if x.dim() != 2 or x.shape[1] != size:
        raise ValueError(f"{name}: expected shape (B, {size}), got {tuple(x.shape)}")
    if batch is not None and x.shape[0] != batch:
        raise ValueError(f"{name}: expected batch size {batch} to match the maps, "
                         f"got shape {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a float32 or float64 tensor, got {x.dtype}")


def _check_intrinsics(name: str, intrinsics: Tensor, batch: int) -> None:
    _check_vectors(name, intrinsics, 4, batch)
    if not bool(torch.isfinite(intrinsics).all()):
        raise ValueError(f"{name}: expected finite normalised intrinsics (fx/W, fy/H, cx/W, cy/H)")
    if bool((intrinsics[:, :2] == 0).any()):
        raise ValueError(f"{name}: focal lengths fx/W and fy/H must be non-zero")


# ----------------------------------------------------------------------------- rotations


def _skew(r: Tensor) -> Tensor:
    """(B, 3) -> (B, 3, 3) cross-product matrices [r]x."""
    zero = torch.zeros_like(r[:, 0])
    x, y, z = r.unbind(1)
    return torch.stack(
        [zero, -z, y, z, zero, -x, -y, x, zero], dim=1
    ).view(-1, 3, 3)


@float32
def angle_axis_to_matrix(r: Tensor) -> Tensor:
    """Rotation matrices from angle-axis vectors (Rodrigues' formula).

    Args:
        r: (B, 3) angle-axis vectors; the angle is ``|r|`` in radians.

    Returns:
        (B, 3, 3) rotation matrices ``R = I + sin(a)/a [r]x + (1 - cos(a))/a^2 [r]x^2``.

    Smooth at ``r = 0`` (a Taylor expansion below 1e-6 rad), so gradients are finite everywhere;
    ``(1 - cos a)/a^2`` is evaluated as ``2 sin^2(a/2)/a^2`` to stay accurate in float32.

    >>> angle_axis_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]])).round()
    tensor([[[ 0., -1.,  0.],
             [ 1.,  0.,  0.],
             [ 0.,  0.,  1.]]])
    """
    _check_vectors("r", r, 3)
    theta2 = (r * r).sum(1)
    small = theta2 < 1e-12
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    half_sin = torch.sin(theta / 2)
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, 2 * half_sin * half_sin / (theta * theta))
    k = _skew(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(k)
    return eye + a[:, None, None] * k + b[:, None, None] * (k @ k)


@float32
def matrix_to_quaternion(R: Tensor) -> Tensor:
    """Unit quaternions ``(w, x, y, z)`` with ``w >= 0`` from rotation matrices (B, 3, 3).

    Shepperd's method: the branch with the largest diagonal term is used, so the result is
    accurate for every angle, including rotations by close to 180 degrees.
    """
    if not isinstance(R, torch.Tensor) or R.dim() != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R: expected shape (B, 3, 3), got {tuple(getattr(R, 'shape', ()))}")
    r00, r01, r02 = R[:, 0, 0], R[:, 0, 1], R[:, 0, 2]
    r10, r11, r12 = R[:, 1, 0], R[:, 1, 1], R[:, 1, 2]
    r20, r21, r22 = R[:, 2, 0], R[:, 2, 1], R[:, 2, 2]
    trace = r00 + r11 + r22
    tiny = torch.finfo(R.dtype).tiny

    def root(x: Tensor) -> Tensor:
        return 2 * torch.sqrt(torch.clamp(1 + x, min=tiny))

    s0, s1, s2, s3 = root(trace), root(r00 - r11 - r22), root(r11 - r00 - r22), root(r22 - r00 - r11)
    candidates = torch.stack([
        torch.stack([s0 / 4, (r21 - r12) / s0, (r02 - r20) / s0, (r10 - r01) / s0], 1),
        torch.stack([(r21 - r12) / s1, s1 / 4, (r01 + r10) / s1, (r02 + r20) / s1], 1),
        torch.stack([(r02 - r20) / s2, (r01 + r10) / s2, s2 / 4, (r12 + r21) / s2], 1),
        torch.stack([(r10 - r01) / s3, (r02 + r20) / s3, (r12 + r21) / s3, s3 / 4], 1),
    ], 1)  # (B, 4 branches, 4)
    branch = torch.stack([trace, r00, r11, r22], 1).argmax(1)
    q = candidates[torch.arange(R.shape[0], device=R.device), branch]
    q = q / q.norm(dim=1, keepdim=True)
    return torch.where(q[:, :1] < 0, -q, q)


@float32
def matrix_to_angle_axis(R: Tensor) -> Tensor:
    """Angle-axis vectors (B, 3), angle in ``[0, pi]``, from rotation matrices (B, 3, 3)."""
    q = matrix_to_quaternion(R)
    w, v = q[:, 0], q[:, 1:]
    n = v.norm(dim=1)
    small = n < 1e-7
    n_safe = torch.where(small, torch.ones_like(n), n)
    # angle / |v| = 2 atan2(|v|, w) / |v|  ->  2 / w for |v| -> 0 (w -> 1).
    scale = torch.where(small, 2 / w, 2 * torch.atan2(n_safe, w) / n_safe)
    return v * scale[:, None]


# ----------------------------------------------------------------------------- projection


def normalised_grid(height: int, width: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised pixel-centre coordinates u (1, 1, W) and v (1, H, 1)."""
    u = (torch.arange(width, dtype=like.dtype, device=like.device) + 0.5) / width
    v = (torch.arange(height, dtype=like.dtype, device=like.device) + 0.5) / height
    return u.view(1, 1, width), v.view(1, height, 1)


def _intrinsics_maps(intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    fx, fy, cx, cy = intrinsics.unbind(1)
    return tuple(k.view(-1, 1, 1) for k in (fx, fy, cx, cy))  # type: ignore[return-value]


def valid_depth(inv_depth: Tensor) -> Tensor:
    """Boolean mask of valid pixels: finite and > 0 (same shape as ``inv_depth``)."""
    return torch.isfinite(inv_depth) & (inv_depth > 0)


def _rays(height: int, width: int, intrinsics: Tensor) -> Tensor:
    """Back-projected pixel-centre rays K^-1 (u, v, 1): (B, 3, H, W), z component 1."""
    u, v = normalised_grid(height, width, intrinsics)
    fx, fy, cx, cy = _intrinsics_maps(intrinsics)
    x = ((u - cx) / fx).expand(-1, height, width)
    y = ((v - cy) / fy).expand(-1, height, width)
    return torch.stack([x, y, torch.ones_like(x)], dim=1)


def _project(
    inv_depth: Tensor, motion: Tensor, intrinsics: Tensor, intrinsics2: Tensor | None
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project view-1 pixels into view 2.

    Returns normalised coordinates (u2, v2) in view 2, the sign-carrying depth term
    ``xi * z2`` (> 0 iff the point is in front of camera 2) and the validity mask, all (B, H, W).
    Works on inverse depth directly: X2 / z = R K^-1 p + xi t, so points at infinity stay finite.
    """
    check_map("inv_depth", inv_depth, 1)
    batch, _, height, width = inv_depth.shape
    _check_vectors("motion", motion, 6, batch)
    _check_intrinsics("intrinsics", intrinsics, batch)
    if intrinsics2 is None:
        intrinsics2 = intrinsics
    else:
        _check_intrinsics("intrinsics2", intrinsics2, batch)
    # The maps set the dtype; the small vectors follow it.
    motion, intrinsics, intrinsics2 = (x.to(inv_depth.dtype) for x in (motion, intrinsics, intrinsics2))
    xi = inv_depth[:, 0]
    valid = valid_depth(xi)
    xi = torch.where(valid, xi, torch.zeros_like(xi))  # finite values keep gradients NaN-free
    R = angle_axis_to_matrix(motion[:, :3])
    rays = torch.einsum("bij,bjhw->bihw", R, _rays(height, width, intrinsics))
    p = rays + xi.unsqueeze(1) * motion[:, 3:, None, None]
    fx, fy, cx, cy = _intrinsics_maps(intrinsics2)
    z = p[:, 2]
    z_safe = torch.where(z == 0, torch.ones_like(z), z)
    u2 = fx * p[:, 0] / z_safe + cx
    v2 = fy * p[:, 1] / z_safe + cy
    return u2, v2, z, valid


@float32
def flow_from_depth_motion(
    inv_depth: Tensor, motion: Tensor, intrinsics: Tensor, intrinsics2: Tensor | None = None
) -> Tensor:
    """Optical flow induced by a depth map and a camera motion (DeMoN's ``depth_to_flow``).

    Args:
        inv_depth: (B, 1, H, W) inverse depth of view 1; invalid pixels (NaN, 0, inf, < 0).
        motion: (B, 6) [r, t], X2 = R X1 + t.
        intrinsics: (B, 4) normalised intrinsics of view 1.
        intrinsics2: (B, 4) normalised intrinsics of view 2 (default: same as view 1).

    Returns:
        (B, 2, H, W) normalised flow; NaN where the depth is invalid. Like DeMoN, points behind
        camera 2 are not treated specially (their projection is still returned).
    """
    u2, v2, _, valid = _project(inv_depth, motion, intrinsics, intrinsics2)
    u, v = normalised_grid(inv_depth.shape[2], inv_depth.shape[3], inv_depth)
    flow = torch.stack([u2 - u, v2 - v], dim=1)
    return torch.where(valid.unsqueeze(1), flow, torch.full_like(flow, math.nan))


@float32
def reproject(
    inv_depth: Tensor, motion: Tensor, intrinsics: Tensor, intrinsics2: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Where each view-1 pixel's 3-D point lands in view 2, and its inverse depth there.

    Args: as :func:`flow_from_depth_motion`.

    Returns:
        ``(coords, inv_depth2)``: (B, 2, H, W) normalised image coordinates (u2, v2) in view 2
        and (B, 1, H, W) inverse camera-z depth 1/z2 of the point in view 2 (negative behind
        camera 2); both NaN where the view-1 depth is invalid.
    """
    u2, v2, z, valid = _project(inv_depth, motion, intrinsics, intrinsics2)
    xi = inv_depth[:, 0]
    # z = z2 / z1 = z2 * xi, so 1 / z2 = xi / z.
    inv2 = xi / torch.where(valid & (z != 0), z, torch.ones_like(z))
    nan = torch.full_like(u2, math.nan)
    coords = torch.stack([u2, v2], dim=1)
    inv2 = torch.where(valid & (z != 0), inv2, nan)
    return torch.where(valid.unsqueeze(1), coords, nan.unsqueeze(1)), inv2.unsqueeze(1)


@float32
def triangulation_angle(inv_depth: Tensor, motion: Tensor, intrinsics: Tensor) -> Tensor:
    """Angle at each view-1 point between the rays to the two camera centres, in degrees.

    With X the 3-D point of a pixel (camera-1 coordinates), C1 = 0 and C2 = -R^T t, this is the
    angle between C1 - X and C2 - X. NaN where the depth is invalid.

    Returns:
        (B, 1, H, W) degrees.
    """
    check_map("inv_depth", inv_depth, 1)
    batch, _, height, width = inv_depth.shape
    _check_vectors("motion", motion, 6, batch)
    _check_intrinsics("intrinsics", intrinsics, batch)
    motion, intrinsics = motion.to(inv_depth.dtype), intrinsics.to(inv_depth.dtype)
    valid = valid_depth(inv_depth)
    z = 1 / torch.where(valid, inv_depth, torch.ones_like(inv_depth))
    X = z * _rays(height, width, intrinsics)
    R = angle_axis_to_matrix(motion[:, :3])
    c2 = -(R.transpose(1, 2) @ motion[:, 3:, None])[:, :, 0]
    a, b = -X, c2[:, :, None, None] - X
    cos = (a * b).sum(1, keepdim=True) / (a.norm(dim=1, keepdim=True) * b.norm(dim=1, keepdim=True))
    angle = torch.rad2deg(torch.acos(cos.clamp(-1, 1)))
    return torch.where(valid, angle, torch.full_like(angle, math.nan))


@float32
def visibility_mask(
    inv_depth: Tensor, motion: Tensor, intrinsics: Tensor, intrinsics2: Tensor | None = None
) -> Tensor:
    """Pixels of view 1 whose 3-D point projects strictly inside image 2, in front of camera 2.

    This is DeMoN's evaluation ``depthmask`` rule (z2 > 0, 0 < u2 < W, 0 < v2 < H); it does
    not test occlusion. Invalid depth gives False.

    Returns:
        (B, 1, H, W) bool.
    """
    u2, v2, z, valid = _project(inv_depth, motion, intrinsics, intrinsics2)
    inside = (z > 0) & (u2 > 0) & (u2 < 1) & (v2 > 0) & (v2 < 1)
    return (valid & inside).unsqueeze(1)


@float32
def depth_from_flow_motion(
    flow: Tensor,
    motion: Tensor,
    intrinsics: Tensor,
    clip: tuple[float, float] | None = None,
) -> Tensor:
    """Inverse depth of view 1 by linear triangulation of the flow (DeMoN's ``flow_to_depth``).

    For every pixel the two views give four linear equations in X (two per view, from the
    cameras ``Kn [I|0]`` and ``Kn [R|t]`` in normalised image coordinates); they are solved in
    least squares exactly as DeMoN's SVD solve (via the normal equations, in float64 whatever the
    input dtype, since they are ill-conditioned at small triangulation angles).

    Args:
        flow: (B, 2, H, W) normalised flow from view 1 to view 2.
        motion: (B, 6) [r, t], X2 = R X1 + t.
        intrinsics: (B, 4) normalised intrinsics (shared by both views, as in DeMoN).
        clip: optional (min, max) applied to the inverse depth (DeMoN v2 uses (0, 50)).

    Returns:
        (B, 1, H, W) inverse depth ``1/Z``; 0 where the point is not triangulable (non-finite
        flow or solution, Z <= 0, a degenerate system such as zero translation).
    """
    check_map("flow", flow, 2)
    batch, _, height, width = flow.shape
    _check_vectors("motion", motion, 6, batch)
    _check_intrinsics("intrinsics", intrinsics, batch)
    dtype = flow.dtype
    f64 = torch.float64
    flow, motion, intrinsics = flow.to(f64), motion.to(f64), intrinsics.to(f64)

    finite = torch.isfinite(flow).all(1)
    flow = torch.where(finite.unsqueeze(1), flow, torch.zeros_like(flow))
    u1, v1 = normalised_grid(height, width, flow)
    fx, fy, cx, cy = _intrinsics_maps(intrinsics)
    du1, dv1 = u1 - cx, v1 - cy  # (B, 1, W), (B, H, 1): view-1 terms are separable
    du2, dv2 = du1 + flow[:, 0], dv1 + flow[:, 1]  # (B, H, W)
    R = angle_axis_to_matrix(motion[:, :3]).view(-1, 3, 3, 1, 1)
    t = motion[:, 3:].view(-1, 3, 1, 1)
    # DeMoN's rows, per view (P, (u, v)): (v P3 - P2) X = P24 - v P34 and (P1 - u P3) X = u P34 - P14.
    # View 1, P = Kn [I|0]: (0, -fy, dv1) X = 0 and (fx, 0, -du1) X = 0.
    # View 2, P = Kn [R|t]: a X = ra and b X = rb with
    a = [dv2 * R[:, 2, k] - fy * R[:, 1, k] for k in range(3)]
    b = [fx * R[:, 0, k] - du2 * R[:, 2, k] for k in range(3)]
    ra = fy * t[:, 1] - dv2 * t[:, 2]
    rb = du2 * t[:, 2] - fx * t[:, 0]
    # Least squares through the normal equations M X = g (M symmetric; view 1 has zero rhs).
    m00 = fx * fx + a[0] * a[0] + b[0] * b[0]
    m01 = a[0] * a[1] + b[0] * b[1]
    m02 = a[0] * a[2] + b[0] * b[2] - fx * du1
    m11 = fy * fy + a[1] * a[1] + b[1] * b[1]
    m12 = a[1] * a[2] + b[1] * b[2] - fy * dv1
    m22 = a[2] * a[2] + b[2] * b[2] + du1 * du1 + dv1 * dv1
    g = [a[k] * ra + b[k] * rb for k in range(3)]
    det = (m00 * (m11 * m22 - m12 * m12)
           + m01 * (m02 * m12 - m01 * m22)
           + m02 * (m01 * m12 - m02 * m11))
    # Z by Cramer's rule: the third column of M replaced by g.
    det_z = (m00 * (m11 * g[2] - g[1] * m12)
             - m01 * (m01 * g[2] - g[1] * m02)
             + g[0] * (m01 * m12 - m11 * m02))
    det_safe = torch.where(det == 0, torch.ones_like(det), det)
    z = det_z / det_safe
    # With finite inputs and det != 0 the whole solution X is finite; DeMoN requires Z > 0.
    ok = finite & (det != 0) & torch.isfinite(z) & (z > 0)
    inv = torch.where(ok, 1 / torch.where(ok, z, torch.ones_like(z)), torch.zeros_like(z))
    if clip is not None:
        inv = inv.clamp(clip[0], clip[1])
    return inv.unsqueeze(1).to(dtype)


# ----------------------------------------------------------------------------- normals


@float32
def normals_from_depth(inv_depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Unit surface normals of view 1 from its inverse depth (DeMoN's ``depth_to_normals``).

    For an interior pixel whose own depth and its 4 neighbours' depths are valid, with 3-D points
    P = z K^-1 (x + 0.5, y + 0.5, 1):
    ``n1 = (P - P_right) x (P_down - P)``, ``n0 = (P - P_left) x (P_up - P)``,
    ``n = normalise(normalise(n1) + normalise(n0))``. Normals point towards the camera (a
    fronto-parallel plane gives (0, 0, -1)).

    Args:
        inv_depth: (B, 1, H, W) inverse depth.
        intrinsics: (B, 4) normalised intrinsics.

    Returns:
        (B, 3, H, W) unit normals in camera-1 coordinates; NaN at border pixels and wherever
        the pixel or a 4-neighbour is invalid (or the normal is undefined).
    """
    check_map("inv_depth", inv_depth, 1)
    batch, _, height, width = inv_depth.shape
    _check_intrinsics("intrinsics", intrinsics, batch)
    intrinsics = intrinsics.to(inv_depth.dtype)
    valid = valid_depth(inv_depth)
    z = 1 / torch.where(valid, inv_depth, torch.ones_like(inv_depth))
    P = z * _rays(height, width, intrinsics)
    out = torch.full((batch, 3, height, width), math.nan, dtype=P.dtype, device=P.device)
    if height < 3 or width < 3:
        return out
    c = P[:, :, 1:-1, 1:-1]
    n1 = _unit(_cross(c - P[:, :, 1:-1, 2:], P[:, :, 2:, 1:-1] - c))
    n0 = _unit(_cross(c - P[:, :, 1:-1, :-2], P[:, :, :-2, 1:-1] - c))
    n = n1 + n0
    norm2 = (n * n).sum(1, keepdim=True)
    ok = (valid[:, :, 1:-1, 1:-1] & valid[:, :, 1:-1, 2:] & valid[:, :, 1:-1, :-2]
          & valid[:, :, 2:, 1:-1] & valid[:, :, :-2, 1:-1] & (norm2 > 0))
    n = n * torch.rsqrt(torch.where(ok, norm2, torch.ones_like(norm2)))
    out[:, :, 1:-1, 1:-1] = torch.where(ok, n, torch.full_like(n, math.nan))
    return out


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """Cross product along dim 1 of (B, 3, H, W) maps (explicit: linalg.cross is slower on these maps)."""
    ax, ay, az = a.unbind(1)
    bx, by, bz = b.unbind(1)
    return torch.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], dim=1)


def _unit(n: Tensor) -> Tensor:
    """Normalise along dim 1; zero vectors stay zero (they are rejected by the caller)."""
    norm2 = (n * n).sum(1, keepdim=True)
    return n * torch.rsqrt(torch.where(norm2 > 0, norm2, torch.ones_like(norm2)))
