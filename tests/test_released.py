"""DeMoN's released model without TensorFlow: the compat mode's special layers against literal
transcriptions of DeMoN's kernels (tests/lmbspecialops_reference.py), its net inputs, the
``model.weights`` keys and jobs, DeMoN's data files as configs and their evaluation protocol."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import table_rows

from demon_lab.__main__ import check
from demon_lab.core import geometry as geo
from demon_lab.core import metrics, warping
from demon_lab.nets import DeMoN
from demon_lab.nets.chain import depth_motion_net_inputs, flow_net_inputs
from tests.jobs import cli, client, compose_config, settings, smoke_overrides

K = torch.tensor([[0.89115971, 1.18821287, 0.5, 0.5]])


def test_compat_warp_is_warp2ds_loop_including_positions_just_left_of_the_image():
    import lmbspecialops_reference as ref

    rng = np.random.default_rng(0)
    image = rng.uniform(-0.5, 0.5, (2, 3, 6, 8)).astype(np.float32)
    flow = (rng.standard_normal((2, 2, 6, 8)) * 0.3).astype(np.float32)
    flow[0, 0, :, 0] = -0.4 / 8  # x + W fx = -0.4: in (-1, 0), truncated to 0, extrapolated
    flow[0, 1, 1:, 0] = 0.0
    flow[0, 1, 0, :] = -0.7 / 6  # y in (-1, 0)
    flow[1, 0, 2, 2] = (8 - 1 - 2 - 0.01) / 8  # just inside the right border (x0 + 1 = 7 < 8)
    flow[1, 1, 2, 2] = 0.0
    flow[1, 0, 3, 3] = (8 - 1 - 3) / 8  # x0 + 1 = 8: outside
    flow[1, :, 4, 4] = np.nan
    ours = warping.warp2d(torch.from_numpy(image), torch.from_numpy(flow)).numpy()
    theirs = ref.warp2d(image, flow)
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-6)
    # x = -0.4 in rows 1-4 (y0 + 1 < H): weights 1.4 and -0.4 on pixels 0 and 1 (an extrapolation),
    # where demon_lab's default warp gives 0
    a = np.float32(-0.4)
    np.testing.assert_allclose(ours[0, :, 1:5, 0], (1 - a) * image[0, :, 1:5, 0] + a * image[0, :, 1:5, 1], atol=1e-6)
    default = warping.warp_image(torch.from_numpy(image), torch.from_numpy(flow)).numpy()
    assert np.all(default[0, :, :, 0] == 0) and np.all(ours[0, :, 5, 0] == 0)
    assert np.all(ours[1, :, 4, 4] == 0) and np.all(ours[1, :, 3, 3] == 0) and np.all(ours[1, :, 2, 2] != 0)


def test_compat_geometry_is_demons_kernels():
    """warp2d and depth_to_flow as the graph's transcription computes them; flow_to_depth equal to
    the exact least-squares triangulation and within float32 rounding of DeMoN's float32 solve on
    well-conditioned pixels."""
    import lmbspecialops_reference as ref

    from demon_lab.core import geometry as geo

    rng = np.random.default_rng(2)
    image = rng.uniform(-0.5, 0.5, (1, 3, 12, 16)).astype(np.float32)
    flow = (rng.standard_normal((1, 2, 12, 16)) * 0.2).astype(np.float32)
    flow[0, :, 0, :4] = -0.5 / 16  # positions in (-1, 0)
    flow[0, 0, 1, 1] = np.nan
    assert np.array_equal(warping.warp2d(torch.from_numpy(image), torch.from_numpy(flow)).numpy(),
                          ref.warp2d(image, flow))
    inv = (1 / rng.uniform(1, 5, (1, 1, 12, 16))).astype(np.float32)
    inv[0, 0, 3, 3] = 0
    motion = np.array([[0.02, -0.05, 0.01, 0.4, 0.1, -0.05]], np.float32)
    K = torch.from_numpy(ref.INTRINSICS[None].copy())
    ours = geo.flow_from_depth_motion(torch.from_numpy(inv), torch.from_numpy(motion), K).numpy()
    theirs = ref.depth_to_flow(inv, motion[:, :3], motion[:, 3:])
    assert np.array_equal(np.isnan(ours), np.isnan(theirs))
    assert np.nanmax(np.abs(ours - theirs)) < 1e-6
    flow = theirs + (rng.standard_normal(theirs.shape) * 1e-3).astype(np.float32)
    flow[np.isnan(flow)] = 0
    ours = geo.depth_from_flow_motion(torch.from_numpy(flow), torch.from_numpy(motion), K).numpy()
    exact = ref.flow_to_depth(flow, motion[:, :3], motion[:, 3:])
    assert np.abs(ours - exact).max() <= 1e-5 * np.abs(exact).max()
    kernel = ref.flow_to_depth(flow, motion[:, :3], motion[:, 3:], dtype=np.float32)
    assert np.abs(ours - kernel).max() <= 1e-3 * np.abs(exact).max()


def test_compat_inputs_are_not_clipped_or_replaced():
    """``compat="demon_original"``: the triangulated inverse depth is not clipped to [0, 50] and
    non-finite flow, confidence, depth and normals reach the nets as they are (DeMoN's graph);
    demon_lab's default clips and replaces them by 0."""
    inv, motion, _ = (x.float() for x in _scene())
    image2_2 = torch.rand(1, 3, 12, 16) - 0.5
    flow = geo.flow_from_depth_motion(inv * 200, motion, K)  # inverse depth 200-600: above the clip
    flow[0, :, 0, 0] = math.nan
    conf = torch.rand(1, 2, 12, 16)
    conf[0, 0, 1, 1] = math.inf
    original = depth_motion_net_inputs(image2_2, flow, conf, motion, K, "demon_original")
    default = depth_motion_net_inputs(image2_2, flow, conf, motion, K)
    assert original[:, 7].max() > 60 and default[:, 7].max() <= 50
    assert math.isnan(original[0, 3, 0, 0]) and default[0, 3, 0, 0] == 0
    assert math.isinf(original[0, 5, 1, 1]) and default[0, 5, 1, 1] == 0
    normals = torch.randn(1, 3, 12, 16)
    depth = inv.clone()
    depth[0, 0, 2, 2] = math.nan
    original = flow_net_inputs(image2_2, depth, normals, motion, K, "demon_original")
    default = flow_net_inputs(image2_2, depth, normals, motion, K)
    assert math.isnan(original[0, 5, 2, 2]) and default[0, 5, 2, 2] == 0
    assert torch.equal(original[:, 3:5], default[:, 3:5])  # both zero the flow of NaN depth
    with pytest.raises(ValueError, match="it needs variant=v1, got v2"):
        DeMoN("v2", 0.0625, (64, 64), compat="demon_original")
    with pytest.raises(ValueError, match="compat"):
        DeMoN("v1", 0.0625, (64, 64), compat="tf")


def _scene():
    from conftest import random_scene

    return random_scene(1, 12, 16, seed=4)


def _smoke_weights(path: Path, seed: int = 0) -> Path:
    torch.manual_seed(seed)
    torch.save(DeMoN("v1", 0.0625, (64, 64)).state_dict(), path)
    return path


@pytest.mark.parametrize("args, message", [
    (["model.compat=tf"], "model.compat: expected one of"),
    (["model.variant=v2", "model.compat=demon_original"], "needs model.variant=v1"),
    (["model.weights=/nope/demon_original.pt"], "model.weights: /nope/demon_original.pt: no such file"),
    (["data=demon_test"], "data.root"),
    (["data=demon_test", "data.root=/nope"], "data.test: none of its files is present in /nope (looked for "
                                             "sun3d_test.h5, rgbd_test.h5, mvs_test.h5, scenes11_test.h5, "
                                             "nyu2_test.h5)"),
])
def test_bad_released_model_settings_are_one_line(args, message, tmp_path):
    error = check(smoke_overrides(tmp_path, *args))
    assert error is not None and message in error and "\n" not in error


def test_weights_of_another_width_are_named_with_the_fix(tmp_path):
    torch.save(DeMoN("v1", 0.125, (64, 64)).state_dict(), tmp_path / "wide.pt")
    error = check(smoke_overrides(tmp_path, f"model.weights={tmp_path / 'wide.pt'}"))
    assert "does not fit the chain of model.variant=v1 model.width=0.0625" in error
    assert "scale=paper, or model.width=1.0 data.size=[192,256]" in error and "\n" not in error


def test_keys_name_the_weights_by_content(tmp_path):
    from demon_lab.pipeline.identity import run_key
    from demon_lab.pipeline.stages.schedule import stage_dirs

    a = _smoke_weights(tmp_path / "a.pt")
    moved = tmp_path / "elsewhere" / "a.pt"
    moved.parent.mkdir()
    shutil.copy(a, moved)
    b = _smoke_weights(tmp_path / "b.pt", seed=1)

    def keys(*extra):
        cfg = compose_config(smoke_overrides(tmp_path, *extra))
        return run_key(settings(cfg)), [s.key for s in stage_dirs(settings(cfg))]

    none, with_a, with_moved, with_b = keys(), keys(f"model.weights={a}"), keys(f"model.weights={moved}"), \
        keys(f"model.weights={b}")
    assert with_a == with_moved  # the path does not matter
    assert len({none[0], with_a[0], with_b[0]}) == 3  # the content does
    assert all(x != y for x, y in zip(none[1], with_a[1])) and all(x != y for x, y in zip(with_a[1], with_b[1]))


def test_stage_files_and_partial_state_dicts_load_net_by_net(tmp_path):
    from demon_lab.pipeline.stages.cache import CheckpointError
    from demon_lab.pipeline.weights import load_weights

    source = DeMoN("v1", 0.0625, (64, 64))
    torch.save({"dm1": source.dm1.state_dict()}, tmp_path / "stage.pt")  # a stage cache file
    torch.save({f"flow1.{k}": v for k, v in source.flow1.state_dict().items()}, tmp_path / "flow1.pt")
    chain = DeMoN("v1", 0.0625, (64, 64))
    assert load_weights(chain, tmp_path / "stage.pt") == ["dm1"]
    assert load_weights(chain, tmp_path / "flow1.pt") == ["flow1"]
    for net in ("flow1", "dm1"):
        for k, v in getattr(source, net).state_dict().items():
            assert torch.equal(getattr(chain, net).state_dict()[k], v)
    assert not torch.equal(chain.flow2.conv1.y.conv.weight, source.flow2.conv1.y.conv.weight)
    torch.save({"flow1.conv1.y.conv.weight": torch.zeros(1)}, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="does not fit this chain"):
        load_weights(chain, tmp_path / "bad.pt")


@pytest.mark.slow
def test_the_iteration_sweep_of_given_weights_trains_nothing(tmp_path):
    weights = _smoke_weights(tmp_path / "chain.pt", seed=3)
    result = cli("-m", *smoke_overrides(tmp_path, "iterations=0,1", f"model.weights={weights}", "train=false"),
                 cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert not (tmp_path / "cache" / "stages").exists()
    assert "training stage" not in result.stdout + result.stderr
    c = client(tmp_path)
    runs = c.search_runs([c.get_experiment_by_name("default").experiment_id])
    jobs = [r for r in runs if "demon_lab.run_key" in r.data.tags]
    assert sorted(r.data.tags["demon_lab.iterations"] for r in jobs) == ["0", "1"]
    assert all(r.info.status == "FINISHED" for r in runs)
    assert not [r for r in runs if r.data.tags.get("demon_lab.kind") == "stage"]
    # the loaded weights are what was evaluated: pass 0 of both jobs is the same chain, and it is
    # not the untrained initialisation that train=false evaluates without model.weights
    from demon_lab.app.job import run

    untrained = run(compose_config(smoke_overrides(tmp_path, "iterations=0", "train=false", "threads=1")))
    key = "test/synthetic_sun3d/it0/l1_inv"
    values = [r.data.metrics[key] for r in jobs]
    assert values[0] == pytest.approx(values[1])
    assert untrained["summary"]["synthetic_sun3d"]["it0/l1_inv"] != pytest.approx(values[0])


def test_eigen_crop_and_poseless_pairs_score_as_demons_evaluation():
    rng = np.random.default_rng(0)
    gt = 1 / rng.uniform(1, 5, (480, 640))
    pred = 1 / rng.uniform(1, 5, (120, 160))
    motion = np.array([np.nan] * 6)
    full = metrics.evaluate_sample({"inv_depth": pred, "motion": np.zeros(6)}, {"inv_depth": gt, "motion": motion},
                                   depthmask=True)
    cropped = metrics.evaluate_sample({"inv_depth": pred}, {"inv_depth": gt, "motion": motion}, eigen_crop=True)
    assert "rot_deg" not in full and full["n_valid"] == 480 * 640  # no poses: depth only, no depthmask
    assert cropped["n_valid"] == 436 * 588
    up = metrics.resize_nearest(pred, (480, 640))[23:459, 27:615]
    expected = metrics.depth_errors(1 / up, 1 / gt[23:459, 27:615])
    assert cropped["sc_inv"] == pytest.approx(expected["sc_inv"])
    with pytest.raises(ValueError, match="480x640"):
        metrics.evaluate_sample({"inv_depth": pred}, {"inv_depth": gt[:240], "motion": motion}, eigen_crop=True)


def test_demon_test_files_are_prepared_with_demons_protocol(tmp_path):
    from demon_lab_test_files import write_demon_test_files

    from demon_lab.pipeline.config import drop_missing_sources, instantiate

    write_demon_test_files(tmp_path, ["sun3d_test.h5", "nyu2_test.h5"], size=(120, 160))
    cfg = compose_config(["data=demon_test", f"data.root={tmp_path}", "scale=paper"])
    notes = drop_missing_sources(cfg)
    assert notes == [f"data.test: not found, skipped: {tmp_path}/rgbd_test.h5, {tmp_path}/mvs_test.h5, "
                     f"{tmp_path}/scenes11_test.h5"]
    sun3d, nyu2 = (instantiate(e) for e in cfg.data.test)
    sample = sun3d[0]
    assert sample["image1"].shape == (3, 192, 256) and sample["gt_inv_depth"].shape == (1, 480, 640)
    assert sample["gt_flow"].shape == (2, 480, 640) and torch.isfinite(sample["motion"]).all()
    np.testing.assert_allclose(sample["intrinsics"].numpy(), geo.DEMON_INTRINSICS, rtol=1e-6)
    assert sun3d.depthmask and not sun3d.eigen_crop
    assert nyu2.eigen_crop and not nyu2.depthmask
    poseless = nyu2[0]
    assert torch.isnan(poseless["motion"]).all() and torch.isnan(poseless["gt_flow"]).all()


@pytest.mark.slow
def test_the_released_model_study_runs_and_reports_beside_the_paper(tmp_path):
    """``report released_model --run --override ...``: the experiment's two jobs (3 and 5
    iterations, nothing trained) on DeMoN's test files, then the report with the paper's DeMoN rows
    (here at the smoke scale with smoke-size weights: the machinery, not the numbers)."""
    import subprocess
    import sys

    from demon_lab_test_files import write_demon_test_files

    root = tmp_path / "testdata"
    write_demon_test_files(root, ["sun3d_test.h5", "mvs_test.h5"], size=(120, 160))
    weights = _smoke_weights(tmp_path / "chain.pt", seed=5)
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    overrides = [f"data.root={root}", f"model.weights={weights}", *smoke_overrides(tmp_path), "eval.point_clouds=0"]
    command = [sys.executable, "-m", "demon_lab.report", "released_model", "--run", "--tracking-uri", uri,
               "--out", str(tmp_path / "reports"), *[a for o in overrides for a in ("--override", o)]]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    md = (tmp_path / "reports" / "released_model.md").read_text()
    rows = table_rows(md)
    assert ["*DeMoN (paper)*", "", "0.019", "0.114", "0.172", "1.801", "18.811"] in rows  # Table 2, SUN3D
    assert ["*DeMoN (paper)*", "", "0.047", "0.202", "0.305", "5.156", "14.447"] in rows  # Table 2, MVS
    assert "### sun3d_test (paper: SUN3D)" in md and "### mvs_test (paper: MVS)" in md
    line = next(r for r in rows if r[:2] == ["DeMoN (released weights, demon_lab)", "1"])
    assert all(cell not in ("", "-") for cell in line[2:])
    assert any(r[:2] == ["iteration 5", "1"] for r in rows)
    assert "`python -m demon_lab -m +experiment=released_model data.root=DIR model.weights=FILE`" in md
    assert not (tmp_path / "cache" / "stages").exists()
    without = subprocess.run(command[:command.index("--override")], cwd=tmp_path, capture_output=True, text=True)
    assert without.returncode == 2 and without.stderr.strip() == (
        "error: released_model runs on files you supply: pass --override data.root=DIR --override model.weights=FILE")


@pytest.mark.slow
def test_fine_tuning_starts_from_the_weights_and_a_zero_step_stage_keeps_them(tmp_path):
    """Table 2's oracle study started from given weights: flow1 kept as it is (0 steps), dm1
    trained with ground-truth flow from the weights' dm1 (not from a fresh initialisation)."""
    from demon_lab.app.job import run
    from demon_lab.pipeline.stages.cache import load_checkpoint
    from demon_lab.pipeline.stages.schedule import stage_dirs

    weights = _smoke_weights(tmp_path / "chain.pt", seed=7)
    given = torch.load(weights, weights_only=True)
    overrides = smoke_overrides(tmp_path, "+experiment=gt_flow_oracle", "oracle=flow", f"model.weights={weights}",
                                "schedule.stages.flow1.steps=0", "threads=1")
    assert run(compose_config(overrides))["status"] == "finished"
    flow1, dm1 = stage_dirs(settings(compose_config(overrides)))
    kept = load_checkpoint(flow1.weights)["flow1"]
    assert all(torch.equal(v, given[f"flow1.{k}"]) for k, v in kept.items())
    tuned = load_checkpoint(dm1.weights)["dm1"]
    fresh = DeMoN("v1", 0.0625, (64, 64)).dm1.state_dict()
    moved = sum(float((v - given[f"dm1.{k}"]).norm()) for k, v in tuned.items())
    apart = sum(float((fresh[k] - given[f"dm1.{k}"]).norm()) for k in tuned)
    assert 0 < moved < 0.05 * apart
    error = check(smoke_overrides(tmp_path, "schedule.stages.flow1.steps=0"))
    assert error.endswith("no earlier stage trains flow1 and model.weights is not set for flow1")
    torch.save({"dm1": DeMoN("v1", 0.0625, (64, 64)).dm1.state_dict()}, tmp_path / "dm1.pt")
    error = check(smoke_overrides(tmp_path, f"model.weights={tmp_path / 'dm1.pt'}", "schedule.stages.flow1.steps=0"))
    assert error.endswith(f"no earlier stage trains flow1 and {tmp_path / 'dm1.pt'} has no flow1")
    # skipping the joint iterative stage keeps flow2 and dm2 as their own stages trained them
    assert check(smoke_overrides(tmp_path, "schedule.stages.iterative.steps=0")) is None


def test_demon_train_trains_on_demons_files_and_tests_on_its_test_files(tmp_path):
    """data=demon_train: the stages train on DeMoN's training files that are under data.root (the
    others named and skipped) and the job tests on its test files; diagnose reads given weights."""
    from demon_lab_test_files import write_demon_test_files

    from demon_lab.app.job import run
    from demon_lab.tools import diagnose

    root = tmp_path / "data"
    write_demon_test_files(root, ["sun3d_train_0.1m_to_0.2m.h5", "scenes11_train.h5", "sun3d_test.h5"],
                           size=(120, 160))
    assert check(smoke_overrides(tmp_path, "data=demon_train", f"data.root={root}", "scale=paper")) is None
    overrides = smoke_overrides(tmp_path, "data=demon_train", f"data.root={root}", "schedule.until=dm1",
                                "iterations=0", "threads=1")
    result = run(compose_config(overrides))
    assert result["status"] == "finished" and set(result["summary"]) == {"sun3d_test"}
    assert result["figures"]["flow1"]["steps_per_second"] > 0 and (tmp_path / "cache" / "stages").is_dir()
    weights = _smoke_weights(tmp_path / "chain.pt")
    passes = diagnose.run(smoke_overrides(tmp_path, "data=demon_test", f"data.root={root}",
                                          f"model.weights={weights}", "train=false", "iterations=2"))
    assert [row["pass"] for row in passes["sun3d_test"]] == [0, 1, 2, "refined"]


def test_compat_iterative_passes_use_demons_constant_intrinsics():
    """DeMoN's IterativeNet computes its inputs with [0.89115971, 1.18821287, 0.5, 0.5] whatever the
    images; demon_lab's default uses the intrinsics it is given."""
    torch.manual_seed(0)
    images = [torch.rand(1, 3, 64, 64) - 0.5 for _ in range(2)]
    other = torch.tensor([[0.8, 1.1, 0.48, 0.52]])
    original = DeMoN("v1", 0.0625, (64, 64), compat="demon_original").eval()
    default = DeMoN("v1", 0.0625, (64, 64)).eval()
    default.load_state_dict(original.state_dict())
    with torch.no_grad():
        a, b = (original(*images, k, iterations=2) for k in (K, other))
        c, d = (default(*images, k, iterations=2) for k in (K, other))
    assert all(torch.equal(p.inv_depth, q.inv_depth) and torch.equal(p.flow, q.flow)
               for p, q in zip(a.passes, b.passes))
    assert not torch.equal(c.passes[2].flow, d.passes[2].flow)


def test_evaluating_given_weights_needs_the_nets_it_runs(tmp_path):
    source = DeMoN("v1", 0.0625, (64, 64))
    torch.save({k: v for k, v in source.state_dict().items() if k.split(".")[0] in ("flow1", "dm1")},
               tmp_path / "bootstrap.pt")
    bootstrap = f"model.weights={tmp_path / 'bootstrap.pt'}"
    error = check(smoke_overrides(tmp_path, bootstrap, "train=false"))  # iterations=3 by default
    assert error == (f"model.weights: {tmp_path / 'bootstrap.pt'} has no flow2, dm2, which train=false with "
                     "iterations=3 evaluates (the refinement net is optional)")
    from demon_lab.app.job import run

    result = run(compose_config(smoke_overrides(tmp_path, bootstrap, "train=false", "iterations=0", "threads=1")))
    assert result["status"] == "finished"
    assert "refined/l1_inv" not in result["summary"]["synthetic_sun3d"]  # no refinement net in the file
    assert "it0/l1_inv" in result["summary"]["synthetic_sun3d"]
