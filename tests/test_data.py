"""demon_lab.data: the Sample type, synthetic scenes, readers, augmentation, the DataModule."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from conftest import SUN3D_PAIR

from demon_lab import resources
from demon_lab.core import geometry as geo
from demon_lab.core import warping
from demon_lab.data import sample as smp
from demon_lab.data import synthetic
from demon_lab.data.datasets import (
    SPLIT_SEEDS,
    DemonH5Dataset,
    MiddleburyDataset,
    PairFolderDataset,
    SyntheticDataset,
    TumDataset,
)
from demon_lab.data.mixture import MixtureSampler, flow_order
from demon_lab.data.readers import (
    middlebury_motorcycle,
    read_demon_h5_pairs,
    read_pair_folder,
    write_demon_h5,
    write_tum_sequence,
)

SIZE = (48, 64)


@pytest.fixture(scope="module")
def rendered():
    """A synthetic sample with its scene and cameras (for exact checks against the renderer)."""
    return synthetic.render_pair("synthetic_sun3d", 7, SIZE, supersample=1, return_scene=True)


def _flow_of(sample: dict) -> torch.Tensor:
    return geo.flow_from_depth_motion(sample["inv_depth"][None], sample["motion"][None],
                                      sample["intrinsics"][None], sample["intrinsics2"][None])[0]


def _photometric_error(sample: dict) -> tuple[float, float]:
    """Mean |image1 - warp(image2, GT flow)| on visible pixels, and without the warp."""
    flow = torch.nan_to_num(sample["flow"], nan=0.0)[None]
    warped = warping.warp_image(sample["image2"][None], flow)[0]
    seen = sample["visible"][0] & (warped.abs().sum(0) > 0)
    err = (warped - sample["image1"]).abs().mean(0)[seen].mean().item()
    base = (sample["image2"] - sample["image1"]).abs().mean(0)[seen].mean().item()
    return err, base


# ----------------------------------------------------------------------------- Sample


def test_sample_keys_shapes_and_dtypes(rendered):
    sample = rendered[0]
    H, W = SIZE
    expected = {"image1": (3, H, W), "image2": (3, H, W), "intrinsics": (4,), "intrinsics2": (4,),
                "inv_depth": (1, H, W), "inv_depth2": (1, H, W), "motion": (6,), "flow": (2, H, W),
                "normals": (3, H, W), "valid": (1, H, W), "visible": (1, H, W)}
    for key, shape in expected.items():
        assert tuple(sample[key].shape) == shape, key
    assert sample["image1"].dtype == torch.float32 and sample["valid"].dtype == torch.bool
    assert -0.5 <= sample["image1"].min() and sample["image1"].max() <= 0.5
    assert sample["id"] == "synthetic_sun3d/7"
    assert sample["baseline"] == pytest.approx(float(sample["motion"][3:].norm()))
    assert not (sample["visible"] & ~sample["valid"]).any()
    torch.testing.assert_close(sample["flow"], _flow_of(sample), equal_nan=True)


@pytest.mark.parametrize("kwargs, message", [
    (dict(image2=np.zeros((3, 8, 9), np.float32)), "image2 has shape"),
    (dict(inv_depth=np.ones((7, 8))), r"inv_depth must be \(8, 8\)"),
    (dict(motion=[0, 0, 0, math.nan, 0, 1]), "motion has non-finite values"),
    (dict(motion=[0, 0, 1]), "motion must have 6 values"),
    (dict(intrinsics=[0, 1, 0.5, 0.5]), "focal lengths must be positive"),
    (dict(inv_depth=np.full((8, 8), np.nan)), "no valid pixel"),
    (dict(inv_depth=-np.ones((8, 8))), "no valid pixel"),
    (dict(image1=np.zeros((8, 8, 4), np.uint8)), r"image1 must be \(H, W, 3\) RGB"),
])
def test_make_sample_bad_input_is_one_clear_line(kwargs, message):
    args = dict(id="pair/0", image1=np.zeros((3, 8, 8), np.float32), image2=np.zeros((3, 8, 8), np.float32),
                intrinsics=[1, 1, 0.5, 0.5], inv_depth=np.ones((8, 8)), motion=[0, 0, 0, 1, 0, 0])
    args.update(kwargs)
    with pytest.raises(smp.DataError, match=message) as info:
        smp.make_sample(**args)
    assert "pair/0" in str(info.value) and "\n" not in str(info.value)


def test_normalize_translation_scales_depth_and_keeps_flow(rendered):
    sample = rendered[0]
    out = smp.normalize_translation(sample)
    norm = float(sample["motion"][3:].norm())
    assert float(out["motion"][3:].norm()) == pytest.approx(1.0)
    torch.testing.assert_close(out["inv_depth"], sample["inv_depth"] * norm, equal_nan=True)
    torch.testing.assert_close(_flow_of(out), sample["flow"], equal_nan=True, atol=1e-6, rtol=1e-5)
    assert out["baseline"] == sample["baseline"]
    zero = dict(sample, motion=torch.zeros(6))
    with pytest.raises(smp.DataError, match="zero baseline"):
        smp.normalize_translation(zero)


def test_resample_to_new_intrinsics_is_the_zoomed_crop():
    rng = np.random.default_rng(0)
    H, W = 40, 64
    image = cv2.resize(rng.random((10, 16, 3)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC) - 0.5
    k = np.array([0.9, 1.2, 0.5, 0.5])
    sample = smp.make_sample("zoom", torch.from_numpy(image).permute(2, 0, 1), torch.from_numpy(image).permute(2, 0, 1),
                             k, np.full((H, W), 0.5), [0, 0, 0, 0.1, 0, 0])
    # Twice the focal length at the same principal point = the central half of the image, scaled x2.
    out = smp.resample(sample, (H, W), intrinsics=[1.8, 2.4, 0.5, 0.5])
    expected = cv2.resize(image[H // 4:3 * H // 4, W // 4:3 * W // 4], (W, H), interpolation=cv2.INTER_LINEAR)
    got = out["image1"].permute(1, 2, 0).numpy()
    assert np.abs(got - expected)[2:-2, 2:-2].max() < 1e-5
    torch.testing.assert_close(out["intrinsics"], torch.tensor([1.8, 2.4, 0.5, 0.5]))
    # A plain resize keeps the normalised intrinsics and averages areas.
    half = smp.resample(sample, (H // 2, W // 2))
    torch.testing.assert_close(half["intrinsics"], sample["intrinsics"])
    np.testing.assert_allclose(half["image1"][:, 0, 0].numpy(), image[:2, :2].mean((0, 1)), atol=1e-6)


def test_resample_real_pair_to_demon_intrinsics_keeps_ground_truth_consistent():
    sample = middlebury_motorcycle()
    out = smp.resample(sample, (192, 256), intrinsics=geo.DEMON_INTRINSICS)
    torch.testing.assert_close(out["intrinsics"], torch.tensor(geo.DEMON_INTRINSICS))
    torch.testing.assert_close(out["intrinsics2"], torch.tensor(geo.DEMON_INTRINSICS))
    err, base = _photometric_error(out)
    assert err < 0.06 and err < base / 3


# ----------------------------------------------------------------------------- augmentation


@pytest.mark.parametrize("transform", ["rotate_180", "mirror", "both"])
@pytest.mark.parametrize("source", ["synthetic", "middlebury"])
def test_augmentation_is_consistent(transform, source, rendered):
    sample = rendered[0] if source == "synthetic" else smp.resample(middlebury_motorcycle(), (96, 128))
    ops = {"rotate_180": [smp.rotate_180], "mirror": [smp.mirror], "both": [smp.rotate_180, smp.mirror]}
    out = sample
    for op in ops[transform]:
        out = op(out)
    # flow from the augmented depth and motion equals the augmented flow
    torch.testing.assert_close(_flow_of(out), out["flow"], equal_nan=True, atol=2e-6, rtol=1e-4)
    # normals (recomputed from the augmented depth) equal the transformed old ones on smooth parts
    sign = {"rotate_180": [-1, -1, 1], "mirror": [-1, 1, 1], "both": [1, -1, 1]}[transform]
    flipped = sample["normals"].flip((-2, -1) if transform == "rotate_180" else (-1,) if transform == "mirror"
                                     else (-2,)) * torch.tensor(sign, dtype=torch.float32)[:, None, None]
    both = torch.isfinite(flipped).all(0) & torch.isfinite(out["normals"]).all(0)
    cos = (flipped * out["normals"]).sum(0)[both]
    assert cos.median() > 0.99  # the stencil differs only at creases and on noisy real depth
    assert not torch.equal(out["image1"], sample["image1"])
    err, base = _photometric_error(out)
    # the images moved with the geometry (the warp's border rule is not flip-symmetric: ~1 %)
    assert err == pytest.approx(_photometric_error(sample)[0], rel=0.05) and err < base / 2
    # rotation angle and baseline do not change
    assert float(out["motion"][:3].norm()) == pytest.approx(float(sample["motion"][:3].norm()), rel=1e-6)
    assert float(out["motion"][3:].norm()) == pytest.approx(float(sample["motion"][3:].norm()), rel=1e-6)


def test_augment_draws_are_deterministic(rendered):
    a = smp.augment(rendered[0], np.random.default_rng([0, 5]))
    b = smp.augment(rendered[0], np.random.default_rng([0, 5]))
    assert torch.equal(a["image1"], b["image1"]) and torch.equal(a["motion"], b["motion"])


def test_augment_equals_its_flips_applied_one_by_one(rendered):
    """augment computes the normals once, after the last flip: the result is the same, bit for
    bit, as rotate_180 and mirror applied in turn (each recomputing them), for every draw."""
    sample = rendered[0]
    for seed in range(40):
        rng = np.random.default_rng([1, seed])
        rotate, flip = rng.random() < 0.5, rng.random() < 0.5
        expected = sample
        if rotate:
            expected = smp.rotate_180(expected)
        if flip:
            expected = smp.mirror(expected)
        got = smp.augment(sample, np.random.default_rng([1, seed]))
        assert got.keys() == expected.keys()
        for key, value in expected.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(got[key].nan_to_num(-7), value.nan_to_num(-7)), (seed, key)


def test_synthetic_samples_are_kept_in_memory_unchanged(tmp_path, monkeypatch):
    from demon_lab.data.datasets import MEMORY, SyntheticDataset, keep_in_memory

    MEMORY.clear()
    ds = SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(32, 32), supersample=1, cache_dir=tmp_path)
    first = ds.load(1)
    (ds.cache / f"{ds.seed_of(1)}.pt").unlink()  # the second read cannot come from the disk
    first.pop("image1")  # a caller's change to its dict does not reach the memory copy
    again = ds.load(1)
    assert "image1" in again and torch.equal(again["inv_depth"].nan_to_num(), first["inv_depth"].nan_to_num())
    assert not (ds.cache / f"{ds.seed_of(1)}.pt").exists()
    again["image1"] = again["image1"] * 0  # nor does replacing an entry
    assert ds.load(1)["image1"].abs().sum() > 0
    # every object of the set reads the same copy: another stage's, a grown pool's
    for other in (SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(32, 32), supersample=1,
                                   cache_dir=tmp_path), ds.extended(2)):
        assert torch.equal(other.load(1)["inv_depth"].nan_to_num(), first["inv_depth"].nan_to_num())
    held = MEMORY.held(ds.memory_key)
    assert held > 0 and keep_in_memory([ds]) == 2 and MEMORY.held(ds.memory_key) == 3 * held  # all 3 now
    assert keep_in_memory([ds]) == 0
    MEMORY.clear()
    small = SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(32, 32), supersample=1,
                             cache_dir=tmp_path, memory_mb=0)
    small.load(0)
    assert MEMORY.held(small.memory_key) == 0 and keep_in_memory([small]) == 0
    budget = SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(32, 32), supersample=1,
                              cache_dir=tmp_path, memory_mb=1.5 * held / 2**20)
    assert keep_in_memory([budget]) == 1 and MEMORY.held(budget.memory_key) == held  # the first that fit
    MEMORY.clear()
    monkeypatch.setenv("DEMON_LAB_MEMORY_MB", "0")
    off = SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(32, 32), supersample=1, cache_dir=tmp_path)
    off.load(0)
    assert off.memory_budget == 0 and MEMORY.held(off.memory_key) == 0


# ----------------------------------------------------------------------------- synthetic


def test_synthetic_ground_truth_is_exact(rendered):
    sample, scene, _cam1, cam2 = rendered
    # Where view-1 points land in view 2 (demon_lab.core.geometry), camera 2's exact ray cast through
    # that sub-pixel position hits the same point at the same depth.
    coords, inv2 = geo.reproject(sample["inv_depth"][None].double(), sample["motion"][None].double(),
                                 sample["intrinsics"][None].double())
    vis = sample["visible"][0].numpy()
    u2, v2 = coords[0, 0].numpy()[vis], coords[0, 1].numpy()[vis]
    fx, fy, cx, cy = synthetic.INTRINSICS
    d_cam = np.stack([(u2 - cx) / fx, (v2 - cy) / fy, np.ones_like(u2)], 1)
    t = synthetic.cast(scene, cam2.center, d_cam @ cam2.rotation)[0]
    rel = np.abs(1 / t - inv2[0, 0].numpy()[vis]) * t
    assert vis.mean() > 0.5
    assert rel.max() < 1e-5  # float32 storage of depth and motion
    # the view-2 depth map itself is the ray cast at pixel centres
    (centre,) = synthetic._pixel_rays(cam2, SIZE, [(0.5, 0.5)])
    t2 = synthetic.cast(scene, cam2.center, centre)[0].reshape(SIZE)
    np.testing.assert_allclose(sample["inv_depth2"][0].numpy(), 1 / t2, rtol=1e-6)
    # photometric consistency: image 2 warped by the GT flow looks like image 1
    err, base = _photometric_error(sample)
    assert err < base / 2


def test_occluded_pixels_are_not_visible(rendered):
    sample, scene, _cam1, cam2 = rendered
    inside = geo.visibility_mask(sample["inv_depth"][None], sample["motion"][None], sample["intrinsics"][None])[0]
    # visible implies projecting inside; some inside pixels are occluded by nearer geometry
    assert not (sample["visible"] & ~inside).any()
    occluded = inside & ~sample["visible"]
    coords, inv2 = geo.reproject(sample["inv_depth"][None].double(), sample["motion"][None].double(),
                                 sample["intrinsics"][None].double())
    if occluded.any():
        u2 = coords[0, 0][occluded[0]].numpy()
        v2 = coords[0, 1][occluded[0]].numpy()
        fx, fy, cx, cy = synthetic.INTRINSICS
        d_cam = np.stack([(u2 - cx) / fx, (v2 - cy) / fy, np.ones_like(u2)], 1)
        t = synthetic.cast(scene, cam2.center, d_cam @ cam2.rotation)[0]
        assert (1 / t > inv2[0, 0][occluded[0]].numpy() * (1 + 1e-6)).all()  # something nearer


def test_synthetic_samples_are_deterministic_and_splits_disjoint():
    a = synthetic.render_pair("synthetic_scenes11", 11, (24, 32))
    b = synthetic.render_pair("synthetic_scenes11", 11, (24, 32))
    c = synthetic.render_pair("synthetic_scenes11", 12, (24, 32))
    for key in ("image1", "image2", "inv_depth", "inv_depth2", "motion", "visible"):
        assert a[key].numpy().tobytes() == b[key].numpy().tobytes(), key
    assert not torch.equal(a["image1"], c["image1"])
    train = SyntheticDataset("synthetic_scenes11", "train", length=10, size=(24, 32), cache_dir=False)
    test = SyntheticDataset("synthetic_scenes11", "test", length=10, size=(24, 32), cache_dir=False)
    assert {train.seed_of(i) for i in range(10)}.isdisjoint({test.seed_of(i) for i in range(10)})
    assert test.seed_of(0) == SPLIT_SEEDS["test"]


@pytest.mark.slow
def test_synthetic_bytes_are_the_same_in_a_fresh_process():
    code = ("import hashlib; from demon_lab.data import synthetic as s;"
            "x = s.render_pair('synthetic_mvs', 3, (24, 32));"
            "keys = ('image1', 'image2', 'inv_depth', 'motion');"
            "print(hashlib.sha256(b''.join(x[k].numpy().tobytes() for k in keys)).hexdigest())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    x = synthetic.render_pair("synthetic_mvs", 3, (24, 32))
    import hashlib

    here = hashlib.sha256(b"".join(x[k].numpy().tobytes() for k in ("image1", "image2", "inv_depth", "motion")))
    assert out == here.hexdigest()


def test_synthetic_cache_returns_identical_samples(tmp_path):
    ds = SyntheticDataset("synthetic_sun3d", "val", length=2, size=(24, 32), cache_dir=tmp_path)
    first = ds[1]
    files = list(tmp_path.rglob("*.pt"))
    assert len(files) == 1 and ds.cache_key in str(files[0])
    again = ds[1]
    for key in ("image1", "inv_depth", "motion", "flow"):
        assert torch.equal(first[key], again[key]) or torch.allclose(first[key], again[key], equal_nan=True)
    files[0].write_bytes(b"truncated")  # a damaged entry is rendered again, not a crash
    assert torch.equal(ds[1]["image1"], first["image1"])


TABLE1 = {"synthetic_scenes11": (3.3, 5.3), "synthetic_sun3d": (10.6, 5.2), "synthetic_mvs": (34.3, 28.9)}


def test_mip_levels_are_box_averages_and_the_filtered_lookup_blends_them():
    from demon_lab.data import textures

    rng = np.random.default_rng(0)
    tex = rng.random((16, 16, 3))
    pyramid = textures.mip_pyramid(tex)
    assert [lv.shape[0] for lv in pyramid] == [16, 8, 4, 2, 1]
    np.testing.assert_allclose(pyramid[1], tex.reshape(8, 2, 8, 2, 3).mean((1, 3)), rtol=1e-12)
    np.testing.assert_allclose(pyramid[-1][0, 0], tex.mean((0, 1)), rtol=1e-12)
    u, v = rng.random(50) * 3 - 1, rng.random(50) * 3 - 1
    lookup = lambda f: textures.sample_filtered(pyramid, u, v, np.full(50, f))  # noqa: E731
    # a footprint up to one texel reads level 0; 2^k texels read level k exactly
    np.testing.assert_allclose(lookup(0.3), textures.sample_texture(tex, u, v), rtol=1e-12)
    np.testing.assert_allclose(lookup(4.0), textures.sample_texture(pyramid[2], u, v), rtol=1e-12)
    # in between, linearly in the footprint
    mid = 0.25 * textures.sample_texture(pyramid[1], u, v) + 0.75 * textures.sample_texture(pyramid[2], u, v)
    np.testing.assert_allclose(lookup(3.5), mid, rtol=1e-12)
    # a footprint larger than the texture reads its mean colour
    np.testing.assert_allclose(lookup(64.0), np.broadcast_to(tex.mean((0, 1)), (50, 3)), rtol=1e-12)


def test_textures_do_not_alias_when_a_surface_is_far_away():
    """A distant textured plane rendered with 2x2 and 4x4 samples per pixel looks the same: the
    texture is filtered to the pixel footprint (without it, a minified texture aliases, and the two
    views of a surface disagree). Measured: 0.011 mean difference; unfiltered (scene generator 4),
    0.11."""
    plane = synthetic.Primitive("plane", np.zeros(3), np.eye(3), np.zeros(3), texture=0,
                                texture_scale=0.5, tint=np.ones(3))
    scene = synthetic.Scene([plane], light=np.array([0.0, 0.0, 1.0]), ambient=0.5, room=None)
    down = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # looks straight down
    camera = synthetic.Camera(rotation=down, center=np.array([0.0, 0.0, 12.0]))
    fine = synthetic.render_view(scene, camera, SIZE, supersample=4)[0]
    coarse = synthetic.render_view(scene, camera, SIZE, supersample=2)[0]
    assert np.abs(fine - coarse).mean() < 0.03


@pytest.mark.parametrize("preset", sorted(synthetic.PRESETS))
def test_brightness_constancy_holds_on_rendered_pairs(preset):
    """Image 2 warped by the GT flow matches image 1 within 4 grey levels (of 255) on average over
    visible pixels (Lambertian shading, filtered textures). Measured on these 6 pairs: 3.3 / 1.1 /
    2.7 on scenes11 / sun3d / mvs; scene generator 4 (unfiltered textures): 7.8 / 1.5 / 6.0."""
    errors = [_photometric_error(synthetic.render_pair(preset, 20_000_000 + i, (96, 128)))[0]
              for i in range(6)]
    assert float(np.mean(errors)) * 255 < 4.0


@pytest.mark.slow
@pytest.mark.parametrize("preset", sorted(TABLE1))
def test_presets_hit_table1_means_within_15_percent(preset):
    from demon_lab.tools.data_stats import dataset_statistics

    ds = SyntheticDataset(preset, "train", length=500, size=(24, 32), supersample=1, cache_dir=False)
    stats = dataset_statistics([ds], 500)
    rot, tri = TABLE1[preset]
    assert stats["n_pairs"] == 500
    assert stats["rot_mean_deg"] == pytest.approx(rot, rel=0.15)
    assert stats["tri_mean_deg"] == pytest.approx(tri, rel=0.15)
    assert stats["visible_fraction"] >= 0.5 * stats["valid_fraction"]


@pytest.mark.slow
@pytest.mark.parametrize("preset", sorted(TABLE1))
@pytest.mark.parametrize("split", ["train", "test"])
def test_camera_2_moves_either_way_sideways(preset, split):
    """Un-augmented pairs move camera 2 to the left about as often as to the right (generator 3
    orbited always one way, t_x < 0 in nearly every pair: a constant translation guess scored well)."""
    ds = SyntheticDataset(preset, split, length=100, size=(24, 32), supersample=1, cache_dir=False)
    tx = np.array([float(ds[i]["motion"][3]) for i in range(len(ds))])
    assert 0.3 <= (tx < 0).mean() <= 0.7


# ----------------------------------------------------------------------------- readers


def test_sun3d_pair_folder_reader(sun3d_pair):
    sample = read_pair_folder(SUN3D_PAIR)
    torch.testing.assert_close(sample["intrinsics"], torch.tensor(geo.DEMON_INTRINSICS), rtol=1e-6, atol=1e-7)
    assert math.degrees(float(sample["motion"][:3].norm())) == pytest.approx(1.853, abs=1e-3)
    t = sample["motion"][3:].double()
    assert float(t.norm()) == pytest.approx(0.0749, abs=1e-4)
    np.testing.assert_allclose((t / t.norm()).numpy(), [-0.8187, -0.0454, -0.5724], atol=1e-4)
    depths = torch.cat([1 / d[torch.isfinite(d)] for d in (sample["inv_depth"], sample["inv_depth2"])])
    assert float(depths.min()) == pytest.approx(0.80, abs=0.01) and float(depths.max()) == pytest.approx(4.0, abs=0.01)
    assert float(sample["valid"].float().mean()) == pytest.approx(0.666, abs=0.001)
    assert float(torch.isfinite(sample["inv_depth2"]).float().mean()) == pytest.approx(0.738, abs=0.001)
    # ground-truth consistency: view-1 depth moved by the motion meets view-2 depth
    coords, inv2 = geo.reproject(sample["inv_depth"][None], sample["motion"][None], sample["intrinsics"][None])
    x = (coords[0, 0] * 640).floor().long().clamp(0, 639)
    y = (coords[0, 1] * 480).floor().long().clamp(0, 479)
    inside = geo.visibility_mask(sample["inv_depth"][None], sample["motion"][None], sample["intrinsics"][None])[0, 0]
    target = sample["inv_depth2"][0][y, x]
    keep = inside & torch.isfinite(target)
    rel = ((1 / inv2[0, 0] - 1 / target).abs() * target)[keep]
    assert float(rel.median()) < 0.01


def test_pair_folder_directory_and_bad_files(tmp_path):
    import shutil

    root = tmp_path / "pairs"
    shutil.copytree(SUN3D_PAIR, root / "scene_a")
    ds = PairFolderDataset(root, size=(96, 128))
    assert len(ds) == 1 and ds[0]["image1"].shape == (3, 96, 128)
    (root / "scene_a" / "0001.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(smp.DataError, match=r"0001\.jpg: not a readable image"):
        ds.load(0)
    (root / "scene_a" / "poses.txt").write_text("1 2 3\n")
    with pytest.raises(smp.DataError, match=r"poses\.txt: expected a line of 12 numbers"):
        ds.load(0)
    with pytest.raises(smp.DataError, match="no pair folder"):
        PairFolderDataset(tmp_path / "pairs" / "scene_a" / "..", size=None).folders and PairFolderDataset(tmp_path)


def test_middlebury_reader():
    sample = middlebury_motorcycle()
    H, W = 500, 741
    assert sample["image1"].shape == (3, H, W)
    torch.testing.assert_close(sample["motion"], torch.tensor([0, 0, 0, -0.193001, 0, 0]))
    assert float(sample["intrinsics"][0]) == pytest.approx(994.978 / W)
    assert float(sample["intrinsics2"][2] - sample["intrinsics"][2]) == pytest.approx(31.086 / W, rel=1e-5)
    depth = 1 / sample["inv_depth"][sample["valid"]]
    assert 2.0 < float(depth.min()) < 2.2 and 4.9 < float(depth.max()) < 5.1
    # the GT flow is minus the disparity: left[y, x] <-> right[y, x - d]
    from skimage import data

    disparity = data.stereo_motorcycle()[2]
    ok = np.isfinite(disparity)
    np.testing.assert_allclose(sample["flow"][0].numpy()[ok] * W, -disparity[ok], atol=2e-3)
    assert np.abs(sample["flow"][1].numpy()[ok]).max() < 1e-6
    err, base = _photometric_error(sample)
    assert err < 0.05 and err < base / 4


def _view_of(scene, camera, size):
    image, depth, _ = synthetic.render_view(scene, camera, size, supersample=1)
    rgb = np.floor(np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    return rgb, np.where(np.isfinite(depth), depth, 0.0)


def _pixel_K(size):
    H, W = size
    fx, fy, cx, cy = synthetic.INTRINSICS
    return np.array([[fx * W, 0, cx * W], [0, fy * H, cy * H], [0, 0, 1.0]])


def test_demon_h5_round_trip(tmp_path, rendered):
    sample, scene, cam1, cam2 = rendered
    views = [_view_of(scene, c, SIZE) for c in (cam1, cam2)]
    K = _pixel_K(SIZE)
    path = tmp_path / "tiny_test.h5"
    scenes = [{"name": "scene0", "viewpoint_pairs": [0, 1, 1, 0],
               "views": [{"image": im, "depth": d, "K": K, "R": c.rotation, "t": c.translation}
                         for (im, d), c in zip(views, (cam1, cam2))]},
              {"name": "scene1",
               "views": [{"image": im, "depth": d, "K": K, "R": c.rotation, "t": c.translation,
                          "depth_metric": "ray_length"} for (im, d), c in zip(views, (cam1, cam2))]}]
    # scene1 stores ray lengths: convert camera-z to ray length to write it
    fx, fy, cx, cy = synthetic.INTRINSICS
    xs = ((np.arange(SIZE[1]) + 0.5) / SIZE[1] - cx) / fx
    ys = ((np.arange(SIZE[0]) + 0.5) / SIZE[0] - cy) / fy
    for v in scenes[1]["views"]:
        v["depth"] = v["depth"] * np.sqrt(xs[None] ** 2 + ys[:, None] ** 2 + 1)
    write_demon_h5(path, scenes)
    assert read_demon_h5_pairs(path, test_phase=True) == [("scene0", 0, 1), ("scene1", 0, 1)]
    assert read_demon_h5_pairs(path, test_phase=False) == [("scene0", 0, 1), ("scene0", 1, 0),
                                                           ("scene1", 0, 1), ("scene1", 1, 0)]
    ds = DemonH5Dataset(path, normalize_translation=False)
    for index in range(2):
        got = ds.load(index)
        np.testing.assert_allclose(got["motion"].numpy(), sample["motion"].numpy(), atol=1e-6)
        torch.testing.assert_close(got["intrinsics"], sample["intrinsics"])
        valid = sample["valid"] & got["valid"]
        assert valid.float().mean() > 0.95 * sample["valid"].float().mean()
        rel = ((got["inv_depth"] - sample["inv_depth"]).abs() / sample["inv_depth"])[valid]
        assert rel.max() < 1.5e-3  # float16 storage (and the ray-length conversion)
        assert (got["image1"] - sample["image1"]).abs().mean() < 0.03  # WebP at quality 90
    assert ds[0]["id"].endswith("scene0/frames/t0/v0,v1")


def test_demon_h5_bad_files(tmp_path):
    bad = tmp_path / "corrupt.h5"
    bad.write_bytes(b"\x89HDF\r\n" + bytes(range(256)) * 4)
    with pytest.raises(smp.DataError, match=r"corrupt\.h5: not a readable HDF5 file"):
        DemonH5Dataset(bad)
    with pytest.raises(smp.DataError, match=r"missing\.h5: file not found"):
        DemonH5Dataset(tmp_path / "missing.h5")
    import h5py

    with h5py.File(tmp_path / "broken.h5", "w") as f:
        f.create_dataset("s/frames/t0/v0/image", data=np.zeros(10, np.int8))
        f.create_dataset("s/frames/t0/v1/image", data=np.zeros(10, np.int8))
    ds = DemonH5Dataset(tmp_path / "broken.h5")
    with pytest.raises(smp.DataError, match=r"lacks the dataset\(s\) depth, camera"):
        ds.load(0)


def test_tum_sequence_round_trip(tmp_path, rendered):
    _, scene, cam1, cam2 = rendered
    # a short trajectory from camera 1 to camera 2 and beyond
    cams = [cam1]
    for step in (0.5, 1.0, 1.5, 2.0):
        center = cam1.center + step * (cam2.center - cam1.center)
        cams.append(synthetic.Camera(cam2.rotation if step >= 1 else cam1.rotation, center))
    frames = []
    for c in cams:
        image, depth = _view_of(scene, c, SIZE)
        frames.append({"image": image, "depth": depth, "R": c.rotation, "t": c.translation})
    root = tmp_path / "rgbd_dataset_synthetic"
    write_tum_sequence(root, frames)
    baseline = float(np.linalg.norm(cam2.center - cam1.center))
    K = _pixel_K(SIZE)
    ds = TumDataset(root, min_baseline=0.9 * baseline, max_baseline=1.1 * baseline, stride=1,
                    intrinsics=(K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5), normalize_translation=False)
    assert len(ds) >= 2
    got = ds.load(0)
    expected = synthetic.relative_motion(cams[0], cams[2])
    np.testing.assert_allclose(got["motion"].numpy(), expected, atol=1e-5)
    torch.testing.assert_close(got["intrinsics"], torch.tensor(synthetic.INTRINSICS, dtype=torch.float32))
    depth = 1 / got["inv_depth"][got["valid"]]
    truth = torch.from_numpy(frames[0]["depth"]).float()[got["valid"][0]]
    assert (depth - truth).abs().max() < 1e-4 + 1 / 5000  # 16-bit PNG at 1/5000 m
    (root / "groundtruth.txt").write_text("# nothing\n")
    with pytest.raises(smp.DataError, match=r"groundtruth\.txt: no entries"):
        TumDataset(root)


# ----------------------------------------------------------------------------- mixing, configs


def test_mixture_sampler_follows_weights_and_is_deterministic():
    sampler = MixtureSampler([10, 1000], [3.0, 1.0], num_samples=4000, seed=1)
    first = list(sampler)
    second = list(sampler)  # the next epoch draws anew
    assert first != second
    replay = MixtureSampler([10, 1000], [3.0, 1.0], num_samples=4000, seed=1)
    assert list(replay) == first
    share = np.mean([s == 0 for s, _, _ in first])
    assert share == pytest.approx(0.75, abs=0.03)
    assert all(0 <= i < (10 if s == 0 else 1000) for s, i, _ in first)
    assert len({d for _, _, d in first + second}) == 8000  # every draw has its own seed


@pytest.mark.parametrize("skip", [0, 24])
def test_mixture_sampler_shards_every_batch_across_data_parallel_processes(skip):
    """Three processes with 4 samples each per step see, together, the 12-sample batches of one
    process, in order, also when a resumed stage skips the keys it already consumed."""
    args = ([10, 1000], [3.0, 1.0], 120)
    seeded = {"seed": 5, "skip": skip}
    batches = lambda keys, b: [keys[i:i + b] for i in range(0, len(keys), b)]  # noqa: E731
    whole = batches(list(MixtureSampler(*args, **seeded)), 12)
    shards = [MixtureSampler(*args, **seeded, rank=r, world=3, batch=4) for r in range(3)]
    assert all(len(s) == 40 for s in shards)
    parts = [batches(list(s), 4) for s in shards]
    assert [[key for p in parts for key in p[k]] for k in range(len(whole))] == whole
    with pytest.raises(ValueError, match="rank 3 of a world of 3"):
        MixtureSampler(*args, **seeded, rank=3, world=3, batch=4)


def test_an_easy_first_curriculum_widens_from_the_easiest_samples_to_all():
    """easy_first=(0.2, 0.5): key n draws among the first ceil(q(n) x length) of the source's order,
    q rising from 0.2 at the first key to 1 at half the keys; shards and a resumed stage see the keys
    of one uninterrupted process; start 1 is the plain sampler."""
    order = [list(range(9, -1, -1)), list(range(19, -1, -1))]  # easiest: the highest indices
    args = ([10, 20], [1.0, 1.0], 400)
    seeded = {"seed": 3}
    keys = list(MixtureSampler(*args, **seeded, easy_first=(0.2, 0.5), order=order))
    for n, (s, i, _) in enumerate(keys):
        share = min(1.0, 0.2 + 0.8 * n / 200)
        assert order[s].index(i) < math.ceil(share * (10, 20)[s]), (n, s, i)
    first = [(s, i) for s, i, _ in keys[:20]]  # q < 0.28: 3 of 10, 6 of 20
    assert {i for s, i in first if s == 0} <= {9, 8, 7} and {i for s, i in first if s == 1} <= set(range(14, 20))
    assert {i for s, i, _ in keys[200:] if s == 1} == set(range(20))  # the whole source after until
    resumed = list(MixtureSampler(*args, **seeded, skip=120, easy_first=(0.2, 0.5), order=order))
    assert resumed == keys[120:]
    shards = [list(MixtureSampler(*args, **seeded, rank=r, world=2, batch=4, easy_first=(0.2, 0.5), order=order))
              for r in range(2)]
    assert [k for b in range(50) for shard in shards for k in shard[4 * b:4 * b + 4]] == keys
    plain = list(MixtureSampler(*args, **seeded))
    assert keys[:200] != plain[:200]
    assert list(MixtureSampler(*args, **seeded, easy_first=(1.0, 0.5), order=order)) == plain
    # every key's pool is exactly ceil(q(n) x length), replayed from the sampler's stream
    rng = np.random.default_rng([3, 0])
    sources = rng.choice(2, size=400, p=[0.5, 0.5])
    for n, s in enumerate(sources):
        q = min(1.0, 0.2 + 0.8 * n / 200)
        expected = int(rng.integers((10, 20)[s])) if q == 1 else order[s][int(rng.integers(math.ceil(q * (10, 20)[s])))]
        assert keys[n][:2] == (int(s), expected), n
    # the ramp counts keys of the whole sequence: a later epoch is past it, drawn as the plain sampler
    later = MixtureSampler(*args, **seeded, easy_first=(0.2, 0.5), order=order)
    plain_later = MixtureSampler(*args, **seeded)
    later.set_epoch(1)
    plain_later.set_epoch(1)
    assert list(later) == list(plain_later)
    with pytest.raises(ValueError, match="easy_first: expected an order"):
        MixtureSampler(*args, **seeded, easy_first=(0.2, 0.5))
    with pytest.raises(ValueError, match=r"easy_first: expected \(start, until\) in \(0, 1\]"):
        MixtureSampler(*args, **seeded, easy_first=(0.2, 0.0), order=order)


def test_flow_order_ranks_samples_by_their_mean_flow():
    dataset = SyntheticDataset("synthetic_sun3d", length=4, size=(32, 32), cache_dir=False)
    means = [float(torch.linalg.vector_norm(dataset.load(i)["flow"].double(), dim=0).nanmean()) for i in range(4)]
    assert list(flow_order(dataset)) == sorted(range(4), key=means.__getitem__)
    assert list(flow_order(dataset)) == [1, 3, 2, 0]  # not the identity: the order is the flows'
    pairs = MiddleburyDataset()
    pairs.load = lambda i: {"image1": torch.zeros(3, 4, 4)}  # no flow: not orderable
    with pytest.raises(smp.DataError, match="easy_first: middlebury has no ground-truth flow"):
        flow_order(pairs)


def test_datamodule_batches_a_mix(tmp_path):
    from demon_lab.data.datamodule import DemonDataModule, Draws

    common = dict(size=(32, 64), cache_dir=tmp_path)
    train = [{"weight": 1.0, "dataset": SyntheticDataset("synthetic_sun3d", "train", length=4, augment=True, **common)},
             {"weight": 1.0, "dataset": MiddleburyDataset(size=(32, 64), augment=True)}]
    draws = Draws(batch_size=4, samples_per_epoch=8, seed=3)
    dm = DemonDataModule(train, draws)
    batch = next(iter(dm.train_dataloader()))
    assert batch["image1"].shape == (4, 3, 32, 64) and batch["motion"].shape == (4, 6)
    assert torch.allclose(batch["motion"][:, 3:].norm(dim=1), torch.ones(4))  # normalised
    assert len(batch["id"]) == 4
    again = next(iter(DemonDataModule(train, draws).train_dataloader()))
    assert torch.equal(batch["image1"], again["image1"])


def test_every_data_config_composes(tmp_path):

    from hydra import compose, initialize_config_dir

    conf = resources.CONF
    names = sorted(p.stem for p in (conf / "data").glob("*.yaml"))
    assert {"synthetic_scenes11", "synthetic_sun3d", "synthetic_mvs", "demon_h5", "pair_folder",
            "middlebury", "tum", "default"} <= set(names)
    with initialize_config_dir(str(conf), version_base="1.3"):
        for name in names:
            extra = {"demon_h5": ["data.path=x"], "tum": ["data.root=x"]}.get(name, [])
            cfg = compose("data_stats", overrides=[f"data={name}", *extra])
            assert cfg.data.name == (cfg.data.preset if name == "synthetic" else name)  # the presets' base
            assert cfg.data.train and "test" in cfg.data
            for entry in cfg.data.train:
                assert str(entry.dataset._target_).startswith("demon_lab.data.datasets.")


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


def test_synthetic_pairs_have_no_points_near_camera_2():
    """The first 120 mvs training seeds: without the depth-ratio filter 5 of them hold points with
    z2 < 0.1 z1 (seeds 10, 79, 82, 83, 118 at 32x24); with it (the preset's default) none does."""
    from demon_lab.tools.data_stats import pair_statistics

    preset = synthetic.PRESETS["synthetic_mvs"]
    unfiltered = dataclasses.replace(preset, min_depth_ratio=0.0)
    near = lambda p, seed: pair_statistics(synthetic.render_pair(p, seed, (24, 32), supersample=1))["near_camera2"]  # noqa: E731
    assert [s for s in range(120) if near(unfiltered, s)] == [10, 79, 82, 83, 118]
    assert not any(near(preset, s) for s in (10, 79, 82, 83, 118))


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


def test_training_draws_carry_what_training_reads_bit_for_bit(rendered):
    """A training draw (index, draw seed) is the augmented sample with only the fields training
    reads (no normals, flow or masks: the losses derive theirs from the depth pyramid), each bit
    for bit as the augmentation of the whole sample gives it."""
    sample = rendered[0]
    for seed in range(8):
        full = smp.augment(sample, np.random.default_rng([2, seed]))
        lean = smp.augment(sample, np.random.default_rng([2, seed]), normals=False)
        assert "normals" in full and "normals" not in lean and set(full) - set(lean) == {"normals"}
        assert all(torch.equal(torch.nan_to_num(full[k], nan=-9.0), torch.nan_to_num(lean[k], nan=-9.0))
                   for k in lean if isinstance(lean[k], torch.Tensor))
    from demon_lab.data.datasets import TRAINING_KEYS, SyntheticDataset

    ds = SyntheticDataset("synthetic_sun3d", split="train", length=2, size=(64, 64), augment=True, cache_dir=False)
    draw = ds[0, 3]
    assert "normals" in ds[0] and set(draw) == set(TRAINING_KEYS)
    expected = smp.augment({k: v for k, v in ds[0].items() if k in TRAINING_KEYS},
                           np.random.default_rng([ds.seed, 3]), normals=False)
    assert all(torch.equal(torch.nan_to_num(draw[k], nan=-9.0), torch.nan_to_num(expected[k], nan=-9.0))
               for k in draw if isinstance(draw[k], torch.Tensor))
    full = smp.augment(ds[0], np.random.default_rng([ds.seed, 3]))  # the same draw with every field
    assert all(torch.equal(torch.nan_to_num(draw[k], nan=-9.0), torch.nan_to_num(full[k], nan=-9.0))
               for k in draw if isinstance(draw[k], torch.Tensor))
    plain = SyntheticDataset("synthetic_sun3d", split="train", length=2, size=(64, 64), augment=False, cache_dir=False)
    assert set(plain[0, 3]) == set(TRAINING_KEYS)  # the same keys whatever a source's augmentation: batches collate


def test_a_training_draw_of_demon_h5_skips_the_derived_maps_and_keeps_every_value(tmp_path):
    """A training draw loads without flow, normals and masks (half its time) and gives, field for
    field and bit for bit, what the full sample gives after its draw drops them; also when the
    pair is resampled to another size."""
    from demon_lab.data.datasets import TRAINING_KEYS
    from demon_lab.data.throughput import write_demon_layout_file

    path = tmp_path / "layout.h5"
    write_demon_layout_file(path, 2, (96, 128))
    for size in ((96, 128), (64, 96)):
        ds = DemonH5Dataset(path, test_phase=False, size=size, augment=True, seed=3)
        assert not {"flow", "normals", "valid", "visible"} & set(ds.load_training(0))
        calls = []
        ds.load_training = lambda index, ds=ds, calls=calls: (calls.append(index)
                                                              or DemonH5Dataset.load_training(ds, index))
        ds[(1, 0)], ds[1]
        assert calls == [1]  # a draw takes the short path, an evaluation sample does not
        del ds.load_training
        for index, draw in [(0, 0), (1, 5), (2, 7)]:
            got = ds[(index, draw)]
            full = ds._prepare(ds.load(index), ds.size)
            assert {"flow", "normals", "visible"} <= set(full)
            expected = smp.augment({k: v for k, v in full.items() if k in TRAINING_KEYS},
                                   np.random.default_rng([3, draw]), normals=False)
            assert set(got) == set(expected)
            for key, value in expected.items():
                if isinstance(value, torch.Tensor):
                    torch.testing.assert_close(got[key], value, rtol=0, atol=0, equal_nan=True)
                else:
                    assert got[key] == value


# ----------------------------------------------------------------------------- 2-D layers


def test_layered_pairs_are_a_function_of_the_seed_and_their_flow_maps_view1_onto_view2():
    """Image 2 sampled at p + flow(p) is image 1 (up to bilinear resampling of 8-bit textures) where
    p + flow lands inside view 2 and the layer is not hidden there; with zero flow, or the flow's sign
    or normalisation wrong, it is not."""
    from demon_lab.core.warping import warp_image
    from demon_lab.data.layers import render_layers

    a, b = render_layers(3, (96, 128)), render_layers(3, (96, 128))
    assert all(torch.equal(a[k], b[k]) for k in ("image1", "image2", "flow"))
    assert not torch.equal(a["image1"], render_layers(4, (96, 128))["image1"])
    assert a["image1"].shape == a["image2"].shape == (3, 96, 128) and a["flow"].shape == (2, 96, 128)
    assert a["image1"].min() >= -0.5 and a["image1"].max() <= 0.5
    errors = {}
    for seed in range(6):
        pair = render_layers(seed, (96, 128))
        flow = pair["flow"][None]
        for label, f in (("flow", flow), ("zero", torch.zeros_like(flow)), ("negated", -flow), ("pixels", flow * 32)):
            warped = warp_image(pair["image2"][None], f)[0]
            diff = (warped - pair["image1"]).abs().mean(0)
            errors.setdefault(label, []).append(float(diff[torch.isfinite(diff)].median()))
    assert np.median(errors["flow"]) < 0.02
    for wrong in ("zero", "negated", "pixels"):
        assert np.median(errors[wrong]) > 4 * np.median(errors["flow"]), (wrong, errors)
    pixels = torch.stack([render_layers(s)["flow"] for s in range(40)]) * torch.tensor([128.0, 96.0])[:, None, None]
    mean = float(pixels.norm(dim=1).mean())
    assert 6 < mean < 25, mean  # pixels at 128x96: the 3-D presets' flow is of this order


def test_layers_dataset_renders_a_new_pair_for_every_index_and_reads_as_flow_ground_truth():
    from demon_lab.data.datasets import LayersDataset

    layers = LayersDataset((64, 96), seed=2)
    assert len(layers) == LayersDataset.LENGTH and layers.name == "layers"
    one, again, other = layers[(5, 123)], layers[5], layers[(6, 123)]
    assert torch.equal(one["image1"], again["image1"]) and not torch.equal(one["image1"], other["image1"])
    assert not torch.equal(one["image1"], LayersDataset((64, 96), seed=3)[5]["image1"])
    from demon_lab.core import losses

    batch = torch.utils.data.default_collate([one, other])
    gt = losses.ground_truth(batch)
    assert gt["flow2"].shape == (2, 2, 16, 24) and gt["flow5"].shape == (2, 2, 2, 3)
    torch.testing.assert_close(gt["flow2"][0, :, 3, 4], batch["flow"][0, :, 12:16, 16:20].mean((1, 2)))
    with pytest.raises(IndexError):
        layers[-1]
    # a 3-D sample that carries its flow (an evaluation sample) keeps the flow of its depth and motion
    scene = SyntheticDataset("synthetic_sun3d", length=2, size=(64, 96), cache_dir=False)
    both = torch.utils.data.default_collate([scene[0], scene[1]])
    draws = {k: v for k, v in both.items() if k != "flow"}
    assert "flow" in both and torch.equal(losses.ground_truth(both)["flow2"].nan_to_num(9.0),
                                          losses.ground_truth(draws)["flow2"].nan_to_num(9.0))


def test_a_lead_source_fills_the_first_fraction_of_the_stage_in_whole_batches():
    """lead=(2, 0.25) over 200 keys in global batches of 8 (4 per process, 2 processes): the first 48
    keys (0.25 x 200 = 50, rounded to 6 whole batches) come from source 2, none after it (weight 0);
    the rest draw as the plain sampler; shards and a resumed stage see the keys of one process."""
    args = ([10, 20, 10**9], [1.0, 1.0, 0.0], 200)
    seeded = {"seed": 4}
    keys = list(MixtureSampler(*args, **seeded, batch=8, lead=(2, 0.25)))
    assert [s for s, _, _ in keys[:48]] == [2] * 48 and all(s != 2 for s, _, _ in keys[48:])
    assert len({i for _, i, _ in keys[:48]}) == 48  # (a fresh pair per key)
    plain = list(MixtureSampler(*args, **seeded, batch=8))
    assert [k[0] for k in keys[48:]] == [k[0] for k in plain[48:]]
    shards = [list(MixtureSampler(*args, **seeded, rank=r, world=2, batch=4, lead=(2, 0.25))) for r in range(2)]
    assert [k for b in range(25) for shard in shards for k in shard[4 * b:4 * b + 4]] == keys
    assert list(MixtureSampler(*args, **seeded, batch=8, skip=40, lead=(2, 0.25))) == keys[40:]
    later = MixtureSampler(*args, **seeded, batch=8, lead=(2, 0.25))
    later.set_epoch(1)
    assert all(s != 2 for s, _, _ in later)  # the lead is the start of the stage (its first epoch)
    with pytest.raises(ValueError, match="lead: expected"):
        MixtureSampler(*args, **seeded, lead=(3, 0.3))
    with pytest.raises(ValueError, match="one curriculum at a time"):
        MixtureSampler([10, 20], [1.0, 1.0], 200, lead=(1, 0.3), easy_first=(0.5, 0.5), order=[range(10), range(20)])


def test_data_stats_scores_the_classical_priors_on_the_real_pair():
    """``priors=true``: the DIS prior flows match the bundled SUN3D pair far better than zero flow, and
    the RANSAC motion the tight-threshold ``ransac_prior`` reads from them is within a few degrees
    (the pair's own camera motion is known)."""
    from demon_lab.data.datasets import PairFolderDataset
    from demon_lab.tools.data_stats import FLOW_PRIORS, dataset_statistics, format_priors, pair_statistics

    dataset = PairFolderDataset(SUN3D_PAIR)
    stats = dataset_statistics([dataset], 1, priors=True)
    zero = pair_statistics(dataset.load(0))["zero_flow_epe"]
    for name in FLOW_PRIORS:
        assert stats[f"{name}_epe"] < 0.5 * zero
        assert stats[f"{name}_ransac_prior_tran_deg"] < 10 and stats[f"{name}_ransac_prior_rot_deg"] < 1
    assert "dis_x2" in format_priors(stats) and "ransac_prior tran" in format_priors(stats)
    assert "dis_epe" not in dataset_statistics([dataset], 1)


def test_a_fresh_source_grows_by_one_new_scene_at_its_rate_and_replays_from_any_step():
    """fresh=[0.1, 0]: source 0 (10 scenes) gains one scene every 10 of its draws, and the draw at
    which it grows is that new scene, its first appearance; every other draw of it is uniform over the
    pool so far; source 1 draws as the plain sampler (the same sources, key for key); shards and a
    resumed stage see the keys of one process; fresh 0 everywhere is the plain sampler."""
    args = ([10, 20], [1.0, 1.0], 400)
    seeded = {"seed": 3}
    keys = list(MixtureSampler(*args, **seeded, batch=8, fresh=[0.1, 0.0]))
    plain = list(MixtureSampler(*args, **seeded, batch=8))
    assert [k[0] for k in keys] == [k[0] for k in plain]
    grown = [i for s, i, _ in keys if s == 0]
    first_seen: dict[int, int] = {}
    for c, index in enumerate(grown, start=1):
        pool = 10 + (c // 10)
        assert index < pool
        first_seen.setdefault(index, c)
        if c % 10 == 0:  # the c-th draw grows the pool: it draws the new scene, never seen before
            assert index == pool - 1 and first_seen[index] == c
    assert sorted(i for i in first_seen if i >= 10) == list(range(10, 10 + len(grown) // 10))
    assert max(i for s, i, _ in keys if s == 1) < 20
    shards = [list(MixtureSampler(*args, **seeded, rank=r, world=2, batch=4, fresh=[0.1, 0.0])) for r in range(2)]
    assert [k for b in range(50) for shard in shards for k in shard[4 * b:4 * b + 4]] == keys
    assert list(MixtureSampler(*args, **seeded, batch=8, skip=96, fresh=[0.1, 0.0])) == keys[96:]
    assert list(MixtureSampler(*args, **seeded, batch=8, fresh=[0.0, 0.0])) == plain
    with pytest.raises(ValueError, match="fresh: expected one rate"):
        MixtureSampler(*args, **seeded, fresh=[0.1])
    with pytest.raises(ValueError, match="fresh: the easy_first order"):
        MixtureSampler(*args, **seeded, fresh=[0.1, 0.0], easy_first=(0.5, 0.5), order=[range(10), range(20)])


def test_fresh_scenes_render_new_scenes_of_the_next_seeds_in_the_loaders_worker(tmp_path):
    """DemonDataModule(fresh_scenes=0.25) over a 3-scene synthetic set: the set's draws reach scenes
    past its own three (the next seeds of its split, the scenes a longer set has at those indices),
    rendered by the loader's worker and cached beside the others; the layers lead keeps its own keys."""
    from demon_lab.data.datamodule import DemonDataModule, Draws

    scenes = SyntheticDataset("synthetic_sun3d", length=3, size=(64, 64), cache_dir=tmp_path)
    module = DemonDataModule([{"weight": 1.0, "dataset": scenes}], Draws(
        batch_size=2, samples_per_epoch=24, fresh_scenes=0.25, layers_first=0.25, layers_size=(64, 64)), num_workers=1)
    loader = module.train_dataloader()
    drawn = [i for s, i, _ in module.sampler if s == 0]
    assert max(drawn) == 3 + 18 // 4 - 1 and len(scenes) == 3
    ahead = module.fresh_scenes()  # what a stage renders before it trains: the set and the new scenes drawn
    assert [len(d) for d in ahead] == [max(drawn) + 1] and ahead[0].cache == scenes.cache
    module.sampler.set_epoch(0)
    batches = list(loader)
    assert len(batches) == 12
    cached = sorted(int(p.stem) for p in scenes.cache.glob("*.pt"))
    assert cached == sorted(set(drawn))  # every drawn scene, the new ones too, rendered once and cached
    longer = SyntheticDataset("synthetic_sun3d", length=8, size=(64, 64), cache_dir=False, memory_mb=0)  # rendered
    again = scenes.extended(5)
    assert len(again) == 8 and torch.equal(again.load(7)["image1"], longer.load(7)["image1"])
