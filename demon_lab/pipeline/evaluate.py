"""Evaluation on the test sets with DeMoN's protocol (docs/reference.md §7), shared by the DeMoN
chain and the classical baselines.

:func:`evaluate_test_sets` scores every test set of a job's config with the job's method;
:func:`evaluate_dataset` is the chain on one set, for every iteration and the refined depth;
:func:`run_chain` is the chain over a dataset's batches, the one loop that every evaluation of the
chain runs through (this module's, the stages' held-apart curves, the diagnosis, the device check).

Per test set, for iteration k = 0 (bootstrap) .. ``iterations``: depth metrics of the level-2
depth, motion metrics and flow EPE of pass k; for ``refined``: depth metrics of the refinement
net's depth and the motion of the last pass. The summary metric of a set (``test/<set>/<metric>``
in MLflow) is the refined depth with the last pass's motion and flow, as DeMoN's summary uses
``3_refined`` for depth and ``3`` for motion.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch.utils.data import DataLoader

from demon_lab.core import execution, metrics, scoring
from demon_lab.nets.chain import ChainOutput, DeMoN, ground_truth_inputs
from demon_lab.pipeline.methods import method
from demon_lab.pipeline.settings import JobSettings

log = logging.getLogger(__name__)


def run_chain(chain: DeMoN, batches: Iterable[dict[str, Any]], iterations: int, oracle: str | None = None,
              precision: Any = 32, channels_last: bool = False, refine: bool = True, priors: bool = False
              ) -> Iterator[tuple[dict[str, Any], dict[str, Any], ChainOutput]]:
    """The chain on each batch of ``batches`` (a loader, or any iterable of collated batches):
    yields the batch as given, the batch on the chain's device (the device of its parameters; its
    image-like tensors channels-last if ``channels_last``) and the chain's output, ``iterations`` passes after
    the bootstrap and, with ``refine``, the refined depth. The chain runs without gradients, its nets in
    ``precision`` (:mod:`demon_lab.core.execution`; the predictions it returns are float32);
    ``oracle`` feeds it the batch's ground truth (:class:`DeMoN`); ``priors`` adds its classical priors
    alone (``ChainOutput.priors``, where it has them). A batch that carries the pairs' bootstrap priors
    (``prior_flow``, ``prior_motion``: :mod:`demon_lab.pipeline.stages.priors`) gives them to the chain,
    which then does not compute them. The caller's code between the
    batches runs outside that autocast region, with gradients as the caller has them."""
    device = next(chain.parameters()).device
    for batch in batches:
        inputs = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        inputs = execution.channels_last_batch(inputs, channels_last)
        gt = {"inv_depth": inputs["inv_depth"], "motion": inputs["motion"]} if oracle else None
        given = {k: inputs[k] for k in ("prior_flow", "prior_motion") if k in inputs}
        with torch.no_grad(), execution.autocast(device, precision):
            out = chain(inputs["image1"], inputs["image2"], inputs["intrinsics"], iterations=iterations,
                        oracle=oracle, gt=gt, refine=refine, **({"priors": True} if priors else {}), **given)
        yield batch, inputs, out


def evaluate_dataset(chain: DeMoN, dataset, iterations: int, oracle: str | None = None,
                     batch_size: int = 4, max_samples: int | None = None, keep: int = 0,
                     refined: bool = True, histogram: metrics.PixelHistogram | None = None,
                     precision: Any = 32, channels_last: bool = False
                     ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Per-sample metric rows (one per sample and iteration, ``it`` = 0..N or 'refined'; 'priors': the
    chain's classical priors alone, where it has both bootstrap priors and no oracle feeds it) and the
    raw predictions of the first ``keep`` samples (for visualisations), scored by
    :func:`demon_lab.core.scoring.score`. ``refined=False`` (the refinement net was not trained) leaves
    out the refined rows. ``histogram`` collects the per-pixel errors of the final depth (refined, else
    the last pass). The chain runs as :func:`run_chain` runs it (``precision``, ``channels_last``); the
    metrics are computed on the host, from the float32 predictions."""
    n = len(dataset) if max_samples is None else min(len(dataset), int(max_samples))
    loader = DataLoader(torch.utils.data.Subset(dataset, range(n)), batch_size=batch_size, shuffle=False)
    batches = run_chain(chain, loader, iterations, oracle, precision, channels_last, refine=refined,
                        priors=oracle is None)
    return scoring.score(dataset, _chain_predictions(batches, refined), keep, histogram)


def _chain_predictions(batches, refined: bool) -> Iterator[scoring.Prediction]:
    """Each pair of :func:`run_chain`'s batches as the chain predicted it: its priors alone (where
    it has them), every pass, and the refined depth with the last pass's motion and flow."""
    def predicted(p, i: int, inv_depth=None) -> dict[str, torch.Tensor]:
        return {"inv_depth": p.inv_depth[i, 0].cpu() if inv_depth is None else inv_depth,
                "motion": p.motion[i].cpu(), "flow": p.flow[i].cpu()}

    for batch, _, out in batches:
        for i in range(batch["image1"].shape[0]):
            sample = {**{k: v[i] for k, v in batch.items() if isinstance(v, torch.Tensor)}, "id": batch["id"][i]}
            groups: dict[Any, dict[str, torch.Tensor]] = {}
            if out.priors is not None:  # the classical priors alone: what the nets add is measured against it
                groups["priors"] = predicted(out.priors, i)
            groups.update({k: predicted(p, i) for k, p in enumerate(out.passes)})
            last = out.passes[-1]
            if refined:
                groups["refined"] = predicted(last, i, inv_depth=out.refined[i, 0].cpu())
            yield scoring.Prediction(sample, groups, "refined" if refined else len(out.passes) - 1,
                                     flow=last.flow[i].cpu(), normals=last.normals[i].cpu())


def summarize(rows: Sequence[dict[str, Any]], iterations: int) -> dict[str, float]:
    """Means over samples: ``it<k>/<metric>``, ``refined/<metric>``, ``priors/<metric>`` and the summary ``<metric>``
    (refined depth when there is one, else the last pass's)."""
    out: dict[str, float] = {}
    groups = [*range(iterations + 1), *[g for g in ("refined", "priors") if any(r["it"] == g for r in rows)]]
    for it in groups:
        means = metrics.summarize([{k: v for k, v in r.items() if k != "it"} for r in rows if r["it"] == it])
        prefix = it if it in ("refined", "priors") else f"it{it}"
        out.update({f"{prefix}/{k}": v for k, v in means.items() if not k.startswith("n_failed")})
    for key in metrics.DEPTH_KEYS:
        source = f"refined/{key}" if "refined" in groups else f"it{iterations}/{key}"
        if source in out:
            out[key] = out[source]
    for key in (*metrics.MOTION_KEYS, "epe"):
        if f"it{iterations}/{key}" in out:
            out[key] = out[f"it{iterations}/{key}"]
    return out


@dataclass
class TestSetResult:
    """One test set scored by one job: per-sample rows, their means, the pixel-error histogram of
    the final depth and the first predictions (for pictures)."""

    name: str
    rows: list[dict[str, Any]]
    summary: dict[str, float]
    histogram: dict[str, Any]
    kept: list[dict[str, Any]] = field(default_factory=list)


def evaluate_test_sets(job: JobSettings, chain: DeMoN | None, refined: bool) -> list[TestSetResult]:
    """Score the job's method (the chain or a classical baseline) on every set of ``data.test``.

    ``chain``: the trained chain (``method=demon``; ``base_mat_f`` reads its flow), None for the
    other baselines; ``refined``: whether the refinement net is trained (its rows are scored)."""
    from demon_lab.baselines import summarize_baseline
    from demon_lab.pipeline.config import instantiate

    scored = method(job.method)
    keep = max(job.eval.visualize, job.eval.point_clouds)
    if scored.scores_passes and chain is not None:  # on the device it trained on (Lightning hands it back on the CPU)
        chain = chain.to(execution.evaluation_device(job))
    results = []
    for entry in job.data.test:
        dataset = instantiate(entry)
        log.info("evaluating on %s (%d pairs)", dataset.name, len(dataset))
        histogram = metrics.PixelHistogram()
        if scored.scores_passes:
            rows, kept = evaluate_dataset(chain, dataset, job.iterations, job.oracle, job.eval.batch_size,
                                          job.eval.max_samples, keep=keep, refined=refined, histogram=histogram,
                                          precision=job.precision, channels_last=job.model.channels_last)
            summary = summarize(rows, job.iterations)
            if job.eval.ceiling:
                summary.update(flow_ceiling(chain, dataset, job))
        else:
            rows, kept = _evaluate_baseline(job, entry, dataset, chain, keep, histogram)
            summary = summarize_baseline(rows)
        results.append(TestSetResult(dataset.name, rows, summary, histogram.to_dict(), kept))
    return results


def flow_ceiling(chain: DeMoN, dataset, job: JobSettings) -> dict[str, float]:
    """``eval.ceiling``: how much camera motion the flow dm1 reads in the bootstrap pass (flow1's, at
    level 2; under ``oracle=flow`` the ground truth at level 2, as dm1 is fed it) carries on ``dataset``,
    and how much each reader of it loses
    (:func:`demon_lab.baselines.ceiling.ceiling`, against the ground-truth flow at the flow's grid, its
    distances in pixels of the input image):
    means over the pairs with a known motion (``ceiling/within_1px``, ``ceiling/ransac/tran_deg``, ...;
    ``ceiling/READER/n_failed``: the pairs a reader read no motion from)."""
    import numpy as np

    from demon_lab.baselines.ceiling import ceiling

    n = len(dataset) if job.eval.max_samples is None else min(len(dataset), int(job.eval.max_samples))
    loader = DataLoader(torch.utils.data.Subset(dataset, range(n)), batch_size=job.eval.batch_size, shuffle=False)
    rows = []
    for batch, _, out in run_chain(chain, loader, 0, job.oracle, job.precision, job.model.channels_last,
                                   refine=False):
        read = out.passes[0].flow
        if job.oracle == "flow":  # (the flow dm1 read: the oracle's, not flow1's)
            read = ground_truth_inputs(batch, batch["intrinsics"]).flow
        for i in range(batch["image1"].shape[0]):
            sample = {k: v[i] for k, v in batch.items() if isinstance(v, torch.Tensor)}
            truth = metrics.ground_truth(sample, dataset)
            motion = np.asarray(truth["motion"], dtype=np.float64)
            if not np.isfinite(motion).all():  # (a source without camera poses)
                continue
            flow = read[i].double().cpu().numpy()
            gt_flow = metrics.resize_nearest(np.asarray(truth["flow"], dtype=np.float64), flow.shape[1:])
            cameras = {k: sample[k].double().numpy() for k in ("intrinsics", "intrinsics2") if k in sample}
            rows.append(ceiling(flow, gt_flow, {**cameras, "motion": motion}, seed=job.baseline.seed,
                                image_width=int(job.data.size[1])))
    if not rows:
        return {}
    out = {}
    for key in rows[0]:
        values = np.array([r[key] for r in rows], dtype=np.float64)
        if key.endswith("n_failed"):
            out[f"ceiling/{key}"] = float(values.sum())
        else:
            finite = values[np.isfinite(values)]
            out[f"ceiling/{key}"] = float(finite.mean()) if finite.size else float("nan")
    return out


def _evaluate_baseline(job: JobSettings, entry, dataset, chain: DeMoN | None, keep: int,
                       histogram: metrics.PixelHistogram):
    """A classical baseline on one test set: it reads each pair at ``baseline.size`` (the source's
    native resolution by default; ``base_mat_f``, which reads the chain's flow, at the chain's) and is
    scored on the same ground truth as the chain."""
    from demon_lab.baselines import evaluate_baseline

    params = job.baseline
    inputs = None if method(job.method).at_chain_size else baseline_inputs(entry, dataset, params.size)
    return evaluate_baseline(job.method, dataset, params, chain=chain, iterations=job.iterations,
                             inputs=inputs, max_samples=job.eval.max_samples, keep=keep,
                             histogram=histogram)


def baseline_inputs(entry, dataset, size):
    """The test set ``entry`` (instantiated as ``dataset``) at the baselines' resolution ``size``:
    ``"native"`` (``dataset.native_size``) or (H, W); ``dataset`` itself when that is its size."""
    from demon_lab.pipeline.config import instantiate

    target = dataset.native_size if size == "native" else (int(size[0]), int(size[1]))
    if target == dataset.size:
        return dataset
    # the inputs only: the scoring reads the ground truth of ``dataset``
    return instantiate(entry, size=None if target is None else list(target), gt_size=None, eigen_crop=False)
