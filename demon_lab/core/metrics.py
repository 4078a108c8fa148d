"""DeMoN's evaluation protocol, exactly (docs/reference.md §7; DeMoN's `python/depthmotionnet/evaluation/metrics.py`).

Inputs are numpy arrays or torch tensors; everything is computed in float64. The per-sample
functions (:func:`depth_errors`, :func:`motion_errors`, :func:`flow_epe`) reproduce DeMoN's
``evaluation/metrics.py``; :func:`evaluate_sample` chains them the way DeMoN's
``examples/evaluation.py`` does (prediction resized to the ground truth by nearest neighbour,
the ``depthmask`` rule, GT depth divided by the GT baseline); :func:`evaluate_set` scores a test
set and returns a per-sample table plus the means over samples (the paper's tables average over
samples, not pixels).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

from demon_lab.core import geometry

DEPTH_KEYS = ("l1", "l1_inv", "sc_inv", "l1_rel", "sq_rel", "log10", "rmse", "rmse_log",
              "delta_1.25", "delta_1.25^2", "delta_1.25^3", "n_valid")
MOTION_KEYS = ("rot_deg", "tran_deg", "tran_dist")
SCALINGS = (None, "abs", "log", "inv")


def _as_f64(name: str, x: Any, shape: tuple[int | None, ...] | None = None) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if shape is not None:
        ok = a.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, a.shape))
        if not ok:
            want = ", ".join("N" if s is None else str(s) for s in shape)
            raise ValueError(f"{name}: expected shape ({want}), got {a.shape}")
    return a


# ----------------------------------------------------------------------------- depth


def depth_scale(pred: np.ndarray, gt: np.ndarray, scaling: str) -> float:
    """Least-squares scale for the prediction (DeMoN's ``scaled=True`` variants).

    'abs': sum(p g) / sum(p^2); 'log': exp(mean(log g - log p)) (the supplementary's s_log);
    'inv': fits inverse depths, 1 / (sum(1/(p g)) / sum(1/p^2)). Inputs: valid pixels only.
    """
    if scaling == "abs":
        return float(np.sum(pred * gt) / np.sum(pred * pred))
    if scaling == "log":
        return float(np.exp(np.mean(np.log(gt) - np.log(pred))))
    if scaling == "inv":
        return float(1.0 / (np.sum(1.0 / (pred * gt)) / np.sum(1.0 / (pred * pred))))
    raise ValueError(f"scaling: expected one of {SCALINGS}, got {scaling!r}")


def depth_errors(
    pred_depth: Any,
    gt_depth: Any,
    gt_translation: Any | None = None,
    scaling: str | None = None,
) -> dict[str, float]:
    """DeMoN's depth metrics for one sample.

    Args:
        pred_depth: (H, W) predicted absolute depth (not inverse).
        gt_depth: (H, W) ground-truth absolute depth, same size.
        gt_translation: (3,) GT translation; unless its norm is close to 1 (``np.isclose``) the GT
            depth is divided by that norm, because the network predicts depth for a unit baseline.
        scaling: None (the paper's numbers), 'abs', 'log' or 'inv': multiply the prediction by
            that least-squares scale first.

    A pixel counts iff both maps are finite and > 0 there. With d = log p - log g, means over
    valid pixels: ``l1`` |p-g|, ``l1_inv`` |1/p-1/g|, ``sc_inv`` sqrt(mean d^2 - (mean d)^2),
    ``l1_rel`` |p-g|/g, ``sq_rel`` (p-g)^2/g, ``log10`` |log10 p - log10 g|, ``rmse``,
    ``rmse_log`` sqrt(mean d^2), ``delta_X`` the fraction with |d| < log X (strict),
    X = 1.25, 1.25^2, 1.25^3; ``n_valid`` the pixel count. With no valid pixel every metric is
    NaN and ``n_valid`` is 0.
    """
    p = _as_f64("pred_depth", pred_depth, (None, None))
    g = _as_f64("gt_depth", gt_depth)
    if g.shape != p.shape:
        raise ValueError(f"gt_depth: expected shape {p.shape} to match pred_depth, got {g.shape}")
    if scaling not in SCALINGS:
        raise ValueError(f"scaling: expected one of {SCALINGS}, got {scaling!r}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(p) & np.isfinite(g) & (p > 0) & (g > 0)
    p, g = p[valid], g[valid]
    if gt_translation is not None:
        norm = float(np.linalg.norm(_as_f64("gt_translation", gt_translation, (3,))))
        if not np.isclose(norm, 1.0):
            g = g / norm
    if p.size == 0:
        return {k: (0 if k == "n_valid" else math.nan) for k in DEPTH_KEYS}
    if scaling is not None:
        p = p * depth_scale(p, g, scaling)
    d = np.log(p) - np.log(g)
    abs_d = np.abs(d)
    out = {
        "l1": np.mean(np.abs(p - g)),
        "l1_inv": np.mean(np.abs(1.0 / p - 1.0 / g)),
        "sc_inv": math.sqrt(max(np.mean(d * d) - np.mean(d) ** 2, 0.0)),
        "l1_rel": np.mean(np.abs(p - g) / g),
        "sq_rel": np.mean((p - g) ** 2 / g),
        "log10": np.mean(np.abs(np.log10(p) - np.log10(g))),
        "rmse": math.sqrt(np.mean((p - g) ** 2)),
        "rmse_log": math.sqrt(np.mean(d * d)),
        "delta_1.25": np.mean(abs_d < math.log(1.25)),
        "delta_1.25^2": np.mean(abs_d < math.log(1.25**2)),
        "delta_1.25^3": np.mean(abs_d < math.log(1.25**3)),
    }
    out = {k: float(v) for k, v in out.items()}
    out["n_valid"] = int(p.size)
    return out


# ----------------------------------------------------------------------------- motion


def angle_axis_to_quaternion(r: np.ndarray) -> np.ndarray:
    """(3,) angle-axis -> (4,) unit quaternion (w, x, y, z); |r| < 1e-6 gives the identity."""
    theta = float(np.linalg.norm(r))
    if theta < 1e-6:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(theta / 2)], math.sin(theta / 2) * r / theta])


def _quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, v1 = a[0], a[1:]
    w2, v2 = b[0], b[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def motion_errors(pred_motion: Any, gt_motion: Any) -> dict[str, float]:
    """DeMoN's motion errors for one sample (``compute_motion_errors``, normalised translations).

    Args:
        pred_motion: (6,) predicted [r, t] (angle-axis, X2 = R X1 + t).
        gt_motion: (6,) ground-truth [r, t].

    Returns:
        ``rot_deg``: angle of the relative rotation, 2 atan2(|vec(q_gt q_pred*)|, |w|), in
        [0, 180]; ``tran_deg``: angle between the translation directions, in degrees;
        ``tran_dist``: |t_gt/|t_gt| - t_pred'|, where t_pred' = t_pred/|t_pred| only if
        |t_pred| > 1e-6 (so a vanishing prediction scores 90 degrees and distance 1). A zero GT
        translation gives NaN translation errors.
    """
    pred = _as_f64("pred_motion", pred_motion, (6,))
    gt = _as_f64("gt_motion", gt_motion, (6,))
    q_gt = angle_axis_to_quaternion(gt[:3])
    q_pred = angle_axis_to_quaternion(pred[:3])
    conj = q_pred * np.array([1.0, -1.0, -1.0, -1.0])
    q = _quaternion_product(q_gt, conj)
    rot = 2.0 * math.atan2(float(np.linalg.norm(q[1:])), abs(float(q[0])))
    t_gt, t_pred = gt[3:], pred[3:]
    with np.errstate(invalid="ignore", divide="ignore"):
        t_gt = t_gt / np.linalg.norm(t_gt)
    pred_norm = float(np.linalg.norm(t_pred))
    if pred_norm > 1e-6:
        t_pred = t_pred / pred_norm
    cos = float(np.clip(t_gt @ t_pred, -1.0, 1.0))
    return {
        "rot_deg": math.degrees(rot),
        "tran_deg": math.degrees(math.acos(cos)) if math.isfinite(cos) else math.nan,
        "tran_dist": float(np.linalg.norm(t_gt - t_pred)),
    }


# ----------------------------------------------------------------------------- flow


def flow_epe(pred_flow: Any, gt_flow: Any) -> float:
    """Mean end-point error of one sample, in normalised flow units (DeMoN's ``flow_epe``).

    Args:
        pred_flow: (2, H, W) predicted normalised flow.
        gt_flow: (2, H, W) ground truth; NaN where unknown.

    Averages over pixels where the error is finite and > 0: DeMoN reuses its depth mask, so
    pixels with exactly zero error are dropped. NaN if no pixel qualifies.
    """
    p = _as_f64("pred_flow", pred_flow, (2, None, None))
    g = _as_f64("gt_flow", gt_flow)
    if g.shape != p.shape:
        raise ValueError(f"gt_flow: expected shape {p.shape} to match pred_flow, got {g.shape}")
    epe = np.sqrt(((p - g) ** 2).sum(0))
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(epe) & (epe > 0)
    return float(epe[keep].mean()) if keep.any() else math.nan


# ----------------------------------------------------------------------------- the protocol


def resize_nearest(x: Any, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour resize of the last two axes, pixel-centre aligned.

    Output pixel i takes input pixel floor((i + 0.5) * n_in / n_out): what DeMoN's evaluation
    gets from ``skimage.transform.resize(order=0)`` when it upsamples a prediction to the
    ground-truth size.
    """
    a = _as_f64("x", x)
    h_in, w_in = a.shape[-2:]
    rows = np.minimum(((np.arange(shape[0]) + 0.5) * h_in / shape[0]).astype(np.int64), h_in - 1)
    cols = np.minimum(((np.arange(shape[1]) + 0.5) * w_in / shape[1]).astype(np.int64), w_in - 1)
    return a[..., rows[:, None], cols[None, :]]


def mask_invisible(
    gt_inv_depth: Any, gt_motion: Any, intrinsics: Sequence[float] = geometry.DEMON_INTRINSICS
) -> np.ndarray:
    """DeMoN's ``depthmask``: GT pixels whose 3-D point does not project strictly inside image 2
    (z > 0, 0 < u < W, 0 < v < H) become NaN.

    Args:
        gt_inv_depth: (H, W) GT inverse depth.
        gt_motion: (6,) GT [r, t].
        intrinsics: (4,) normalised intrinsics (DeMoN's default: the SUN3D ones).

    Returns:
        (H, W) float64 inverse depth with the invisible pixels set to NaN.
    """
    d = _as_f64("gt_inv_depth", gt_inv_depth, (None, None))
    m = _as_f64("gt_motion", gt_motion, (6,))
    k = _as_f64("intrinsics", intrinsics, (4,))
    visible = geometry.visibility_mask(
        torch.from_numpy(d)[None, None], torch.from_numpy(m)[None], torch.from_numpy(k)[None]
    )[0, 0].numpy()
    return np.where(visible, d, np.nan)


EIGEN_CROP = (slice(23, 23 + 436), slice(27, 27 + 588))
"""Eigen's NYU evaluation crop of 480x640 maps (DeMoN's ``eigen_crop_gt_and_pred``)."""


def protocol(dataset: Any) -> dict[str, bool]:
    """A test set's evaluation options for :func:`evaluate_sample` (its ``depthmask`` and
    ``eigen_crop``; DeMoN's paper-style defaults where a dataset does not set them)."""
    return {"depthmask": bool(getattr(dataset, "depthmask", True)),
            "eigen_crop": bool(getattr(dataset, "eigen_crop", False))}


def ground_truth(sample: Mapping[str, Any], dataset: Any) -> dict[str, Any]:
    """The ground truth :func:`evaluate_sample` scores one prepared sample against: at the
    dataset's ``gt_size`` where it has one (``gt_*`` keys: DeMoN's 640x480), else at the inputs'
    size, with the intrinsics the depthmask rule projects with (``depthmask_intrinsics``, else
    the sample's)."""
    mask_k = getattr(dataset, "depthmask_intrinsics", None)
    pick = lambda key: sample[f"gt_{key}"] if f"gt_{key}" in sample else sample[key]  # noqa: E731
    return {"inv_depth": pick("inv_depth")[0], "motion": sample["motion"], "flow": pick("flow"),
            "intrinsics": pick("intrinsics") if mask_k is None else torch.tensor(mask_k, dtype=torch.float64)}


def evaluate_sample(
    pred: Mapping[str, Any],
    gt: Mapping[str, Any],
    depthmask: bool = True,
    scaling: str | None = None,
    eigen_crop: bool = False,
) -> dict[str, float]:
    """Score one prediction the way DeMoN's ``examples/evaluation.py`` does.

    Args:
        pred: ``inv_depth`` (h, w) inverse depth for a unit baseline (any resolution), and
            optionally ``motion`` (6,) and ``flow`` (2, h', w') normalised.
        gt: ``inv_depth`` (H, W) GT inverse depth (NaN/0 invalid), ``motion`` (6,) GT [r, t]
            (not normalised), ``intrinsics`` (4,) normalised; optionally ``flow`` (2, H, W)
            (default: computed from the GT depth and motion).
        depthmask: apply DeMoN's ``depthmask`` rule to the GT depth (its paper-style numbers).
        scaling: forwarded to :func:`depth_errors`.
        eigen_crop: score the depth on Eigen's crop of 480x640 ground truth (:data:`EIGEN_CROP`,
            after the upsampling), as DeMoN's evaluation does for NYU.

    GT motion that is not finite (a source without camera poses, DeMoN's NYU pairs) scores the
    depth only, with a unit baseline and without the depthmask rule, as DeMoN's ``evaluate`` does.

    Returns:
        The depth metrics, plus the motion metrics when ``pred`` has ``motion`` and ``epe`` when
        it has ``flow`` (and the GT motion is known).
    """
    gt_motion = _as_f64("gt['motion']", gt["motion"], (6,))
    known = bool(np.isfinite(gt_motion).all())
    pred_depth, gt_depth = _paired_depths(pred, gt, depthmask and known, eigen_crop)
    out: dict[str, float] = dict(depth_errors(pred_depth, gt_depth, gt_motion[3:] if known else None, scaling))
    if not known:
        return out
    intrinsics = _as_f64("gt['intrinsics']", gt.get("intrinsics", geometry.DEMON_INTRINSICS), (4,))
    if "motion" in pred and pred["motion"] is not None:
        out.update(motion_errors(pred["motion"], gt_motion))
    if "flow" in pred and pred["flow"] is not None:
        gt_flow = gt.get("flow")
        if gt_flow is None:
            gt_flow = geometry.flow_from_depth_motion(
                torch.from_numpy(_as_f64("gt['inv_depth']", gt["inv_depth"]))[None, None],
                torch.from_numpy(gt_motion)[None], torch.from_numpy(intrinsics)[None])[0]
        gt_flow = _as_f64("gt['flow']", gt_flow, (2, None, None))
        pred_flow = resize_nearest(_as_f64("pred['flow']", pred["flow"], (2, None, None)),
                                   gt_flow.shape[1:])
        out["epe"] = flow_epe(pred_flow, gt_flow)
    return out


def _paired_depths(pred: Mapping[str, Any], gt: Mapping[str, Any], depthmask: bool,
                   eigen_crop: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Predicted and GT absolute depth on the GT grid (Eigen's crop of it with ``eigen_crop``),
    NaN where either is invalid (the pixels :func:`evaluate_sample` scores)."""
    gt_inv = _as_f64("gt['inv_depth']", gt["inv_depth"], (None, None))
    if depthmask:
        gt_motion = _as_f64("gt['motion']", gt["motion"], (6,))
        intrinsics = _as_f64("gt['intrinsics']", gt.get("intrinsics", geometry.DEMON_INTRINSICS), (4,))
        gt_inv = mask_invisible(gt_inv, gt_motion, intrinsics)
    pred_inv = resize_nearest(_as_f64("pred['inv_depth']", pred["inv_depth"], (None, None)),
                              gt_inv.shape)
    if eigen_crop:
        if gt_inv.shape != (480, 640):
            raise ValueError(f"eigen_crop: Eigen's crop needs 480x640 ground truth, got {gt_inv.shape[1]}x"
                             f"{gt_inv.shape[0]}")
        gt_inv, pred_inv = gt_inv[EIGEN_CROP], pred_inv[EIGEN_CROP]
    with np.errstate(divide="ignore", invalid="ignore"):
        # Valid pixels are decided on the inverse depths (both finite and > 0), then inverted.
        valid = np.isfinite(gt_inv) & (gt_inv > 0) & np.isfinite(pred_inv) & (pred_inv > 0)
        return np.where(valid, 1.0 / pred_inv, np.nan), np.where(valid, 1.0 / gt_inv, np.nan)


def pixel_depth_errors(pred: Mapping[str, Any], gt: Mapping[str, Any], depthmask: bool = True,
                       eigen_crop: bool = False) -> dict[str, np.ndarray]:
    """Per-pixel ``l1_inv`` and ``l1_rel`` (1-D arrays over the scored pixels) for the error
    histograms of the supplementary's Figure 6; their means are :func:`evaluate_sample`'s."""
    gt_motion = _as_f64("gt['motion']", gt["motion"], (6,))
    known = bool(np.isfinite(gt_motion).all())
    p, g = _paired_depths(pred, gt, depthmask and known, eigen_crop)
    valid = np.isfinite(p) & np.isfinite(g)
    p, g = p[valid], g[valid]
    norm = float(np.linalg.norm(gt_motion[3:])) if known else 1.0
    if not np.isclose(norm, 1.0):
        g = g / norm
    return {"l1_inv": np.abs(1.0 / p - 1.0 / g), "l1_rel": np.abs(p - g) / g}


class PixelHistogram:
    """Accumulates per-pixel depth errors into fixed bins (the last bin holds everything above
    the range, as the supplementary's Figure 6) with exact sums for the means."""

    RANGES: ClassVar[dict[str, float]] = {"l1_inv": 0.1, "l1_rel": 1.0}
    BINS = 50

    def __init__(self):
        self.counts = {k: np.zeros(self.BINS, dtype=np.int64) for k in self.RANGES}
        self.sums = dict.fromkeys(self.RANGES, 0.0)
        self.below_sums = dict.fromkeys(self.RANGES, 0.0)

    def add(self, errors: Mapping[str, np.ndarray]) -> None:
        for key, top in self.RANGES.items():
            e = np.asarray(errors[key], dtype=np.float64)
            index = np.minimum((e / top * self.BINS).astype(np.int64), self.BINS - 1)
            self.counts[key] += np.bincount(index, minlength=self.BINS)
            self.sums[key] += float(e.sum())
            self.below_sums[key] += float(e[index < self.BINS - 1].sum())

    def to_dict(self) -> dict[str, Any]:
        return {key: {"upper": top, "bins": self.BINS, "counts": self.counts[key].tolist(), "sum": self.sums[key],
                      "sum_below_last_bin": self.below_sums[key]} for key, top in self.RANGES.items()}


def evaluate_set(
    preds: Iterable[Mapping[str, Any]],
    gts: Iterable[Mapping[str, Any]],
    ids: Iterable[str] | None = None,
    **kwargs: Any,
) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """Score a test set with :func:`evaluate_sample`.

    Returns:
        ``(rows, means)``: one dict per sample (``id`` first, then the metrics) and the mean of
        every metric over the samples where it is finite (the paper averages over samples);
        ``means['n_samples']`` is the number of samples, ``means['n_failed_<metric>']`` counts
        samples whose metric was NaN (for example no valid pixel).
    """
    preds, gts = list(preds), list(gts)
    if len(preds) != len(gts):
        raise ValueError(f"preds: expected {len(gts)} predictions to match gts, got {len(preds)}")
    ids = [str(i) for i in range(len(gts))] if ids is None else [str(i) for i in ids]
    rows = [{"id": i, **evaluate_sample(p, g, **kwargs)} for i, p, g in zip(ids, preds, gts)]
    return rows, summarize(rows)


def summarize(rows: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Means over samples of every numeric column (NaN entries skipped and counted)."""
    means: dict[str, float] = {"n_samples": len(rows)}
    keys = [k for k in (rows[0] if rows else {}) if k != "id"]
    for key in keys:
        values = np.array([row[key] for row in rows], dtype=np.float64)
        finite = np.isfinite(values)
        means[key] = float(values[finite].mean()) if finite.any() else math.nan
        if not finite.all():
            means[f"n_failed_{key}"] = int((~finite).sum())
    return means


# ----------------------------------------------------------------------------- names


@dataclass(frozen=True)
class Column:
    """How one quantity is named wherever demon_lab shows it.

    ``key``: its name in MLflow (``test/<set>/<key>``) and in report specs; ``text``: the
    terminal tables' header (ASCII); ``label``: Markdown tables and figures; ``tex``: LaTeX;
    ``paper``: its column in ``ablations/paper_numbers.csv`` (None: the paper has none);
    ``unit``: what a figure's axis adds to the label (None: a count or a plain number).
    """

    key: str
    text: str
    label: str
    tex: str
    paper: str | None = None
    unit: str | None = None


COLUMNS: dict[str, Column] = {c.key: c for c in (
    Column("l1_inv", "L1-inv", "L1-inv", "L1-inv", "L1-inv", "inverse depth, unit baseline"),
    Column("sc_inv", "sc-inv", "sc-inv", "sc-inv", "sc-inv", "log depth, scale-invariant"),
    Column("l1_rel", "L1-rel", "L1-rel", "L1-rel", "L1-rel", "relative to true depth"),
    Column("delta_1.25", "d<1.25", "δ<1.25", r"$\delta<1.25$", "delta<1.25", "fraction of pixels"),
    Column("delta_1.25_2", "d<1.25^2", "δ<1.25²", r"$\delta<1.25^2$", "delta<1.25^2", "fraction of pixels"),
    Column("delta_1.25_3", "d<1.25^3", "δ<1.25³", r"$\delta<1.25^3$", "delta<1.25^3", "fraction of pixels"),
    Column("rot_deg", "rot", "rot (°)", "rot", "rot", "rotation error, degrees"),
    Column("tran_deg", "tran", "tran (°)", "tran", "tran", "translation direction error, degrees"),
    Column("epe", "EPE", "EPE", "EPE", "EPE", "normalised flow units"),
    Column("n_failed", "failed", "failed", "failed"),
    # what python -m demon_lab.diagnose measures per pass (demon_lab/tools/diagnose.py)
    Column("flow", "flow", "flow length", "flow length"),
    Column("gt_flow", "gt flow", "GT flow length", "GT flow length"),
    Column("prior", "prior", "prior flow length", "prior flow length"),
    Column("prior_epe", "prior epe", "prior flow EPE", "prior flow EPE"),
    Column("follow", "follow", "distance to the prior", "distance to the prior"),
    Column("t_norm", "|t|", "|t|", r"$|t|$"),
    Column("gt_rot_deg", "gt rot", "GT rot (°)", "GT rot"),
    # the ceiling's measures of a flow (eval.ceiling: demon_lab/baselines/ceiling.py)
    Column("within_1px", "<=1px", "≤ 1 px", r"$\leq$ 1 px", None, "share of flow vectors"),
    Column("within_2px", "<=2px", "≤ 2 px", r"$\leq$ 2 px", None, "share of flow vectors"),
    Column("within_4px", "<=4px", "≤ 4 px", r"$\leq$ 4 px", None, "share of flow vectors"),
    Column("median_px", "median px", "median error (px)", "median error (px)", None, "pixels of the input image"),
    Column("nonpositive_depth", "inv<=0", "share of inverse depth <= 0", r"inverse depth $\leq 0$"),
)}
UNITS_NOTE = "depth metrics on unit-baseline depth, rot/tran in degrees, EPE in normalised flow units"
"""The units of the result tables, in one sentence (the main command's and the reports')."""
RESULT_COLUMNS = ("l1_inv", "sc_inv", "l1_rel", "delta_1.25", "rot_deg", "tran_deg", "epe")
"""The columns of the main command's results table."""


def column(key: str) -> Column:
    """The names of ``key`` (a key without an entry is shown as itself)."""
    return COLUMNS.get(key) or Column(key, key, key, key.replace("_", r"\_"))
