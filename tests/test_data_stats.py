"""python -m demon_lab.data_stats: the statistics of a data set and their reference scores."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import SUN3D_PAIR
from data_helpers import _photometric_error

from demon_lab.core import geometry as geo
from demon_lab.data import sample as smp
from demon_lab.data import synthetic
from demon_lab.data.datasets import (
    PairFolderDataset,
)


def _run_stats(*args):
    return subprocess.run([sys.executable, "-m", "demon_lab.data_stats", *args],
                          capture_output=True, text=True)


@pytest.mark.slow
def test_data_stats_command_writes_json(tmp_path):
    import json

    out = tmp_path / "stats.json"
    result = _run_stats("data=synthetic_mvs", "n=6", "data.size=[24,32]", "data.cache_dir=false", f"out={out}")
    assert result.returncode == 0, result.stderr
    stats = json.loads(out.read_text())
    for key in ("n_pairs", "rot_mean_deg", "rot_std_deg", "tri_mean_deg", "tri_std_deg",
                "valid_fraction", "visible_fraction", "median_depth", "zero_flow_epe", "constant_depth_sc_inv",
                "tran_x_negative_fraction", "photometric_error", "near_camera2_fraction"):
        assert key in stats
    assert stats["n_pairs"] == 6 and stats["outdoor"] == "yes" and stats["perfect_gt"] == "yes"
    assert "Rot. avg" in result.stdout and "synthetic_mvs" in result.stdout


def test_zero_flow_epe_is_the_mean_ground_truth_flow_length(rendered):
    from demon_lab.tools.data_stats import pair_statistics

    rendered = rendered[0]
    flow = rendered["flow"]
    length = flow.double().norm(dim=0)
    keep = torch.isfinite(length) & (length > 0)
    stats = pair_statistics(rendered)
    assert stats["zero_flow_epe"] == pytest.approx(float(length[keep].mean()), rel=1e-9)
    assert stats["tran_x_negative"] == float(rendered["motion"][3] < 0)
    assert stats["photometric_error"] == pytest.approx(_photometric_error(rendered)[0] * 255, rel=1e-6)


def test_constant_depth_sc_inv_is_the_sc_inv_of_a_constant_prediction(rendered):
    from demon_lab.core import metrics
    from demon_lab.tools.data_stats import pair_statistics

    sample = rendered[0]
    gt = {"inv_depth": sample["inv_depth"][0].numpy(), "motion": sample["motion"].numpy(),
          "intrinsics": sample["intrinsics"].numpy()}
    for constant in (0.3, 2.0):
        scored = metrics.evaluate_sample({"inv_depth": np.full_like(gt["inv_depth"], constant)}, gt, depthmask=False)
        assert pair_statistics(sample)["constant_depth_sc_inv"] == pytest.approx(scored["sc_inv"], rel=1e-6)


@pytest.mark.parametrize("t_z, near", [(-0.5, 0.0), (-0.95, 1.0), (-1.5, 1.0)])
def test_pairs_with_points_near_or_behind_camera_2_are_counted(t_z, near):
    """Every point at depth 1 in view 1; camera 2 moves forward by -t_z: z2 = 1 + t_z."""
    from demon_lab.tools.data_stats import pair_statistics

    image = np.zeros((8, 8, 3), np.uint8)
    sample = smp.make_sample("plane", image, image, geo.DEMON_INTRINSICS, np.ones((8, 8)), [0, 0, 0, 0, 0, t_z])
    stats = pair_statistics(sample)
    assert stats["near_camera2"] == near
    if near:  # DeMoN's GT flow has no check of z2: it explodes there
        assert float(torch.nan_to_num(sample["flow"]).abs().max()) > 1


def test_depth_ratio_filter_rejects_points_near_camera_2():
    """Camera 2 at the origin looking down +z: a point at z2 = 0.5 passes for depth1 = 4 (ratio
    0.125), fails for depth1 = 6 (0.083) and for any point behind the camera."""
    camera = synthetic.Camera(rotation=np.eye(3), center=np.zeros(3))
    ok = lambda z2, z1: synthetic.depth_ratio_ok(np.array([[0.1, 0.2, z2]]), np.array([z1]), camera, 0.1)  # noqa: E731
    assert ok(0.5, 4.0) and not ok(0.5, 6.0) and not ok(-0.5, 1.0)


@pytest.mark.slow
@pytest.mark.parametrize("args, message", [
    (["data=pair_folder", "data.path=/does/not/exist"], "/does/not/exist: no such file or directory"),
    (["data=demon_h5"], "Missing mandatory value"),
    (["n=0"], "n: expected a positive integer"),
])
def test_data_stats_bad_input_is_one_line(args, message):
    result = _run_stats(*args)
    assert result.returncode == 2
    assert message in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_data_stats_scores_the_classical_priors_on_the_real_pair():
    """``priors=true``: the DIS prior flows match the bundled SUN3D pair far better than zero flow, and
    the RANSAC motion the tight-threshold ``ransac_prior`` reads from them is within a few degrees
    (the pair's own camera motion is known)."""
    from demon_lab.tools.data_stats import FLOW_PRIORS, dataset_statistics, format_priors, pair_statistics

    dataset = PairFolderDataset(SUN3D_PAIR)
    stats = dataset_statistics([dataset], 1, priors=True)
    zero = pair_statistics(dataset.load(0))["zero_flow_epe"]
    for name in FLOW_PRIORS:
        assert stats[f"{name}_epe"] < 0.5 * zero
        assert stats[f"{name}_ransac_prior_tran_deg"] < 10 and stats[f"{name}_ransac_prior_rot_deg"] < 1
    assert "dis_x2" in format_priors(stats) and "ransac_prior tran" in format_priors(stats)
    assert "dis_epe" not in dataset_statistics([dataset], 1)
