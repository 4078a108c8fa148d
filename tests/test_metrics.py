"""demon_lab.core.metrics: hand-computed expectations for DeMoN's evaluation protocol."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import random_scene, rotation_about

from demon_lab.core import geometry as geo
from demon_lab.core import metrics

LN2 = math.log(2.0)


# ----------------------------------------------------------------------------- depth


def test_depth_errors_hand_computed():
    pred = np.array([[1.0, 2.0], [4.0, np.nan]])
    gt = np.array([[2.0, 2.0], [2.0, 1.0]])
    e = metrics.depth_errors(pred, gt)
    # valid pixels: (p, g) = (1, 2), (2, 2), (4, 2); d = log p - log g = -ln2, 0, ln2
    assert e["n_valid"] == 3
    assert e["l1"] == pytest.approx((1 + 0 + 2) / 3)
    assert e["l1_inv"] == pytest.approx((0.5 + 0 + 0.25) / 3)
    assert e["l1_rel"] == pytest.approx((0.5 + 0 + 1) / 3)
    assert e["sq_rel"] == pytest.approx((1 / 2 + 0 + 4 / 2) / 3)
    assert e["sc_inv"] == pytest.approx(LN2 * math.sqrt(2 / 3))
    assert e["rmse"] == pytest.approx(math.sqrt(5 / 3))
    assert e["rmse_log"] == pytest.approx(LN2 * math.sqrt(2 / 3))
    assert e["log10"] == pytest.approx(2 * math.log10(2) / 3)
    assert e["delta_1.25"] == pytest.approx(1 / 3)


def test_depth_thresholds_are_strict_ratios():
    gt = np.ones(5)
    pred = np.array([1.2, 1 / 1.5, 1.9, 2.5, 1.25])  # ratios 1.2, 1.5, 1.9, 2.5 and exactly 1.25
    e = metrics.depth_errors(pred[None], gt[None])
    assert e["delta_1.25"] == pytest.approx(1 / 5)  # 1.25 itself is not < 1.25
    assert e["delta_1.25^2"] == pytest.approx(3 / 5)  # 1.2, 1.5, 1.25
    assert e["delta_1.25^3"] == pytest.approx(4 / 5)  # + 1.9


def test_sc_inv_ignores_a_global_scale():
    rng = np.random.default_rng(0)
    gt = rng.uniform(1, 5, (8, 9))
    pred = gt * np.exp(rng.normal(0, 0.1, gt.shape))
    assert metrics.depth_errors(3 * pred, gt)["sc_inv"] == pytest.approx(
        metrics.depth_errors(pred, gt)["sc_inv"], rel=1e-12)


@pytest.mark.parametrize("bad", [0.0, -1.0, np.inf, -np.inf, np.nan])
def test_invalid_pixels_in_either_map_are_ignored(bad):
    pred = np.array([[2.0, 3.0, 5.0]])
    gt = np.array([[2.0, 1.0, 5.0]])  # the middle pixel is wrong: it must not count
    p = pred.copy()
    p[0, 1] = bad
    e = metrics.depth_errors(p, gt)
    assert e["n_valid"] == 2 and e["l1"] == 0 and e["delta_1.25"] == 1
    g = gt.copy()
    g[0, 1] = bad
    e = metrics.depth_errors(pred, g)
    assert e["n_valid"] == 2 and e["l1"] == 0


def test_no_valid_pixel_gives_nan_and_zero_count():
    e = metrics.depth_errors(np.full((2, 2), np.nan), np.ones((2, 2)))
    assert e["n_valid"] == 0
    assert all(math.isnan(v) for k, v in e.items() if k != "n_valid")


def test_gt_depth_is_divided_by_the_baseline_unless_it_is_one():
    gt = np.array([[4.0, 8.0]])
    pred = np.array([[2.0, 4.0]])  # depth for a unit baseline when |t_gt| = 2
    assert metrics.depth_errors(pred, gt, gt_translation=[0, 2.0, 0])["l1"] == 0
    assert metrics.depth_errors(pred, gt, gt_translation=[0.6, 0, 0.8])["l1"] == pytest.approx(3)
    # |t| = 1 + 1e-9 is "close to 1": no division (DeMoN uses np.isclose)
    assert metrics.depth_errors(pred, gt, gt_translation=[1 + 1e-9, 0, 0])["l1"] == pytest.approx(3)
    e = metrics.depth_errors(pred, gt, gt_translation=[1.001, 0, 0])
    assert e["l1"] == pytest.approx(np.mean(np.abs(pred - gt / 1.001)))


@pytest.mark.parametrize("scaling", ["abs", "log", "inv"])
def test_least_squares_scalings_remove_a_global_scale(scaling):
    gt = np.array([[1.0, 2.0, 3.0, 4.0]])
    e = metrics.depth_errors(0.25 * gt, gt, scaling=scaling)
    assert e["l1"] == pytest.approx(0, abs=1e-12) and e["delta_1.25"] == 1


def test_least_squares_scales_hand_computed():
    p, g = np.array([1.0, 2.0]), np.array([2.0, 2.0])
    assert metrics.depth_scale(p, g, "abs") == pytest.approx((2 + 4) / (1 + 4))
    assert metrics.depth_scale(p, g, "log") == pytest.approx(math.exp((LN2 + 0) / 2))
    assert metrics.depth_scale(p, g, "inv") == pytest.approx(1 / ((1 / 2 + 1 / 4) / (1 + 1 / 4)))
    e = metrics.depth_errors(p[None], g[None], scaling="abs")
    assert e["l1"] == pytest.approx((abs(1.2 - 2) + abs(2.4 - 2)) / 2)


def test_depth_errors_bad_input():
    with pytest.raises(ValueError, match="gt_depth: expected shape"):
        metrics.depth_errors(np.ones((2, 3)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="scaling: expected one of"):
        metrics.depth_errors(np.ones((2, 2)), np.ones((2, 2)), scaling="median")
    with pytest.raises(ValueError, match=r"pred_depth: expected shape \(N, N\)"):
        metrics.depth_errors(np.ones(4), np.ones(4))


# ----------------------------------------------------------------------------- motion


def _motion(r, t) -> np.ndarray:
    return np.concatenate([np.asarray(r, float), np.asarray(t, float)])


def test_motion_errors_identical_and_scaled_translation():
    gt = _motion(rotation_about([1, 2, 3], 20), [0.3, -0.1, 0.5])
    e = metrics.motion_errors(_motion(gt[:3], 5 * gt[3:]), gt)
    assert e["rot_deg"] == pytest.approx(0, abs=1e-6)
    assert e["tran_deg"] == pytest.approx(0, abs=1e-6)
    assert e["tran_dist"] == pytest.approx(0, abs=1e-12)


def test_rotation_error_is_the_relative_angle():
    gt = _motion(rotation_about([0, 0, 1], 90), [1, 0, 0])
    assert metrics.motion_errors(_motion([0, 0, 0], [1, 0, 0]), gt)["rot_deg"] == pytest.approx(90)
    # +179 and -179 degrees about the same axis are 2 degrees apart, not 358
    gt = _motion(rotation_about([0, 0, 1], 179), [1, 0, 0])
    pred = _motion(rotation_about([0, 0, 1], -179), [1, 0, 0])
    assert metrics.motion_errors(pred, gt)["rot_deg"] == pytest.approx(2)
    assert metrics.motion_errors(gt, pred)["rot_deg"] == pytest.approx(2)
    # 10 degrees about x against 10 degrees about y: the composed relative rotation
    a = geo.angle_axis_to_matrix(torch.from_numpy(rotation_about([1, 0, 0], 10))[None])[0].numpy()
    b = geo.angle_axis_to_matrix(torch.from_numpy(rotation_about([0, 1, 0], 10))[None])[0].numpy()
    expected = math.degrees(math.acos((np.trace(a @ b.T) - 1) / 2))
    e = metrics.motion_errors(_motion(rotation_about([0, 1, 0], 10), [1, 0, 0]),
                              _motion(rotation_about([1, 0, 0], 10), [1, 0, 0]))
    assert e["rot_deg"] == pytest.approx(expected, rel=1e-9)


def test_near_identity_rotations():
    t = [0, 0, 1]
    # below 1e-6 rad an angle-axis vector is the identity (DeMoN's quaternion conversion)
    assert metrics.motion_errors(_motion([5e-7, 0, 0], t), _motion([0, 0, 0], t))["rot_deg"] == 0
    e = metrics.motion_errors(_motion([2e-5, 0, 0], t), _motion([0, 0, 0], t))
    assert e["rot_deg"] == pytest.approx(math.degrees(2e-5), rel=1e-6)


def test_translation_errors_opposite_and_orthogonal():
    gt = _motion([0, 0, 0], [0, 0, 2])
    e = metrics.motion_errors(_motion([0, 0, 0], [0, 0, -0.5]), gt)
    assert e["tran_deg"] == pytest.approx(180) and e["tran_dist"] == pytest.approx(2)
    e = metrics.motion_errors(_motion([0, 0, 0], [3, 0, 0]), gt)
    assert e["tran_deg"] == pytest.approx(90) and e["tran_dist"] == pytest.approx(math.sqrt(2))


def test_tiny_predicted_translation_is_not_normalised():
    gt = _motion([0, 0, 0], [0, 0, 2])
    e = metrics.motion_errors(_motion([0, 0, 0], [0, 0, 1e-7]), gt)
    # |t_pred| <= 1e-6 stays as it is: the dot product is ~1e-7, so ~90 degrees, distance ~1
    assert e["tran_deg"] == pytest.approx(math.degrees(math.acos(1e-7)))
    assert e["tran_dist"] == pytest.approx(1 - 1e-7)
    e = metrics.motion_errors(_motion([0, 0, 0], [0, 0, 2e-6]), gt)  # just above: normalised
    assert e["tran_deg"] == pytest.approx(0) and e["tran_dist"] == pytest.approx(0)


def test_zero_gt_translation_gives_nan_translation_errors():
    e = metrics.motion_errors(_motion([0, 0, 0], [1, 0, 0]), _motion([0, 0, 0], [0, 0, 0]))
    assert math.isnan(e["tran_deg"]) and math.isnan(e["tran_dist"]) and e["rot_deg"] == 0


# ----------------------------------------------------------------------------- flow


def test_flow_epe_drops_exact_zeros_and_nan():
    gt = np.zeros((2, 2, 2))
    pred = np.zeros((2, 2, 2))
    pred[:, 0, 0] = [3, 4]  # error 5
    pred[:, 0, 1] = [0.6, 0.8]  # error 1
    gt[:, 1, 0] = np.nan  # unknown
    # pixel (1, 1) has exactly zero error and is dropped, as in DeMoN
    assert metrics.flow_epe(pred, gt) == pytest.approx(3.0)
    assert math.isnan(metrics.flow_epe(gt, gt))


# ----------------------------------------------------------------------------- protocol


@pytest.mark.parametrize("shape_in, shape_out", [((48, 64), (480, 640)), ((192, 256), (480, 640)),
                                                 ((6, 8), (192, 256)), ((48, 64), (500, 741))])
def test_resize_nearest_matches_skimage_order_0(shape_in, shape_out):
    from skimage.transform import resize

    x = np.random.default_rng(1).random(shape_in)
    np.testing.assert_array_equal(metrics.resize_nearest(x, shape_out),
                                  resize(x, shape_out, order=0))


def test_mask_invisible_sets_pixels_leaving_image_2_to_nan():
    inv = np.full((4, 10), 0.5)
    # camera 2 moved right by 0.5 at depth 2 with fx/W = 1: points shift left by 0.25 of the width
    out = metrics.mask_invisible(inv, [0, 0, 0, -0.5, 0, 0], (1.0, 1.0, 0.5, 0.5))
    u = (np.arange(10) + 0.5) / 10
    np.testing.assert_array_equal(np.isnan(out[0]), u - 0.25 <= 0)
    assert (out[~np.isnan(out)] == 0.5).all()


def _gt_sample(seed: int = 0, baseline: float = 2.0):
    inv, motion, K = random_scene(1, 48, 64, seed=seed)
    motion[:, 3:] *= baseline / motion[:, 3:].norm()
    return {"inv_depth": inv[0, 0].numpy(), "motion": motion[0].numpy(), "intrinsics": K[0].numpy()}


def test_evaluate_sample_perfect_prediction_scores_zero():
    gt = _gt_sample()
    baseline = np.linalg.norm(gt["motion"][3:])
    gt_flow = geo.flow_from_depth_motion(torch.from_numpy(gt["inv_depth"])[None, None],
                                         torch.from_numpy(gt["motion"])[None],
                                         torch.from_numpy(gt["intrinsics"])[None])[0].numpy()
    pred = {
        "inv_depth": gt["inv_depth"] * baseline,  # the network predicts for a unit baseline
        "motion": np.concatenate([gt["motion"][:3], gt["motion"][3:] / baseline]),
        "flow": gt_flow + np.array([0.003, 0.004])[:, None, None],
    }
    e = metrics.evaluate_sample(pred, gt)
    for key in ("l1", "l1_inv", "sc_inv", "l1_rel", "rot_deg", "tran_deg"):
        assert e[key] == pytest.approx(0, abs=1e-6), key
    assert e["delta_1.25"] == 1
    assert e["epe"] == pytest.approx(0.005)
    visible = geo.visibility_mask(torch.from_numpy(gt["inv_depth"])[None, None],
                                  torch.from_numpy(gt["motion"])[None],
                                  torch.from_numpy(gt["intrinsics"])[None]).sum().item()
    assert e["n_valid"] == visible < 48 * 64
    assert metrics.evaluate_sample(pred, gt, depthmask=False)["n_valid"] == 48 * 64
    # twice the depth everywhere: L1-rel is exactly 1
    assert metrics.evaluate_sample({"inv_depth": pred["inv_depth"] / 2}, gt)["l1_rel"] == pytest.approx(1)


def test_evaluate_sample_upsamples_the_prediction_by_nearest_neighbour():
    gt = _gt_sample(seed=1, baseline=1.0)
    coarse = np.random.default_rng(2).uniform(0.2, 0.5, (12, 16))
    gt["inv_depth"] = np.kron(coarse, np.ones((4, 4)))  # piecewise constant in 4x4 blocks
    e = metrics.evaluate_sample({"inv_depth": coarse}, gt, depthmask=False)
    assert e["l1"] == pytest.approx(0, abs=1e-12) and e["n_valid"] == 48 * 64


def test_evaluate_set_rows_and_means():
    gts = [_gt_sample(seed=s) for s in range(3)]
    preds = []
    for g, factor in zip(gts, (1.0, 2.0, 4.0)):
        baseline = np.linalg.norm(g["motion"][3:])
        preds.append({"inv_depth": g["inv_depth"] * baseline / factor, "motion": g["motion"]})
    preds[2]["inv_depth"] = np.full((48, 64), np.nan)  # nothing valid: a failed sample
    rows, means = metrics.evaluate_set(preds, gts, ids=["a", "b", "c"])
    assert [r["id"] for r in rows] == ["a", "b", "c"]
    assert rows[0]["l1_rel"] == pytest.approx(0, abs=1e-12)
    assert rows[1]["l1_rel"] == pytest.approx(1)
    assert means["l1_rel"] == pytest.approx(0.5)  # mean over the samples where it is defined
    assert means["n_failed_l1_rel"] == 1 and means["n_samples"] == 3
    assert means["rot_deg"] == pytest.approx(0, abs=1e-6)
    with pytest.raises(ValueError, match="preds: expected 3 predictions"):
        metrics.evaluate_set(preds[:2], gts)
