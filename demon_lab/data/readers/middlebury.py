"""The Middlebury 2014 "Motorcycle" pair that scikit-image ships (``skimage.data.stereo_motorcycle``).

Calibration for the shipped size (scikit-image's docstring; docs/reference.md §9): focal length 994.978 px,
left principal point (311.193, 254.877) px, principal-point x offset between the cameras
doffs = 31.086 px, baseline 193.001 mm. Depth Z = baseline f / (d + doffs); the right camera sits
at +baseline along the left camera's x axis, unrotated, so X2 = X1 - (baseline, 0, 0). The two
views keep their own principal points (``intrinsics2``). Depth in metres; view 2 has no GT depth.
"""

from __future__ import annotations

import numpy as np

from demon_lab.data.sample import Sample, make_sample

FOCAL = 994.978
CX, CY = 311.193, 254.877
DOFFS = 31.086
BASELINE = 0.193001  # metres


def middlebury_motorcycle() -> Sample:
    from skimage import data

    left, right, disparity = data.stereo_motorcycle()
    height, width = disparity.shape
    disparity = disparity.astype(np.float64)
    with np.errstate(invalid="ignore"):
        inv_depth = np.where(np.isfinite(disparity), (disparity + DOFFS) / (BASELINE * FOCAL), np.nan)
    # Pixel centres at +0.5 (DeMoN's convention); Middlebury's principal points use the same
    # pixel-index origin as the disparity maps, left[y, x] <-> right[y, x - d].
    k1 = np.array([FOCAL / width, FOCAL / height, (CX + 0.5) / width, (CY + 0.5) / height])
    k2 = k1 + np.array([0.0, 0.0, DOFFS / width, 0.0])
    motion = np.array([0.0, 0.0, 0.0, -BASELINE, 0.0, 0.0])
    return make_sample("middlebury/motorcycle", np.ascontiguousarray(left), np.ascontiguousarray(right),
                       k1, inv_depth.astype(np.float32), motion, intrinsics2=k2)
