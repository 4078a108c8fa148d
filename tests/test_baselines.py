"""The classical baselines: exact two-view geometry on exact correspondences, robustness to
outliers, plane sweep on a rendered scene, recorded failures on degenerate pairs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from demon_lab import geometry as geo
from demon_lab import metrics
from demon_lab.baselines import BaselineConfig, BaselineFailure, evaluate_baseline, summarize_baseline
from demon_lab.baselines import methods as M
from demon_lab.baselines import twoview as T
from demon_lab.data import synthetic as syn
from demon_lab.data.datasets import SyntheticDataset
from demon_lab.data.sample import make_sample, normalize_translation
from tests.conftest import random_scene


def correspondences(seed: int = 0, h: int = 96, w: int = 128):
    """Pixel correspondences from an exact depth + motion, and the motion and intrinsics."""
    inv, motion, k = random_scene(1, h, w, seed=seed)
    flow = geo.flow_from_depth_motion(inv, motion, k)[0].numpy()
    ys, xs = np.mgrid[0:h, 0:w]
    x1 = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    x2 = x1 + np.stack([flow[0].ravel() * w, flow[1].ravel() * h], 1)
    return x1, x2, motion[0].numpy(), k[0].numpy(), inv[0, 0].numpy(), flow


def test_pixel_intrinsics_matches_demon_projection():
    x1, x2, motion, k, inv, _ = correspondences()
    K = T.pixel_intrinsics(k, 96, 128)
    R = geo.angle_axis_to_matrix(torch.from_numpy(motion[None, :3]))[0].numpy()
    # Re-project pixel (x, y) with depth 1/inv through K [R | t]: must land on x2.
    ray = np.linalg.solve(K, np.concatenate([x1, np.ones((len(x1), 1))], 1).T)
    X = ray / inv.ravel()[None]
    p = K @ (R @ X + motion[3:, None])
    np.testing.assert_allclose((p[:2] / p[2]).T, x2, atol=1e-6)


def test_eight_point_satisfies_the_epipolar_constraint_of_exact_points():
    x1, x2, *_ = correspondences()
    F = T.eight_point(x1[::37], x2[::37])
    assert np.linalg.matrix_rank(F, tol=1e-9) == 2
    assert np.median(T.sampson_distance(F, x1, x2)) < 1e-6


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("outlier_share, rot_tol, tran_tol", [(0.0, 0.2, 0.5), (0.3, 2.5, 10.0)])
def test_ransac_recovers_the_motion_through_outliers(seed, outlier_share, rot_tol, tran_tol):
    """0.1 px noise: near-exact motion. With 30 % outliers the few that land within the threshold
    of their epipolar line (the 8-point fit is algebraic, not robust to those) cost degrees."""
    x1, x2, motion, k, *_ = correspondences(seed)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(x1), 1500, replace=False)
    x1, x2 = x1[pick], x2[pick].copy()
    outliers = rng.random(len(x2)) < outlier_share
    x2[outliers] += rng.uniform(-30, 30, (outliers.sum(), 2))
    x2[~outliers] += rng.normal(0, 0.1, ((~outliers).sum(), 2))
    F, inliers = T.ransac_fundamental(x1, x2, threshold=1.0, iterations=500, seed=seed)
    # An outlier offset along its epipolar line is consistent with F: a few percent pass by chance.
    assert (inliers & outliers).sum() <= 0.1 * outliers.sum() and (inliers & ~outliers).sum() > 0.9 * (~outliers).sum()
    estimate = T.motion_from_fundamental(F, x1, x2, T.pixel_intrinsics(k, 96, 128), inliers)
    errors = metrics.motion_errors(estimate, motion)
    assert errors["rot_deg"] < rot_tol and errors["tran_deg"] < tran_tol, errors


def test_ransac_with_too_few_points_is_a_failure_not_a_crash():
    x1, x2, *_ = correspondences()
    with pytest.raises(BaselineFailure, match="8-point"):
        T.ransac_fundamental(x1[:5], x2[:5], 1.0)


def test_triangulated_depth_of_exact_flow_is_exact():
    _, _, motion, k, inv, flow = correspondences()
    flow_px = np.stack([flow[0] * 128, flow[1] * 96], -1)
    unit = np.concatenate([motion[:3], motion[3:] / np.linalg.norm(motion[3:])])
    estimate = T.depth_from_pixel_flow(flow_px, np.ones((96, 128), bool), unit, k)
    np.testing.assert_allclose(estimate, inv * np.linalg.norm(motion[3:]), rtol=1e-6)


def test_base_mat_f_on_exact_flow_recovers_motion_and_depth():
    _, _, motion, k, inv, flow = correspondences()
    sample = {"intrinsics": torch.from_numpy(k)}
    out = M.base_mat_f(sample, BaselineConfig(), torch.from_numpy(flow))
    errors = metrics.motion_errors(out["motion"], motion)
    assert errors["rot_deg"] < 0.05 and errors["tran_deg"] < 0.5, errors
    truth = {"inv_depth": torch.from_numpy(inv), "motion": torch.from_numpy(motion), "intrinsics": torch.from_numpy(k)}
    scores = metrics.evaluate_sample({"inv_depth": out["inv_depth"], "motion": out["motion"]}, truth)
    assert scores["l1_rel"] < 0.01 and scores["sc_inv"] < 0.01, scores


@pytest.fixture(scope="module")
def sun3d_test_pairs(tmp_path_factory):
    """The first 12 synthetic_sun3d test pairs at the cpu scale and at 256x192, with each pair's
    median triangulation angle (degrees)."""
    from demon_lab.data_stats import pair_statistics

    cache = tmp_path_factory.mktemp("data")
    low = SyntheticDataset(preset="synthetic_sun3d", split="test", length=12, size=[96, 128], cache_dir=str(cache))
    high = SyntheticDataset(preset="synthetic_sun3d", split="test", length=12, size=[192, 256], cache_dir=str(cache))
    return low, high, [pair_statistics(low.load(i))["tri_deg"] for i in range(len(low))]


@pytest.fixture(scope="module")
def sun3d_like(sun3d_test_pairs):
    """The first three of them whose triangulation angle is at least 3° (with less parallax the
    depth is barely observable from any method)."""
    from torch.utils.data import Subset

    low, high, tri = sun3d_test_pairs
    keep = [i for i, t in enumerate(tri) if t >= 3][:3]
    assert len(keep) == 3
    return Subset(low, keep), Subset(high, keep)


def test_plane_sweep_with_true_motion_finds_the_depth_of_a_rendered_scene(sun3d_like):
    low, high = sun3d_like
    rows, _ = evaluate_baseline("base_oracle", low, BaselineConfig(), inputs=high)
    summary = summarize_baseline(rows)
    assert summary["n_failed"] == 0
    assert summary["rot_deg"] == 0 and summary["tran_deg"] < 1e-3
    # A constant-depth guess (the GT median) is the bar the sweep must clear by far.
    constant = []
    for i in range(len(low)):
        s = low[i]
        gt = s["inv_depth"][0]
        guess = torch.full_like(gt, float(torch.nanmedian(gt[gt > 0])))
        truth = {"inv_depth": gt, "motion": s["motion"], "intrinsics": s["intrinsics"]}
        constant.append(metrics.evaluate_sample({"inv_depth": guess}, truth)["l1_inv"])
    assert summary["l1_inv"] < 0.5 * np.mean(constant), (summary["l1_inv"], constant)


def test_base_ff_and_base_sift_on_rendered_pairs(sun3d_like, sun3d_test_pairs):
    low, _ = sun3d_like
    for method in ("base_ff", "base_sift"):
        rows, _ = evaluate_baseline(method, low, BaselineConfig(), keep=1)
        assert len(rows) == len(low)
        for row in rows:  # a result or a recorded failure (too few matches at 128x96), never a crash
            assert row["failed"] or (math.isfinite(row["rot_deg"]) and math.isfinite(row["l1_inv"]))
    # On the first pair of moderate parallax (triangulation angle 1.5-3°: DIS follows its flow at
    # 128x96; the close scenes of larger angles have parallax that DIS does not) the motion comes
    # out right.
    from torch.utils.data import Subset

    all_pairs, _, tri = sun3d_test_pairs
    moderate = next(i for i, t in enumerate(tri) if 1.5 <= t < 3)
    row = evaluate_baseline("base_ff", Subset(all_pairs, [moderate]), BaselineConfig())[0][0]
    assert not row["failed"] and row["rot_deg"] < 1 and row["tran_deg"] < 25, row


def test_degenerate_pairs_are_recorded_failures(sun3d_like):
    low, _ = sun3d_like

    class Degenerate(torch.utils.data.Dataset):
        """Flat grey images (no texture) and a zero-baseline pair (identical cameras)."""

        def __len__(self):
            return 2

        def __getitem__(self, i):
            s = dict(low[0])
            s["id"] = f"degenerate{i}"
            if i == 0:
                s["image1"] = torch.zeros_like(s["image1"])
                s["image2"] = torch.zeros_like(s["image2"])
            else:
                s["image2"] = s["image1"].clone()
                s["motion"] = torch.zeros(6)
            return s

    for method in ("base_ff", "base_sift", "base_oracle"):
        rows, _ = evaluate_baseline(method, Degenerate(), BaselineConfig())
        summary = summarize_baseline(rows)
        assert summary["n_samples"] == 2
        assert summary["n_failed"] >= 1, (method, rows)
        assert all(isinstance(r["failed"], str) for r in rows)


def controlled_pair(preset: str, seed: int, size=(192, 256), baseline: float = 0.08, yaw: float = 2.0):
    """A rendered synthetic scene seen by its first camera and by that camera moved sideways by
    ``baseline`` x the median depth and turned by ``yaw`` degrees: known motion, exact depth."""
    _, scene, cam1, _ = syn.render_pair(preset, seed, size=(24, 32), return_scene=True)
    _, coarse, _ = syn.render_view(scene, cam1, (24, 32), supersample=1)
    median = float(np.median(coarse[np.isfinite(coarse)]))
    turn = syn._rot_axis(np.array([0.0, 1.0, 0.0]), math.radians(yaw))
    cam2 = syn.Camera(turn @ cam1.rotation, cam1.center + baseline * median * cam1.rotation[0])
    image1, depth1, points1 = syn.render_view(scene, cam1, size)
    image2, _, _ = syn.render_view(scene, cam2, size)
    u8 = lambda im: np.floor(np.clip(im, 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    with np.errstate(divide="ignore"):
        inv1 = np.where(np.isfinite(depth1), 1.0 / depth1, np.nan).astype(np.float32)
    visible = syn.visibility(scene, points1, np.isfinite(depth1).reshape(-1), cam2, size).reshape(size)
    sample = make_sample(f"{preset}/controlled{seed}", u8(image1), u8(image2), syn.INTRINSICS, inv1,
                         syn.relative_motion(cam1, cam2), visible=visible)
    return normalize_translation(sample)


@pytest.fixture(scope="module")
def known_motion_pair():
    """A room (textured walls and floor: several planes, 309 SIFT keypoints at 256x192). Outdoor
    scenes of scene generator 5 put nearly every keypoint on the ground plane, a degenerate
    configuration for the fundamental matrix (scenes11 seeds 0-3: Base-SIFT rotation 3-6 deg)."""
    return controlled_pair("synthetic_sun3d", 1)


@pytest.mark.parametrize("method", ["base_ff", "base_sift", "base_mat_f"])
def test_each_baseline_recovers_a_known_motion(known_motion_pair, method):
    """Rotation within 1 degree and translation direction within 5 degrees on a textured scene
    (base_mat_f is given the exact flow in place of DeMoN's)."""
    s = known_motion_pair
    cfg = BaselineConfig()
    if method == "base_mat_f":
        out = M.base_mat_f(s, cfg, s["flow"])
    else:
        out = getattr(M, method)(s, cfg)
    errors = metrics.motion_errors(out["motion"], s["motion"].numpy())
    assert errors["rot_deg"] < 1.0 and errors["tran_deg"] < 5.0, errors


def test_base_oracle_recovers_the_depth_of_a_textured_scene():
    s = controlled_pair("synthetic_sun3d", 0)
    out = M.base_oracle(s, BaselineConfig())
    truth = {"inv_depth": s["inv_depth"][0], "motion": s["motion"], "intrinsics": s["intrinsics"]}
    scores = metrics.evaluate_sample(out, truth)
    assert scores["l1_rel"] < 0.05 and scores["rot_deg"] == 0 and scores["tran_deg"] < 1e-3, scores


def _test_entry(dataset) -> dict:
    """The config entry of ``sun3d_test_pairs``' 96x128 set (its cache folder included)."""
    return {"_target_": "demon_lab.data.datasets.SyntheticDataset", "preset": "synthetic_sun3d", "split": "test",
            "length": len(dataset), "size": [96, 128], "cache_dir": str(dataset.cache.parents[1])}


def test_baselines_read_each_pair_at_baseline_size_and_score_on_the_chains_ground_truth(sun3d_test_pairs):
    from demon_lab.data.datasets import MiddleburyDataset
    from demon_lab.evaluate import baseline_inputs

    low, high, _ = sun3d_test_pairs
    entry = _test_entry(low)
    native = baseline_inputs(entry, low, "native")  # rendered scenes: DeMoN's 256x192
    assert native.size == (192, 256) and native is not low
    assert torch.equal(native[3]["image1"], high[3]["image1"])
    assert baseline_inputs(entry, low, [96, 128]) is low
    assert baseline_inputs(entry, low, [48, 64])[0]["image1"].shape == (3, 48, 64)
    # A source with a resolution of its own is read at it (the Middlebury pair: 741x500 as shipped),
    # with DeMoN's intrinsics when the chain's set has them (the same crop, at the native size).
    entry_mb = {"_target_": "demon_lab.data.datasets.MiddleburyDataset", "size": [96, 128]}
    stored = MiddleburyDataset()[0]
    native_mb = baseline_inputs(entry_mb, MiddleburyDataset(size=[96, 128]), "native")[0]
    assert native_mb["image1"].shape == stored["image1"].shape != (3, 96, 128)
    assert torch.equal(native_mb["intrinsics"], stored["intrinsics"])
    fixed = baseline_inputs({**entry_mb, "fixed_intrinsics": True},
                            MiddleburyDataset(size=[96, 128], fixed_intrinsics=True), "native")[0]
    assert fixed["image1"].shape == stored["image1"].shape
    torch.testing.assert_close(fixed["intrinsics"].double(), torch.tensor(geo.DEMON_INTRINSICS).double())
    unsized = MiddleburyDataset()
    assert baseline_inputs({"_target_": "demon_lab.data.datasets.MiddleburyDataset"}, unsized, "native") is unsized
    # Scored on the chain's ground truth: the same rows as scoring the 256x192 prediction by hand.
    from torch.utils.data import Subset

    pick = [0, 1]
    rows, kept = evaluate_baseline("base_oracle", Subset(low, pick), BaselineConfig(), inputs=Subset(high, pick),
                                   keep=1)
    for i, row in zip(pick, rows, strict=True):
        pred = M.base_oracle(high[i], BaselineConfig())
        assert pred["inv_depth"].shape == (192, 256)
        truth = metrics.ground_truth(low[i], low)
        truth.pop("flow")
        assert row["l1_inv"] == metrics.evaluate_sample(pred, truth, **metrics.protocol(low))["l1_inv"]
    assert kept[0]["inv_depth"].shape == (96, 128)  # shown beside the chain's image 1
    with pytest.raises(ValueError, match="inputs: expected the 2 pairs"):
        evaluate_baseline("base_ff", Subset(low, pick), BaselineConfig(), inputs=high)


def test_a_baseline_job_reads_its_pairs_at_baseline_size(sun3d_test_pairs, monkeypatch):
    """``evaluate_test_sets`` with a baseline method: the pairs reach the method at ``baseline.size``
    and are scored on the chain's test set."""
    from omegaconf import OmegaConf

    from demon_lab import evaluate, resources

    low, _, _ = sun3d_test_pairs
    seen = []
    real = M.base_oracle
    monkeypatch.setattr("demon_lab.baselines.base_oracle", lambda s, c: seen.append(s["image1"].shape) or real(s, c))
    entry = _test_entry(low)
    for size, shape in (("native", (3, 192, 256)), ([96, 128], (3, 96, 128))):
        cfg = OmegaConf.create({"method": "base_oracle", "seed": 0, "iterations": 3, "oracle": None,
                                "data": {"test": [entry], "size": [96, 128]},
                                "baseline": {**OmegaConf.to_container(OmegaConf.load(
                                    resources.CONF / "baseline" / "default.yaml")), "size": size},
                                "eval": {"visualize": 0, "point_clouds": 0, "max_samples": 1, "batch_size": 1}})
        seen.clear()
        (result,) = evaluate.evaluate_test_sets(cfg, None, refined=False)
        assert seen == [shape] and result.summary["n_samples"] == 1 and result.summary["n_failed"] == 0, size
