"""demon_lab.data: the Sample type, its translation normalisation and resampling, DeMoN's augmentation, the scene
memory, and the draws training reads."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from data_helpers import SIZE, _flow_of, _photometric_error

from demon_lab.core import geometry as geo
from demon_lab.data import sample as smp
from demon_lab.data.datasets import (
    SyntheticDataset,
)
from demon_lab.data.readers import (
    middlebury_motorcycle,
)


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
    from demon_lab.data.datasets import MEMORY, keep_in_memory

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
    from demon_lab.data.datasets import TRAINING_KEYS

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
