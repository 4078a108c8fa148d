"""``python -m demon_lab.data_stats``: the supplementary's Table 1 for any configured source.

Prints the Table 1 columns — perfect GT, photorealistic, outdoor (the source's metadata),
rotation angle mean/std and triangulation angle mean/std in degrees — plus the number of pairs,
the valid-depth fraction, the visible fraction and the median depth; ``out=FILE`` writes them as
JSON.

Definitions: the rotation angle of a pair is the angle of the relative rotation |r|; its
triangulation angle is the median, over the valid pixels of view 1, of the angle at the scene
point between the rays from the two camera centres. Means and (population) standard deviations
are over pairs; the fractions are means over pairs of per-pair pixel fractions (visible: valid
and seen in view 2); the median depth is the median over pairs of each pair's median view-1
depth, in the source's unit (metres for real data). ``zero_flow_epe`` is the mean over pairs of the
EPE of predicting no flow (DeMoN's EPE, normalised units, full resolution): what a flow net must
beat. ``tran_x_negative_fraction``: the share of pairs with t_x < 0, i.e. whose camera 2 sits to the
right of camera 1 (its centre is -R^T t; about half for a source without a sideways bias).
``photometric_error``: the mean over pairs of the mean |image 1 - image 2 warped by the GT flow|
over the visible pixels, in grey levels of 255 (how well brightness constancy holds: what ties the
flow to the images). ``near_camera2_fraction``: the share of pairs with a valid view-1 point at
camera-2 depth z2 < 0.1 z1 (near or behind camera 2's image plane), where the ground-truth flow
(DeMoN's ``depth_to_flow``, no check of z2) grows without bound and one pair can dominate a training
batch's flow loss. ``constant_depth_sc_inv``: the mean over pairs of the population standard
deviation of the log ground-truth depth over the valid pixels, the sc-inv of any constant depth
(what a depth prediction must beat to show structure). Samples are read at the source's native
resolution (synthetic ones at the configured ``data.size``), without augmentation.

``priors=true`` adds what the chain's classical priors (:mod:`demon_lab.nets.prior`) give on each
pair, before any net corrects them: ``<flow prior>_epe``, the EPE of the prior flow (``dis``,
``dis_x2``) at level 2 scored as the chain's flow is; ``<flow prior>_<motion prior>_rot_deg`` and
``..._tran_deg``, the errors of the 5-point RANSAC motion that ``model.dm1_prior`` (``ransac``,
``ransac_prior``) reads from that flow.

    python -m demon_lab.data_stats data=synthetic_sun3d n=500 out=stats.json
    python -m demon_lab.data_stats data=synthetic_sun3d split=test n=32 priors=true
    python -m demon_lab.data_stats data=pair_folder data.path=/data/sun3d_pairs
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig

from demon_lab.pipeline.config import ConfigError
from demon_lab.reporting.tables import text_table
from demon_lab.resources import CONF

KEYS = ("n_pairs", "rot_mean_deg", "rot_std_deg", "tri_mean_deg", "tri_std_deg",
        "valid_fraction", "visible_fraction", "median_depth", "zero_flow_epe", "constant_depth_sc_inv",
        "tran_x_negative_fraction", "photometric_error", "near_camera2_fraction")


def pair_statistics(sample: dict) -> dict[str, float]:
    """Rotation angle, median triangulation angle, fractions and median depth of one sample."""
    import torch

    from demon_lab.core import geometry as geo
    from demon_lab.core import warping
    from demon_lab.core.metrics import flow_epe

    inv = sample["inv_depth"][None].double()
    motion = sample["motion"][None].double()
    tri = geo.triangulation_angle(inv, motion, sample["intrinsics"][None].double()).numpy()
    valid = sample["valid"].numpy()
    flow = torch.nan_to_num(sample["flow"], nan=0.0)[None]
    warped = warping.warp_image(sample["image2"][None], flow)[0]
    seen = sample["visible"][0] & (warped.abs().sum(0) > 0)  # 0: a neighbour fell outside image 2
    photometric = (warped - sample["image1"]).abs().mean(0)[seen].mean().item() * 255
    _, inv2 = geo.reproject(inv, motion, sample["intrinsics"][None].double(),
                            sample["intrinsics2"][None].double())
    near = bool((inv / inv2 < 0.1).any())  # z2 / z1 = inv1 / inv2; NaN (invalid depth) compares False
    return {
        "rot_deg": math.degrees(float(sample["motion"][:3].double().norm())),
        "tri_deg": float(np.nanmedian(tri)),
        "valid_fraction": float(valid.mean()),
        "visible_fraction": float(sample["visible"].numpy().mean()),
        "median_depth": float(np.median(1.0 / inv.numpy()[valid[None]])),
        "zero_flow_epe": flow_epe(np.zeros_like(sample["flow"].numpy()), sample["flow"].numpy()),
        "constant_depth_sc_inv": float(np.log(inv.numpy()[valid[None]]).std()),
        "tran_x_negative": float(sample["motion"][3] < 0),
        "photometric_error": photometric,
        "near_camera2": float(near),
    }


FLOW_PRIORS = ("dis", "dis_x2")
MOTION_PRIORS = ("ransac", "ransac_prior")  # (keys of demon_lab.nets.prior.RANSAC_SETTINGS)


def prior_statistics(sample: dict) -> dict[str, float]:
    """The classical priors of one sample: each flow prior's EPE, and the errors of each RANSAC motion
    read from it (:mod:`demon_lab.nets.prior`)."""
    import torch

    from demon_lab.core.metrics import flow_epe, motion_errors, resize_nearest
    from demon_lab.nets import prior

    pair = torch.cat([sample["image1"], sample["image2"]])[None].float()
    intrinsics = sample["intrinsics"][None].float()
    truth = sample["flow"].numpy()
    out = {}
    for name in FLOW_PRIORS:
        flow = prior.dis_prior(pair, level=2, upsample=prior.DIS_UPSAMPLE[name])
        out[f"{name}_epe"] = flow_epe(resize_nearest(flow[0].double().numpy(), truth.shape[1:]), truth)
        for motion_prior in MOTION_PRIORS:
            settings = prior.RANSAC_SETTINGS[motion_prior]
            errors = motion_errors(prior.ransac_motion(flow, intrinsics, *settings)[0].double().numpy(),
                                   sample["motion"].double().numpy())
            out[f"{name}_{motion_prior}_rot_deg"] = errors["rot_deg"]
            out[f"{name}_{motion_prior}_tran_deg"] = errors["tran_deg"]
    return out


def dataset_statistics(datasets: list, n: int, priors: bool = False) -> dict[str, Any]:
    """Table 1 statistics over the first ``n`` pairs of the datasets (in order); with ``priors``,
    the classical priors' errors too (:func:`prior_statistics`)."""
    rows = []
    for dataset in datasets:
        for index in range(len(dataset)):
            if len(rows) >= n:
                break
            sample = dataset.load(index)
            rows.append({**pair_statistics(sample), **(prior_statistics(sample) if priors else {})})
    if not rows:
        raise ConfigError("the configured split has no pair")
    rot = np.array([r["rot_deg"] for r in rows])
    tri = np.array([r["tri_deg"] for r in rows])
    first = datasets[0]
    return {
        "source": ", ".join(sorted({d.name for d in datasets})),
        "perfect_gt": first.perfect_gt,
        "photorealistic": first.photorealistic,
        "outdoor": first.outdoor,
        "n_pairs": len(rows),
        "rot_mean_deg": float(rot.mean()), "rot_std_deg": float(rot.std()),
        "tri_mean_deg": float(tri.mean()), "tri_std_deg": float(tri.std()),
        "valid_fraction": float(np.mean([r["valid_fraction"] for r in rows])),
        "visible_fraction": float(np.mean([r["visible_fraction"] for r in rows])),
        "median_depth": float(np.median([r["median_depth"] for r in rows])),
        "zero_flow_epe": float(np.nanmean([r["zero_flow_epe"] for r in rows])),
        "constant_depth_sc_inv": float(np.mean([r["constant_depth_sc_inv"] for r in rows])),
        "tran_x_negative_fraction": float(np.mean([r["tran_x_negative"] for r in rows])),
        "photometric_error": float(np.nanmean([r["photometric_error"] for r in rows])),
        "near_camera2_fraction": float(np.mean([r["near_camera2"] for r in rows])),
        **{k: float(np.nanmean([r[k] for r in rows])) for k in rows[0] if k.startswith(FLOW_PRIORS)},
    }


def format_table(stats: dict[str, Any]) -> str:
    header = ("Dataset", "Perfect GT", "Photorealistic", "Outdoor", "Rot. avg", "Rot. std",
              "Tri. avg", "Tri. std", "pairs", "valid", "visible", "median depth")
    row = (stats["source"], stats["perfect_gt"], stats["photorealistic"], stats["outdoor"],
           f"{stats['rot_mean_deg']:.1f}", f"{stats['rot_std_deg']:.1f}",
           f"{stats['tri_mean_deg']:.1f}", f"{stats['tri_std_deg']:.1f}", str(stats["n_pairs"]),
           f"{stats['valid_fraction']:.2f}", f"{stats['visible_fraction']:.2f}",
           f"{stats['median_depth']:.2f}")
    return text_table(header, [row], left=4)


def format_priors(stats: dict[str, Any]) -> str:
    """The classical priors' errors: one row per flow prior (EPE), one column pair per RANSAC motion."""
    header = ("flow prior", "EPE", *(f"{m} {e}" for m in MOTION_PRIORS for e in ("rot", "tran")))
    rows = [(name, f"{stats[f'{name}_epe']:.4f}",
             *(f"{stats[f'{name}_{m}_{e}_deg']:.2f}" for m in MOTION_PRIORS for e in ("rot", "tran")))
            for name in FLOW_PRIORS]
    return text_table(header, rows, left=1)


def split_datasets(cfg: DictConfig) -> list:
    from demon_lab.pipeline.config import drop_missing_sources, instantiate

    if cfg.split not in ("train", "val", "test"):
        raise ConfigError(f"split: {cfg.split!r} is not one of train, val, test")
    for note in drop_missing_sources(cfg):  # DeMoN's files under data.root: whichever are there
        print(f"[demon_lab.data_stats] {note}", flush=True)
    entries = cfg.data[cfg.split]
    if cfg.split == "train":
        entries = [e.dataset for e in entries]
    return [instantiate(e) for e in entries]


def run(cfg: DictConfig) -> dict[str, Any]:
    if not isinstance(cfg.n, int) or cfg.n < 1:
        raise ConfigError(f"n: expected a positive integer, got {cfg.n!r}")
    if not isinstance(cfg.priors, bool):
        raise ConfigError(f"priors: expected true or false, got {cfg.priors!r}")
    stats = dataset_statistics(split_datasets(cfg), cfg.n, cfg.priors)
    print(format_table(stats))
    if cfg.priors:
        print(format_priors(stats))
    if cfg.out:
        Path(cfg.out).write_text(json.dumps(stats, indent=2) + "\n")
        print(f"wrote {cfg.out}")
    return stats


@hydra.main(version_base="1.3", config_path=str(CONF), config_name="data_stats")
def main(cfg: DictConfig) -> None:
    from omegaconf.errors import OmegaConfBaseException

    from demon_lab.data.sample import DataError

    try:
        run(cfg)
    except (ConfigError, DataError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except OmegaConfBaseException as e:
        print(f"error: {str(e).splitlines()[0]}", file=sys.stderr)
        sys.exit(2)

