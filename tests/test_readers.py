"""The readers of real formats: a pair folder (the bundled SUN3D pair), Middlebury, DeMoN's HDF5 files, TUM."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import SUN3D_PAIR
from data_helpers import SIZE, _photometric_error, _pixel_K, _view_of

from demon_lab.core import geometry as geo
from demon_lab.data import sample as smp
from demon_lab.data import synthetic
from demon_lab.data.datasets import (
    DemonH5Dataset,
    PairFolderDataset,
    TumDataset,
)
from demon_lab.data.readers import (
    middlebury_motorcycle,
    read_demon_h5_pairs,
    read_pair_folder,
    write_demon_h5,
    write_tum_sequence,
)


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
