"""Tiny files in DeMoN's HDF5 test layout under their real names (tests of data=demon_test)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from demon_lab.core.geometry import DEMON_INTRINSICS
from demon_lab.data.readers.demon_h5 import write_demon_h5


def write_demon_test_files(root: Path, names: list[str], size: tuple[int, int] = (240, 320)) -> None:
    """One scene of two views per file: a slanted plane 2-4 m away seen by DeMoN's camera,
    the second view 0.2 m to the side. ``nyu2_test.h5`` gets no camera poses (NaN R, t), as
    DeMoN's NYU pairs have no motion ground truth."""
    root.mkdir(parents=True, exist_ok=True)
    height, width = size
    fx, fy, cx, cy = DEMON_INTRINSICS
    K = np.array([[fx * width, 0, cx * width], [0, fy * height, cy * height], [0, 0, 1.0]])
    depth = np.broadcast_to(np.linspace(2.0, 4.0, width)[None], (height, width)).copy()
    depth[:4, :4] = 0  # a few invalid pixels
    for i, name in enumerate(names):
        rng = np.random.default_rng(i)
        views = []
        for t in ([0.0, 0.0, 0.0], [-0.2, 0.0, 0.02]):
            pose = {"R": np.eye(3), "t": np.asarray(t)}
            if name.startswith("nyu2"):
                pose = {"R": np.full((3, 3), np.nan), "t": np.full(3, np.nan)}
            views.append({"image": rng.integers(0, 255, (height, width, 3), dtype=np.uint8), "depth": depth,
                          "K": K, **pose})
        write_demon_h5(root / name, [{"name": "scene0", "views": views}])
