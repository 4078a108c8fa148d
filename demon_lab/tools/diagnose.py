"""``python -m demon_lab.diagnose [overrides]``: what each pass of a trained chain passes on.

DeMoN's iterative flow net is fed the flow induced by the previous pass's depth and motion (its
"prior"); whether the passes improve depends on how good that prior is and how closely the net
follows it. For every test set with ground truth this prints, per pass (0 = bootstrap), means over
the pairs of:

- ``epe``: the pass's flow against the ground-truth flow (level 2, normalised units, as the loss);
- ``flow``: the mean length of the pass's flow (``gt flow``: of the ground truth, which is also the
  EPE of predicting no flow at all);
- ``prior`` / ``prior epe`` (passes 1+): the mean length and EPE of the flow induced by the previous
  depth and motion, exactly as the iterative flow net receives it (vectors of norm >= 1 set to 0);
- ``follow``: the mean distance between the pass's flow and that prior (0: the net copies it);
- ``|t|``, ``rot``: the predicted translation's length (ground truth: 1) and rotation angle in
  degrees (``gt rot``: the ground truth's);
- ``inv<=0``: the share of pixels whose predicted inverse depth is not positive (no depth there);
  row ``refined``: the same for the refinement net's full-resolution depth (when it is trained).

The chain's stages must be in the stage cache (``python -m demon_lab`` with the same overrides
trains them), or ``model.weights=FILE train=false`` names the weights to diagnose as they are
(DeMoN's released ones: docs/released_model.md); nothing is trained or tracked here.
``--out FILE`` also writes the numbers as JSON.

    python -m demon_lab.diagnose                       # the default chain (scale cpu, seed 0)
    python -m demon_lab.diagnose seed=1 iterations=5 --out diag.json
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path

import torch

from demon_lab.core import losses
from demon_lab.nets.chain import ChainOutput, downsample_image, flow_net_inputs, net_intrinsics
from demon_lab.pipeline.evaluate import run_chain

COLUMNS = ("epe", "flow", "gt_flow", "prior", "prior_epe", "follow", "t_norm", "rot_deg", "gt_rot_deg",
           "nonpositive_depth")
"""The diagnosis's quantities, in table order (their names: :data:`demon_lab.core.metrics.COLUMNS`)."""


def _pixel_mean(x: torch.Tensor) -> torch.Tensor:
    """Per-sample mean over the finite pixels of a (B, H, W) map (NaN for a sample with none)."""
    finite = torch.isfinite(x)
    total = torch.where(finite, x, torch.zeros_like(x)).flatten(1).sum(1)
    count = finite.flatten(1).sum(1)
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, math.nan))


def diagnose_batch(batch: dict, out: ChainOutput, compat: str | None = None,
                   refine: bool = False) -> list[list[dict[str, float]]]:
    """Per pass of ``out`` (the chain's output on ``batch``), per sample: the numbers the module
    docstring names; with ``refine``, one more entry for the refined depth (only
    ``nonpositive_depth`` set). ``compat``: the chain's, with which its iterative flow net builds
    the prior."""
    gt = losses.ground_truth(batch)
    image2_2, K = downsample_image(batch["image2"]), batch["intrinsics"]
    gt_flow = gt["flow2"]
    n = batch["image1"].shape[0]
    passes = []
    for k, p in enumerate(out.passes):
        if k == 0:
            prior = None
        else:
            prev = out.passes[k - 1]
            prior = flow_net_inputs(image2_2, prev.inv_depth, prev.normals, prev.motion,
                                    net_intrinsics(K, compat), compat)[:, 3:5]
        nan = torch.full((n,), math.nan)
        row = {
            "epe": _pixel_mean((p.flow - gt_flow).norm(dim=1)),
            "flow": _pixel_mean(p.flow.norm(dim=1)),
            "gt_flow": _pixel_mean(gt_flow.norm(dim=1)),
            "prior": nan if prior is None else _pixel_mean(prior.norm(dim=1)),
            "prior_epe": nan if prior is None else _pixel_mean((prior - gt_flow).norm(dim=1)),
            "follow": nan if prior is None else _pixel_mean((p.flow - prior).norm(dim=1)),
            "t_norm": p.motion[:, 3:].norm(dim=1),
            "rot_deg": torch.rad2deg(p.motion[:, :3].norm(dim=1)),
            "gt_rot_deg": torch.rad2deg(gt["motion"][:, :3].norm(dim=1)),
            "nonpositive_depth": (~(p.inv_depth > 0)).flatten(1).float().mean(1),
        }
        passes.append([{key: float(v[i]) for key, v in row.items()} for i in range(n)])
    if refine:
        share = (~(out.refined[:, :1] > 0)).flatten(1).float().mean(1)
        passes.append([{**dict.fromkeys(COLUMNS, math.nan), "nonpositive_depth": float(share[i])} for i in range(n)])
    return passes


def summarize(per_sample: Sequence[Sequence[dict[str, float]]]) -> list[dict[str, float]]:
    """Mean over the samples of each pass (NaN where no sample has a finite value)."""
    out = []
    for samples in per_sample:
        means = {}
        for key in COLUMNS:
            values = [s[key] for s in samples if math.isfinite(s[key])]
            means[key] = sum(values) / len(values) if values else math.nan
        means["pairs"] = len(samples)
        out.append(means)
    return out


def format_table(results: dict[str, list[dict[str, float]]]) -> str:
    from demon_lab.core.metrics import column
    from demon_lab.reporting.tables import number, text_table

    header = ["test set", "pass", *[column(key).text for key in COLUMNS]]
    return text_table(header, [[name, str(r.get("pass", k)), *[number(r[key]) for key in COLUMNS]]
                               for name, passes in results.items() for k, r in enumerate(passes)])


def run(overrides: Sequence[str], out: str | None = None) -> dict[str, list[dict[str, float]]]:
    from hydra import compose, initialize_config_dir

    from demon_lab.pipeline.config import ConfigError, drop_missing_sources, instantiate
    from demon_lab.pipeline.stages.schedule import build_chain, load_stage, stage_dirs
    from demon_lab.pipeline.validate import validate
    from demon_lab.resources import CONF

    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    drop_missing_sources(cfg, cfg.train)
    job = validate(cfg)
    if job.threads is not None:
        from demon_lab.core.execution import set_threads

        set_threads(job.threads)
    chain = build_chain(job)  # with model.weights loaded, if given
    if job.model.weights and not job.train:  # the given weights as they are (DeMoN's released ones)
        from demon_lab.pipeline.weights import read_nets

        refine = "refine_net" in read_nets(job.model.weights, mmap=True)
    else:
        stages = stage_dirs(job)
        if not {s.name for s in stages} >= {"flow1", "dm1", "flow2", "dm2", "iterative"}:
            raise ConfigError("schedule.until: the diagnosis needs the chain up to the iterative stage")
        refine = any(s.name == "refine" and s.done() for s in stages)
        stages = [s for s in stages if s.name != "refine" or refine]
        missing = [s.name for s in stages if not s.done()]
        if missing:
            raise ConfigError(f"stages not in the cache: {', '.join(missing)} (train them with "
                              f"python -m demon_lab {' '.join(overrides)})")
        for stage in stages:
            load_stage(chain, stage)
    chain.eval()
    results = {}
    for spec in cfg.data.test:
        dataset = instantiate(spec)
        loader = torch.utils.data.DataLoader(dataset, batch_size=job.eval.batch_size)
        per_pass: list[list[dict[str, float]]] = [[] for _ in range(job.iterations + 1 + refine)]
        for _, batch, output in run_chain(chain, loader, job.iterations, refine=refine):  # CPU, float32
            for k, samples in enumerate(diagnose_batch(batch, output, chain.compat, refine)):
                per_pass[k] += samples
        results[dataset.name] = summarize(per_pass)
        for k, row in enumerate(results[dataset.name]):
            row["pass"] = "refined" if k > job.iterations else k
    print(f"[demon_lab] diagnosis (scale {cfg.scale.name}, seed {cfg.seed}; flow at level 2, "
          f"normalised units; rot in degrees):")
    print(format_table(results))
    if out:
        Path(out).write_text(json.dumps({"overrides": list(overrides), "passes": results}, indent=1))
        print(f"wrote {out}")
    return results


def main(argv: Sequence[str] | None = None) -> int:
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from demon_lab.pipeline.config import ConfigError

    args = list(sys.argv[1:] if argv is None else argv)
    if any(a in ("-h", "--help") for a in args):
        print(__doc__)
        return 0
    out = None
    if "--out" in args:
        i = args.index("--out")
        if i + 1 >= len(args):
            print("error: --out needs a file name", file=sys.stderr)
            return 2
        out = args[i + 1]
        del args[i:i + 2]
    try:
        run(args, out)
    except (ConfigError, HydraException, OmegaConfBaseException) as e:
        print(f"error: {str(e).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0

