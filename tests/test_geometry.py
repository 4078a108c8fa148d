"""demon_lab.core.geometry: analytic cases, round trips, real data and OpenCV cross-checks."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest
import torch
from conftest import DEVICES, random_scene, rotation_about

from demon_lab.core import geometry as geo
from demon_lab.core import loss_maps, warping

K_DEMON = torch.tensor([geo.DEMON_INTRINSICS], dtype=torch.float64)


# ----------------------------------------------------------------------------- rotations


def _cv2_rodrigues(r: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(r, dtype=np.float64).reshape(3, 1))[0]


ROTATIONS = [
    rotation_about([0, 0, 1], 90), rotation_about([1, 2, 3], 37.5), rotation_about([1, 0, 0], 1e-5),
    rotation_about([0, 1, 1], 179.9), rotation_about([3, -1, 2], 180.0), np.zeros(3),
    rotation_about([-1, 0.5, 0.2], 5.0), rotation_about([0.3, 0.9, -0.2], 120.0),
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_angle_axis_to_matrix_matches_cv2_rodrigues(dtype):
    r = np.stack(ROTATIONS + list(np.random.default_rng(1).normal(size=(20, 3))))
    ours = geo.angle_axis_to_matrix(torch.tensor(r, dtype=dtype)).double().numpy()
    ref = np.stack([_cv2_rodrigues(x) for x in r])
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    np.testing.assert_allclose(ours, ref, atol=tol)


def test_matrix_to_angle_axis_matches_cv2_rodrigues():
    r = np.stack(ROTATIONS[:-3] + [rotation_about([0.3, 0.9, -0.2], 120.0)]
                 + list(np.random.default_rng(2).normal(size=(20, 3)) * 0.8))
    R = np.stack([_cv2_rodrigues(x) for x in r])
    ours = geo.matrix_to_angle_axis(torch.from_numpy(R)).numpy()
    ref = np.stack([cv2.Rodrigues(m)[0][:, 0] for m in R])
    for a, b, truth in zip(ours, ref, r):
        angle = np.linalg.norm(truth)
        if abs(angle - math.pi) < 1e-6:  # r and -r are the same rotation at 180 degrees
            b = b if np.dot(a, b) >= 0 else -b
        if angle < 1e-5:  # cv2.Rodrigues rounds tiny rotations to 0; ours keeps them
            np.testing.assert_allclose(a, truth, rtol=1e-6, atol=1e-20)
        else:
            np.testing.assert_allclose(a, b, atol=1e-7)
    # and back: the matrix is reproduced for every angle up to 180 degrees
    np.testing.assert_allclose(geo.angle_axis_to_matrix(torch.from_numpy(ours)).numpy(), R,
                               atol=1e-12)


def test_rotation_of_90_degrees_about_z_is_exact():
    R = geo.angle_axis_to_matrix(torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64))[0]
    np.testing.assert_allclose(R.numpy(), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)


# ----------------------------------------------------------------------------- analytic flow


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fronto_parallel_plane_under_translation_has_closed_form_flow(dtype):
    H, W, z0 = 24, 32, 2.5
    fx, fy, cx, cy = 0.9, 1.2, 0.45, 0.55
    K = torch.tensor([[fx, fy, cx, cy]], dtype=dtype)
    inv = torch.full((1, 1, H, W), 1 / z0, dtype=dtype)
    tx, ty, tz = 0.3, -0.2, 0.4
    flow = geo.flow_from_depth_motion(inv, torch.tensor([[0, 0, 0, tx, ty, tz]], dtype=dtype), K)
    u = (np.arange(W) + 0.5) / W
    v = (np.arange(H) + 0.5) / H
    # X1 = z0 ((u - cx)/fx, (v - cy)/fy, 1); X2 = X1 + t; u2 = fx X2x / X2z + cx.
    u2 = ((u - cx) * z0 + fx * tx) / (z0 + tz) + cx
    v2 = ((v - cy) * z0 + fy * ty) / (z0 + tz) + cy
    expected = np.stack([np.broadcast_to(u2 - u, (H, W)), np.broadcast_to((v2 - v)[:, None], (H, W))])
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    np.testing.assert_allclose(flow[0].double().numpy(), expected, atol=tol)
    # Sideways motion alone gives a uniform flow fx tx / z0.
    flow = geo.flow_from_depth_motion(inv, torch.tensor([[0, 0, 0, tx, ty, 0]], dtype=dtype), K)
    np.testing.assert_allclose(flow[0, 0].double().numpy(), fx * tx / z0, atol=tol)
    np.testing.assert_allclose(flow[0, 1].double().numpy(), fy * ty / z0, atol=tol)


def test_pure_rotation_flow_is_independent_of_depth_and_is_the_homography():
    inv_a, motion, K = random_scene(2, 24, 32, seed=3)
    inv_b = inv_a * 7.3 + 0.01
    motion[:, 3:] = 0
    flow_a = geo.flow_from_depth_motion(inv_a, motion, K)
    flow_b = geo.flow_from_depth_motion(inv_b, motion, K)
    torch.testing.assert_close(flow_a, flow_b, atol=1e-14, rtol=0)
    # The infinite homography K R K^-1 in normalised coordinates.
    fx, fy, cx, cy = K[0].tolist()
    Kn = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    H_inf = Kn @ geo.angle_axis_to_matrix(motion[:1, :3])[0].numpy() @ np.linalg.inv(Kn)
    u, v = (np.arange(32) + 0.5) / 32, (np.arange(24) + 0.5) / 24
    uu, vv = np.meshgrid(u, v)
    p = H_inf @ np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    np.testing.assert_allclose(flow_a[0, 0].numpy().ravel(), p[0] / p[2] - uu.ravel(), atol=1e-14)
    np.testing.assert_allclose(flow_a[0, 1].numpy().ravel(), p[1] / p[2] - vv.ravel(), atol=1e-14)


def test_invalid_depth_gives_nan_flow_and_false_visibility():
    inv, motion, K = random_scene(1, 8, 10)
    inv[0, 0, 2, 3] = math.nan
    inv[0, 0, 4, 5] = 0.0
    inv[0, 0, 1, 1] = -1.0
    flow = geo.flow_from_depth_motion(inv, motion, K)
    bad = torch.zeros(8, 10, dtype=torch.bool)
    bad[2, 3] = bad[4, 5] = bad[1, 1] = True
    assert torch.isnan(flow[0, :, bad]).all()
    assert torch.isfinite(flow[0, :, ~bad]).all()
    assert not geo.visibility_mask(inv, motion, K)[0, 0, bad].any()


def test_visibility_mask_for_a_sideways_translation():
    # Plane at depth 2, camera 2 moved 0.5 to the right: X2 = X1 - (0.5, 0, 0). A point shifts by
    # fx * (-0.5) / 2 = -0.25 fx in u; pixels with u < 0.25 fx leave image 2 on the left.
    H, W, fx = 12, 40, 0.8
    K = torch.tensor([[fx, 1.0, 0.5, 0.5]], dtype=torch.float64)
    inv = torch.full((1, 1, H, W), 0.5, dtype=torch.float64)
    mask = geo.visibility_mask(inv, torch.tensor([[0, 0, 0, -0.5, 0, 0.0]], dtype=torch.float64), K)
    u = (np.arange(W) + 0.5) / W
    expected = (u - 0.25 * fx > 0) & (u - 0.25 * fx < 1)
    np.testing.assert_array_equal(mask[0, 0].numpy(), np.broadcast_to(expected, (H, W)))
    # Behind camera 2 is never visible.
    behind = geo.visibility_mask(inv, torch.tensor([[0, 0, 0, 0, 0, -3.0]], dtype=torch.float64), K)
    assert not behind.any()


def test_reproject_gives_view2_depth_of_the_point():
    H, W = 6, 8
    K = torch.tensor([[1.0, 1.0, 0.5, 0.5]], dtype=torch.float64)
    inv = torch.full((1, 1, H, W), 0.25, dtype=torch.float64)
    coords, inv2 = geo.reproject(inv, torch.tensor([[0, 0, 0, 0, 0, 1.0]], dtype=torch.float64), K)
    np.testing.assert_allclose(inv2.numpy(), 1 / 5.0)  # z2 = 4 + 1
    flow = geo.flow_from_depth_motion(inv, torch.tensor([[0, 0, 0, 0, 0, 1.0]], dtype=torch.float64), K)
    u, v = (np.arange(W) + 0.5) / W, (np.arange(H) + 0.5) / H
    np.testing.assert_allclose(coords[0, 0].numpy() - u, flow[0, 0].numpy(), atol=1e-15)
    np.testing.assert_allclose(coords[0, 1].numpy() - v[:, None], flow[0, 1].numpy(), atol=1e-15)


# ----------------------------------------------------------------------------- triangulation


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
def test_depth_flow_round_trip_recovers_depth(dtype, tol):
    inv, motion, K = random_scene(3, 48, 64, dtype=dtype, seed=4)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    back = geo.depth_from_flow_motion(flow, motion, K)
    assert back.dtype == dtype
    triangulable = back > 0
    assert triangulable.double().mean() > 0.99
    rel = ((back - inv).abs() / inv)[triangulable]
    assert rel.max() < tol, rel.max()


def test_depth_from_flow_matches_cv2_triangulate_points():
    inv, motion, K = random_scene(1, 12, 16, seed=5)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    ours = geo.depth_from_flow_motion(flow, motion, K)[0, 0].numpy()
    fx, fy, cx, cy = K[0].tolist()
    Kn = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    R = geo.angle_axis_to_matrix(motion[:, :3])[0].numpy()
    P1 = Kn @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = Kn @ np.hstack([R, motion[0, 3:].numpy()[:, None]])
    uu, vv = np.meshgrid((np.arange(16) + 0.5) / 16, (np.arange(12) + 0.5) / 12)
    x1 = np.stack([uu.ravel(), vv.ravel()])
    x2 = x1 + flow[0].numpy().reshape(2, -1)
    X = cv2.triangulatePoints(P1, P2, x1, x2)
    np.testing.assert_allclose(ours.ravel(), X[3] / X[2], rtol=1e-9)


def test_depth_from_noisy_flow_is_the_least_squares_solution_of_demons_system():
    inv, motion, K = random_scene(1, 6, 7, seed=6)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    flow = flow + torch.randn(flow.shape, generator=torch.Generator().manual_seed(0),
                              dtype=torch.float64) * 0.01
    ours = geo.depth_from_flow_motion(flow, motion, K)[0, 0].numpy()
    fx, fy, cx, cy = K[0].tolist()
    Kn = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    R = geo.angle_axis_to_matrix(motion[:, :3])[0].numpy()
    cams = [Kn @ np.hstack([np.eye(3), np.zeros((3, 1))]),
            Kn @ np.hstack([R, motion[0, 3:].numpy()[:, None]])]
    for y in range(6):
        for x in range(7):
            u1, v1 = (x + 0.5) / 7, (y + 0.5) / 6
            pts = [(u1, v1), (u1 + flow[0, 0, y, x].item(), v1 + flow[0, 1, y, x].item())]
            A, b = [], []
            for P, (u, v) in zip(cams, pts):  # lmbspecialops' flow_to_depth (docs/reference.md §3)
                A += [v * P[2, :3] - P[1, :3], P[0, :3] - u * P[2, :3]]
                b += [P[1, 3] - v * P[2, 3], u * P[2, 3] - P[0, 3]]
            X = np.linalg.lstsq(np.array(A), np.array(b), rcond=None)[0]
            expected = 1 / X[2] if X[2] > 0 else 0.0
            assert ours[y, x] == pytest.approx(expected, rel=1e-8)


def test_untriangulable_pixels_give_zero_and_clip_applies():
    inv, motion, K = random_scene(1, 8, 8, seed=7)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    flow[0, :, 0, 0] = math.nan
    out = geo.depth_from_flow_motion(flow, motion, K)
    assert out[0, 0, 0, 0] == 0
    no_motion = geo.depth_from_flow_motion(torch.zeros_like(flow), torch.zeros_like(motion), K)
    assert (no_motion == 0).all()
    # Without rotation, reversing the translation mirrors the solution behind camera 1: all 0.
    motion[:, :3] = 0
    flow = geo.flow_from_depth_motion(inv, motion, K)
    assert (geo.depth_from_flow_motion(flow, motion, K) > 0).all()
    reversed_motion = torch.cat([motion[:, :3], -motion[:, 3:]], 1)
    assert (geo.depth_from_flow_motion(flow, reversed_motion, K) == 0).all()
    clipped = geo.depth_from_flow_motion(flow, motion, K, clip=(0.0, 0.3))
    assert clipped.max() <= 0.3 and (clipped == 0.3).any()


# ----------------------------------------------------------------------------- real data


def test_sun3d_view1_depth_and_motion_predict_view2_depth(sun3d_pair):
    d1, d2, K, T = sun3d_pair["depth1"], sun3d_pair["depth2"], sun3d_pair["K"], sun3d_pair["T12"]
    H, W = d1.shape
    # The facts demon_lab/data/real/README.md states about this pair.
    angle = math.degrees(np.linalg.norm(cv2.Rodrigues(T[:3, :3])[0]))
    assert angle == pytest.approx(1.853, abs=1e-3)
    t = T[:3, 3]
    assert np.linalg.norm(t) == pytest.approx(0.0749, abs=1e-4)
    np.testing.assert_allclose(t / np.linalg.norm(t), [-0.8187, -0.0454, -0.5724], atol=1e-4)
    intrinsics = torch.tensor([[K[0, 0] / W, K[1, 1] / H, K[0, 2] / W, K[1, 2] / H]])
    np.testing.assert_allclose(intrinsics[0].numpy(), geo.DEMON_INTRINSICS, rtol=1e-7)
    motion = geo.matrix_to_angle_axis(torch.from_numpy(T[None, :3, :3]).float())
    motion = torch.cat([motion, torch.from_numpy(T[None, :3, 3]).float()], 1)
    with np.errstate(divide="ignore"):
        inv1 = torch.from_numpy(np.where(d1 > 0, 1 / d1, np.nan)).float()[None, None]
    coords, inv2 = geo.reproject(inv1, motion, intrinsics)
    x = np.floor(coords[0, 0].numpy() * W)
    y = np.floor(coords[0, 1].numpy() * H)
    inside = np.isfinite(x) & (x >= 0) & (x < W) & (y >= 0) & (y < H)
    xi, yi = x[inside].astype(int), y[inside].astype(int)
    target = d2[yi, xi]
    predicted = 1 / inv2[0, 0].numpy()[inside]
    keep = target > 0
    rel = np.abs(predicted[keep] - target[keep]) / target[keep]
    assert keep.sum() > 0.5 * (d1 > 0).sum()
    assert np.median(rel) < 0.01
    assert (rel < 0.05).mean() > 0.95


# ----------------------------------------------------------------------------- warping


def test_warp_matches_cv2_remap_in_the_interior():
    rng = np.random.default_rng(8)
    H, W = 48, 64
    image = (rng.random((H, W, 3)) - 0.5).astype(np.float32)
    flow = ((rng.random((2, H, W)) - 0.5) * 0.2).astype(np.float32)
    ours = warping.warp_image(torch.from_numpy(image).permute(2, 0, 1)[None],
                          torch.from_numpy(flow)[None])[0].permute(1, 2, 0).numpy()
    mx = (np.arange(W)[None] + W * flow[0]).astype(np.float32)
    my = (np.arange(H)[:, None] + H * flow[1]).astype(np.float32)
    ref = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    interior = (np.floor(mx) >= 0) & (np.floor(mx) <= W - 2) & (np.floor(my) >= 0) & (np.floor(my) <= H - 2)
    assert 0.6 < interior.mean() < 0.95
    # OpenCV 4 interpolates with 5-bit fixed-point weights; OpenCV 5 in float.
    tol = 1e-5 if int(cv2.__version__.split(".")[0]) >= 5 else 1 / 32
    assert np.abs(ours - ref)[interior].max() < tol
    assert (ours[~interior] == 0).all()


def test_warp_requires_all_four_neighbours_inside():
    H, W = 4, 5
    image = torch.arange(H * W, dtype=torch.float64).view(1, 1, H, W) + 1
    flow = torch.zeros(1, 2, H, W, dtype=torch.float64)
    out = warping.warp_image(image, flow)
    # Zero flow samples exactly at pixel centres: the last row/column have a neighbour outside.
    np.testing.assert_allclose(out[0, 0, :-1, :-1].numpy(), image[0, 0, :-1, :-1].numpy(), rtol=1e-14)
    assert (out[0, 0, -1] == 0).all() and (out[0, 0, :, -1] == 0).all()
    # Half a pixel right: the bilinear mean of two neighbours.
    flow[:, 0] = 0.5 / W
    out = warping.warp_image(image, flow)
    assert out[0, 0, 1, 1].item() == pytest.approx((image[0, 0, 1, 1] + image[0, 0, 1, 2]).item() / 2)
    # Left of the image and NaN flow give 0.
    flow[:, 0] = -0.5 / W
    flow[0, 0, 2, 2] = math.nan
    out = warping.warp_image(image, flow)
    assert (out[0, 0, :, 0] == 0).all() and out[0, 0, 2, 2] == 0


def test_warp_with_ground_truth_flow_reproduces_view_1():
    # A plane textured in world space: warping image 2 with the true flow gives image 1.
    H, W = 48, 64
    K = torch.tensor([[1.0, 1.0, 0.5, 0.5]], dtype=torch.float64)
    inv = torch.full((1, 1, H, W), 0.5, dtype=torch.float64)
    motion = torch.tensor([[0, 0, 0, -0.1, 0.05, 0.0]], dtype=torch.float64)
    flow = geo.flow_from_depth_motion(inv, motion, K)  # uniform (-0.05, 0.025)

    def texture(u, v):  # a smooth pattern: bilinear interpolation is nearly exact
        return 0.3 * torch.sin(2 * math.pi * u * 1.3) * torch.cos(2 * math.pi * v * 0.9)

    u = ((torch.arange(W) + 0.5) / W).double().view(1, W)
    v = ((torch.arange(H) + 0.5) / H).double().view(H, 1)
    image1 = texture(u, v)
    image2 = texture(u - flow[0, 0, 0, 0], v - flow[0, 1, 0, 0])
    out = warping.warp_image(image2.view(1, 1, H, W), flow)[0, 0]
    seen = out != 0
    assert seen.double().mean() > 0.85
    assert (out - image1)[seen].abs().max() < 2e-3


# ----------------------------------------------------------------------------- normals


def test_normals_of_a_plane_are_the_plane_normal():
    H, W = 20, 24
    K = torch.tensor([[0.9, 1.1, 0.48, 0.52]], dtype=torch.float64)
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    d = -2.0  # plane n.X = d, in front of the camera
    u, v = (np.arange(W) + 0.5) / W, (np.arange(H) + 0.5) / H
    ray = np.stack(np.broadcast_arrays((u[None] - 0.48) / 0.9, ((v - 0.52) / 1.1)[:, None], 1.0))
    z = d / np.tensordot(n, ray, axes=1)
    assert (z > 0).all()
    out = geo.normals_from_depth(torch.from_numpy(1 / z)[None, None], K)[0].numpy()
    interior = out[:, 1:-1, 1:-1].reshape(3, -1)
    np.testing.assert_allclose(interior, n[:, None].repeat(interior.shape[1], 1), atol=1e-12)
    assert np.isnan(out[:, 0]).all() and np.isnan(out[:, :, -1]).all()


def test_fronto_parallel_normals_point_at_the_camera_and_invalid_neighbours_give_nan():
    inv = torch.full((1, 1, 7, 9), 0.5)
    inv[0, 0, 3, 4] = math.nan
    n = geo.normals_from_depth(inv, K_DEMON.float())
    torch.testing.assert_close(n[0, :, 1, 1], torch.tensor([0.0, 0.0, -1.0]))
    for y, x in [(3, 4), (2, 4), (4, 4), (3, 3), (3, 5)]:
        assert torch.isnan(n[0, :, y, x]).all()
    assert torch.isfinite(n[0, :, 2, 3]).all()  # a diagonal neighbour does not matter


# ----------------------------------------------------------------------------- loss helpers


def test_scale_invariant_gradients_hand_computed():
    x = torch.tensor([[[[1.0, 3.0, -1.0], [2.0, 2.0, 0.0]]]])  # (1, 1, 2, 3)
    g = loss_maps.scale_invariant_gradients(x, spacings=(1, 2), eps=0.0)
    assert g.shape == (1, 1, 4, 2, 3)
    gx1, gy1, gx2, gy2 = g[0, 0]
    torch.testing.assert_close(gx1, torch.tensor([[2 / 4, -4 / 4, 0], [0 / 4, -2 / 2, 0]]))
    torch.testing.assert_close(gy1, torch.tensor([[1 / 3, -1 / 5, 1 / 1], [0, 0, 0]]))
    torch.testing.assert_close(gx2, torch.tensor([[-2 / 2, 0, 0], [-2 / 2, 0, 0]]))
    assert (gy2 == 0).all()  # spacing 2 reaches outside a 2-row image
    eps = loss_maps.scale_invariant_gradients(x, spacings=(1,), eps=1.0)[0, 0, 0]
    assert eps[0, 0].item() == pytest.approx(2 / 5)


def test_scale_invariant_gradients_are_scale_invariant_and_propagate_nan():
    x = torch.rand(2, 2, 16, 20) + 0.1
    torch.testing.assert_close(loss_maps.scale_invariant_gradients(x, eps=0),
                               loss_maps.scale_invariant_gradients(7 * x, eps=0))
    x[0, 0, 5, 5] = math.nan
    g = loss_maps.scale_invariant_gradients(x)
    assert g.shape == (2, 2, 10, 16, 20)
    assert torch.isnan(g[0, 0, 0, 5, 5]) and torch.isnan(g[0, 0, 0, 5, 4])
    assert torch.isfinite(g[1]).all()


def _median_kernel_reference(x: np.ndarray) -> np.ndarray:
    """A literal transcription of DeMoN's median3x3_downsample kernel (an lmbspecialops op;
    docs/reference.md §3)."""
    H, W = x.shape
    out = np.empty(((H + 1) // 2, (W + 1) // 2))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            v = [x[min(max(2 * i + dy, 0), H - 1), min(max(2 * j + dx, 0), W - 1)]
                 for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
            for a in range(5):  # partial selection sort with '>' comparisons
                best = a
                for b in range(a + 1, 9):
                    if v[best] > v[b]:
                        best = b
                v[a], v[best] = v[best], v[a]
            out[i, j] = v[4]
    return out


@pytest.mark.parametrize("shape,nan", [((9, 13), 0.3), ((8, 12), 0.3), ((5, 4), 0.3), ((16, 16), 0.0),
                                       ((16, 16), 0.7), ((1, 1), 0.0), ((2, 3), 0.0)])
def test_median_downsample_matches_the_kernel_including_nan(shape, nan):
    rng = np.random.default_rng(9)
    x = rng.random(shape)
    x[rng.random(shape) < nan] = np.nan
    x[rng.random(shape) < 0.05] = np.inf
    ours = loss_maps.median_downsample(torch.from_numpy(x)[None, None])[0, 0].numpy()
    np.testing.assert_array_equal(ours, _median_kernel_reference(x))


def test_the_median_network_sorts_every_input():
    # 0-1 principle: a comparator network that sorts every sequence of 0s and 1s sorts every input.
    bits = torch.tensor(list(itertools.product([0.0, 1.0], repeat=9)))
    v = list(bits.T)
    for i, j in loss_maps.MEDIAN9_NETWORK:
        v[i], v[j] = torch.minimum(v[i], v[j]), torch.maximum(v[i], v[j])
    assert torch.equal(torch.stack(v, 1), bits.sort(dim=1).values)


def test_median_downsample_without_nan_is_the_median():
    x = torch.tensor([[[[5.0, 1, 9, 2], [7, 3, 4, 8], [6, 0, 2, 1]]]])
    # centre (0,0): clamped window [5,5,1,5,5,1,7,7,3] -> 5; centre (0,2): [1,9,2,1,9,2,3,4,8] -> 3
    # centre (2,0): [7,7,3,6,6,0,6,6,0] -> 6; centre (2,2): [3,4,8,0,2,1,0,2,1] -> 2
    torch.testing.assert_close(loss_maps.median_downsample(x), torch.tensor([[[[5.0, 3], [6, 2]]]]))


def test_inverse_depth_pyramid_sizes_and_invalid_pixels():
    inv = torch.rand(2, 1, 192, 256) + 0.1
    inv[:, :, :8, :8] = 0  # invalid marker 0 becomes NaN, not a median value
    levels = loss_maps.inverse_depth_pyramid(inv)
    assert [tuple(x.shape[2:]) for x in levels] == [(192, 256), (96, 128), (48, 64), (24, 32),
                                                     (12, 16), (6, 8)]
    assert torch.isnan(levels[0][:, :, :8, :8]).all() and torch.isnan(levels[2][:, :, 0, 0]).all()
    # DeMoN's kernel keeps a NaN centre, so the corner stays NaN up the pyramid; the rest is filled.
    assert torch.isnan(levels[5][:, :, 0, 0]).all()
    assert torch.isfinite(levels[5].flatten(2)[:, :, 1:]).all()


# ----------------------------------------------------------------------------- batching, dtypes


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batched_results_equal_per_sample_results(device, dtype):
    inv, motion, K = (x.to(device) for x in random_scene(3, 24, 32, dtype=dtype, seed=10))
    image = torch.rand(3, 3, 24, 32, dtype=dtype, device=device)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    outputs = {
        "flow": flow,
        "depth": geo.depth_from_flow_motion(flow, motion, K),
        "warp": warping.warp_image(image, flow),
        "normals": geo.normals_from_depth(inv, K),
    }
    for b in range(3):
        s = slice(b, b + 1)
        single = {
            "flow": geo.flow_from_depth_motion(inv[s], motion[s], K[s]),
            "depth": geo.depth_from_flow_motion(flow[s], motion[s], K[s]),
            "warp": warping.warp_image(image[s], flow[s]),
            "normals": geo.normals_from_depth(inv[s], K[s]),
        }
        for key, value in single.items():
            assert value.dtype == dtype and value.device.type == device
            torch.testing.assert_close(outputs[key][s], value, equal_nan=True)


# ----------------------------------------------------------------------------- gradients


def test_gradcheck_differentiable_functions():
    torch.manual_seed(11)
    inv, motion, K = random_scene(1, 5, 6, seed=11)
    inv.requires_grad_(True)
    motion.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d, m: geo.flow_from_depth_motion(d, m, K), (inv, motion))
    flow = geo.flow_from_depth_motion(inv, motion, K).detach().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f, m: geo.depth_from_flow_motion(f, m, K), (flow, motion))
    assert torch.autograd.gradcheck(geo.angle_axis_to_matrix, (motion[:, :3],))
    # (border pixels are NaN by definition: check the interior)
    assert torch.autograd.gradcheck(lambda d: geo.normals_from_depth(d, K)[..., 1:-1, 1:-1], (inv,))
    x = (torch.rand(1, 2, 5, 6, dtype=torch.float64) + 0.2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: loss_maps.scale_invariant_gradients(a, (1, 2)), (x,))
    image = torch.rand(1, 2, 6, 7, dtype=torch.float64, requires_grad=True)
    # sample positions away from integer pixels, where bilinear weights are smooth
    small = ((torch.rand(1, 2, 6, 7, dtype=torch.float64) * 0.6 + 0.2) / torch.tensor([7.0, 6.0],
             dtype=torch.float64).view(1, 2, 1, 1)).requires_grad_(True)
    assert torch.autograd.gradcheck(warping.warp_image, (image, small))


def test_gradients_are_finite_with_invalid_depth():
    inv, motion, K = random_scene(1, 6, 8, seed=12)
    inv[0, 0, 2, 2] = math.nan
    inv.requires_grad_(True)
    motion.requires_grad_(True)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    torch.nan_to_num(flow, nan=0.0).sum().backward()
    assert torch.isfinite(inv.grad).all() and torch.isfinite(motion.grad).all()
    assert inv.grad[0, 0, 2, 2] == 0


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("call, message", [
    (lambda: geo.flow_from_depth_motion(torch.rand(2, 24, 32), torch.rand(2, 6), K_DEMON.repeat(2, 1)),
     r"inv_depth: expected shape \(B, 1, H, W\)"),
    (lambda: geo.flow_from_depth_motion(torch.rand(2, 1, 4, 4), torch.rand(3, 6), K_DEMON.repeat(2, 1)),
     r"motion: expected batch size 2"),
    (lambda: geo.flow_from_depth_motion(torch.rand(1, 1, 4, 4), torch.rand(1, 7), K_DEMON.float()),
     r"motion: expected shape \(B, 6\)"),
    (lambda: geo.flow_from_depth_motion(torch.rand(1, 1, 4, 4), torch.rand(1, 6),
                                        torch.tensor([[math.nan, 1, 0.5, 0.5]])),
     r"intrinsics: expected finite"),
    (lambda: geo.depth_from_flow_motion(torch.rand(1, 3, 4, 4), torch.rand(1, 6), K_DEMON.float()),
     r"flow: expected shape \(B, 2, H, W\)"),
    (lambda: warping.warp_image(torch.rand(1, 3, 4, 4), torch.rand(1, 2, 4, 5)),
     r"flow: expected shape \(1, 2, 4, 4\)"),
    (lambda: geo.normals_from_depth(torch.rand(1, 1, 4, 4), torch.rand(2, 4)),
     r"intrinsics: expected batch size 1"),
    (lambda: geo.angle_axis_to_matrix(torch.rand(3)), r"r: expected shape \(B, 3\)"),
    (lambda: geo.matrix_to_angle_axis(torch.rand(2, 3)), r"R: expected shape \(B, 3, 3\)"),
    (lambda: geo.visibility_mask(torch.rand(1, 1, 4, 4), torch.rand(1, 6), K_DEMON.float(),
                                 torch.tensor([[1.0, 1, 0.5, math.inf]])),
     r"intrinsics2: expected finite"),
    (lambda: geo.flow_from_depth_motion(torch.ones(1, 1, 4, 4, dtype=torch.int64), torch.rand(1, 6),
                                        K_DEMON.float()),
     r"inv_depth: expected a float32 or float64"),
])
def test_bad_input_raises_value_error_naming_the_argument(call, message):
    with pytest.raises(ValueError, match=message):
        call()
