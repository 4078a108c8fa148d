"""The ``train`` section of ``python -m demon_lab.bench``: where a stage's time goes, for each shipped
design at the ``cpu`` scale (the profile, DeMoN's design, the learned design) and each of its stages.

* **The bare step**: the stage's own module, built as the job builds it (its options, the design's
  nets), on a batch of the design's training pairs (each carrying its classical priors where the
  design has them, as the job's draws do), forward, backward, the gradients clipped and Adam with its
  learning-rate schedule, without the memo of ``trainer.reuse_frozen``: what a step computes, nothing
  else. Its FLOP/s against the machine's float32 matmul, and its largest costs by self time (``torch.profiler``).
* **The job's loop**: ``python -m demon_lab [design] scale.steps.NAME=N ... trainer.profile=true`` in a
  temporary stage cache and MLflow store, the scene cache as the user has it: each stage's loop once
  running (``stage/NAME/loop_steps_per_second``: past its first tenth of batches, with the loading,
  scoring, checkpoints and logging between them) against the bare step, the whole stage's rate
  (``steps_per_second``: its set-up and end too), and the largest parts of the loop beside the
  batches as Lightning's SimpleProfiler timed them (``stage/NAME/profile/...``: the loader, the
  callbacks that score the held-apart sets, keep the best nets and write checkpoints, the rest).
* The correlation front's operation against the shifted products it replaced, channels-last and
  torch.compile on the profile's flow1, full-chain inference and MLflow's share of a stage's time.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence

import torch

from demon_lab.reporting.tables import markdown_table
from demon_lab.tools.benchmarking import machine_line, measure

DESIGNS: dict[str, tuple[str, ...]] = {
    "profile": (),
    "DeMoN's design": ("design=demon",),
    "learned": ("design=learned",),
}
"""The shipped designs at the cpu scale, by the overrides that choose them (DeMoN's design,
``design=demon``: the cpu_departures study's row ``demon``)."""

LOOP_STEPS = {"flow1": 1000, "dm1": 600, "flow2": 400, "dm2": 400, "iterative": 300, "refine": 300}
"""Steps of each stage in the job the bench times (each long enough to hold its held-apart scoring,
every 250 steps, and its checkpoints)."""

TOP = 3
"""Entries of each stage's largest costs in the table."""


def _compose(overrides: Sequence[str]):
    from hydra import compose, initialize_config_dir

    from demon_lab.resources import CONF

    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def training_batch(cfg, chain, size: int, draws: int = 0) -> dict[str, torch.Tensor]:
    """``size`` training draws of ``cfg``'s sources in turn (the job's data path: the scene cache,
    DeMoN's augmentation), each with the classical priors of ``chain`` where it has them."""
    from torch.utils.data import default_collate

    from demon_lab.pipeline.config import instantiate
    from demon_lab.pipeline.stages.priors import PairPriors

    sources = [instantiate(e.dataset) for e in cfg.data.train]
    samples = [sources[i % len(sources)][(i // len(sources), draws + i)] for i in range(size)]
    priors = PairPriors.of(chain)
    if priors is not None:
        samples = [{**s, **p} for s, p in zip(samples, priors.compute(samples), strict=True)]
    batch = default_collate([{k: v for k, v in s.items() if k != "id"} for s in samples])
    return batch


def mid_stage(module) -> None:
    """The step as a stage trains it once its ramps have ended (outside a Trainer the step count stays
    0): every ramped term at full weight, except the terms a stage never turns on (``sig_start: 1``),
    and flow1's flow, not ground truth, fed to dm1 (``gt_flow_warmup``)."""
    module.ramp = lambda duration, start=0.0: 0.0 if start >= 1 else 1.0
    if hasattr(module.spec, "gt_flow_warmup"):
        module.spec = dataclasses.replace(module.spec, gt_flow_warmup=0.0)
    module.memo = None


def bare_steps(overrides: Sequence[str], repeats: int, peak: float) -> dict[str, dict]:
    """Each scheduled stage's bare step under ``overrides``: steps/s, FLOP/s as a share of ``peak``, and
    its largest costs by self time."""
    from torch.utils.flop_counter import FlopCounterMode

    from demon_lab.pipeline.settings import JobSettings
    from demon_lab.pipeline.stages.schedule import build_chain
    from demon_lab.pipeline.stages.training import stage_module

    cfg = _compose(overrides)
    job = JobSettings.of(cfg)
    out = {}
    for name in job.schedule.trained():
        torch.manual_seed(0)
        chain = build_chain(job)
        module = stage_module(job, chain, name)
        mid_stage(module)
        module.freeze_upstream()
        module.train()
        step = training_step(module, training_batch(cfg, chain, job.stages[name].batch_size or job.data.batch_size),
                             job.schedule.grad_clip)
        for _ in range(3):  # (the iterative stage's queue fills)
            step()
        with FlopCounterMode(display=False) as counter:
            step()
        seconds = measure(step, repeats, block_s=0.1)  # (2 s at the default effort: a shorter window was noisy)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            for _ in range(5):
                step()
        events = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
        total = sum(e.self_cpu_time_total for e in events)
        top = [(e.key, e.self_cpu_time_total / total) for e in events[:TOP]]
        out[name] = {"rate": 1 / seconds, "flops": counter.get_total_flops() / seconds, "top": top}
    return out


def training_step(module, batch, grad_clip: float | None = None):
    """One training step of ``module`` on ``batch`` as the job's Trainer takes it: the stage's loss, its
    backward pass, the gradients clipped by value (``schedule.grad_clip``), the optimiser and its
    learning-rate schedule."""
    from demon_lab.core import losses

    optimisation = module.configure_optimizers()
    optimizer, scheduler = optimisation["optimizer"], optimisation["lr_scheduler"]["scheduler"]
    trained = [p for group in optimizer.param_groups for p in group["params"]]

    def step():
        loss, _ = module.stage_loss(batch, losses.ground_truth(batch))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if grad_clip:
            torch.nn.utils.clip_grad_value_(trained, grad_clip)
        optimizer.step()
        scheduler.step()

    return step


BESIDE_THE_BATCH = ("trainingepochloop.train_dataloader_next", "callback.")


def loop_rates(overrides: Sequence[str]) -> dict[str, dict]:
    """Each stage's steps/s in the job (``LOOP_STEPS``, ``trainer.profile=true``) and the largest parts
    of its loop beside the batches: the loader, each callback, the time outside both (shares of the
    stage's time)."""
    import mlflow

    steps = [f"scale.steps.{k}={v}" for k, v in LOOP_STEPS.items()]
    with tempfile.TemporaryDirectory() as tmp:
        uri = f"sqlite:///{tmp}/mlflow.db"
        cmd = [sys.executable, "-m", "demon_lab", *overrides, *steps, "iterations=0", "eval.max_samples=1",
               "trainer.profile=true", f"cache_dir={tmp}/cache", f"tracking.uri={uri}",
               f"tracking.artifact_dir={tmp}/artifacts", f"hydra.run.dir={tmp}/out"]
        subprocess.run(cmd, check=True, cwd=tmp, stdout=subprocess.DEVNULL)
        client = mlflow.MlflowClient(tracking_uri=uri)
        metrics: dict[str, float] = {}
        for run in client.search_runs([e.experiment_id for e in client.search_experiments()]):
            metrics.update({k: v for k, v in run.data.metrics.items() if k.startswith("stage/") and k.count("/") >= 2})
    out = {}
    for name in LOOP_STEPS:
        prefix = f"stage/{name}/"
        if prefix + "steps_per_second" not in metrics:
            continue
        seconds = metrics[prefix + "seconds"]
        parts = {k[len(prefix + "profile/"):-len("_seconds")]: v / seconds for k, v in metrics.items()
                 if k.startswith(prefix + "profile/") and (any(p in k for p in BESIDE_THE_BATCH) or "outside" in k)}
        out[name] = {"rate": metrics.get(prefix + "loop_steps_per_second", metrics[prefix + "steps_per_second"]),
                     "stage_rate": metrics[prefix + "steps_per_second"], "parts": parts}
    return out


def _named(part: str) -> str:
    return {"trainingepochloop.train_dataloader_next": "loader", "outside": "rest"}.get(
        part, part.replace("callback.", "").replace(".on_train_batch_end", ""))


def design_table(bare: Mapping[str, Mapping[str, dict]], loop: Mapping[str, Mapping[str, dict]], peak: float) -> str:
    """One row per design and stage: the bare step, the job's loop and their ratio, the step's largest
    costs and the loop's largest parts beside its batches."""
    rows = []
    for design, stages in bare.items():
        for name, b in stages.items():
            job = loop.get(design, {}).get(name)
            top = ", ".join(f"{key} {share:.0%}" for key, share in b["top"])
            parts = "" if job is None else ", ".join(
                f"{_named(k)} {v:.1%}" for k, v in sorted(job["parts"].items(), key=lambda kv: -kv[1])[:TOP])
            rows.append([design, name, f"{b['rate']:.2f}", f"{b['flops'] / peak:.1%}",
                         "" if job is None else f"{job['rate']:.2f}",
                         "" if job is None else f"{job['rate'] / b['rate']:.1%}",
                         "" if job is None else f"{job.get('stage_rate', job['rate']):.2f}", top, parts])
    return markdown_table(["design", "stage", "bare step, steps/s", "of matmul", "job's loop, steps/s", "loop / step",
                           "whole stage, steps/s", "the step's largest self times", "the loop beside its batches"],
                          rows, "llrrrrrll")


def correlation_by_shifts(features1: torch.Tensor, features2: torch.Tensor, max_displacement: int,
                          stride: int) -> torch.Tensor:
    """The correlation as ``CORRELATION_VERSION`` 1 computed it: the channel mean of each shifted product,
    concatenated, differentiated by autograd (what the operation replaced, and what tests check it against)."""
    import torch.nn.functional as F

    reach = (max_displacement // stride) * stride
    height, width = features1.shape[2:]
    padded = F.pad(features2, (reach, reach, reach, reach))
    shifts = range(-reach, reach + 1, stride)
    return torch.cat([(features1 * padded[:, :, reach + dy: reach + dy + height, reach + dx: reach + dx + width])
                      .mean(1, keepdim=True) for dy in shifts for dx in shifts], 1)


def correlation_rows(repeats: int) -> list[list[str]]:
    """The correlation front at the learned flow1's size (batch 8, 16 channels at 32x24, [8, 2]),
    forward and backward: the operation against the shifted products it replaced."""
    from demon_lab.nets.blocks import correlation

    g = torch.Generator().manual_seed(0)
    f1, f2 = (torch.randn(8, 16, 24, 32, generator=g).requires_grad_() for _ in range(2))
    times = {}
    for label, fn in (("shifted products (version 1)", correlation_by_shifts),
                      ("one operation (version 2)", correlation)):
        times[label] = measure(lambda fn=fn: fn(f1, f2, 8, 2).square().sum().backward(), max(3, repeats // 4),
                               block_s=0.05)
    base = times["shifted products (version 1)"]
    return [[label, f"{t * 1e3:.2f}", f"{base / t:.2f}x"] for label, t in times.items()]


def variant_rows(repeats: int, peak: float) -> list[list[str]]:
    """The profile's flow1 step with the nets in channels-last layout (``model.channels_last``) and
    compiled (``model.compile``: each net compiled, the loss, clipping and optimiser eager, as the job
    runs them)."""
    from demon_lab.core import execution
    from demon_lab.pipeline.settings import JobSettings
    from demon_lab.pipeline.stages.schedule import build_chain
    from demon_lab.pipeline.stages.training import stage_module

    cfg = _compose(DESIGNS["profile"])
    job = JobSettings.of(cfg)
    rows = []
    for label, channels_last, compile_nets in (("channels-last", True, False), ("torch.compile", False, True)):
        try:
            torch.manual_seed(0)
            chain = execution.prepare_nets(build_chain(job), channels_last, compile_nets)
            module = stage_module(job, chain, "flow1")
            mid_stage(module)
            module.train()
            batch = execution.channels_last_batch(training_batch(cfg, chain, job.data.batch_size), channels_last)
            step = training_step(module, batch, job.schedule.grad_clip)
            for _ in range(4 if compile_nets else 2):  # (a compiled net compiles again once its shapes vary)
                step()
            rows.append(["profile", "flow1", label, f"{1 / measure(step, max(3, repeats // 4), block_s=0.125):.2f}"])
        except Exception as e:  # (a compiler missing on the machine: the row says so)
            rows.append(["profile", "flow1", label, f"failed: {type(e).__name__}"])
    return rows


def matmul_flops(repeats: int) -> float:
    """This machine's float32 matmul rate (2048x2048), FLOP/s."""
    a, b = torch.rand(2048, 2048), torch.rand(2048, 2048)
    return 2 * 2048**3 / measure(lambda: a @ b, max(3, repeats // 2))


def logging_share(steps: int = 300) -> float:
    """DeMoN's flow1 stage trained through Lightning with a job's stage logger (Lightning's MLFlowLogger
    on an MLflow run, metrics every 10 steps) for ``steps`` steps: the logger's share of the fit's time."""
    import lightning as L
    from lightning.pytorch.loggers import MLFlowLogger

    from demon_lab.pipeline.settings import JobSettings
    from demon_lab.pipeline.stages.schedule import build_chain
    from demon_lab.pipeline.stages.training import stage_module
    from demon_lab.pipeline.tracking import Tracker, process_tracking_uri

    class TimedLogger(MLFlowLogger):
        seconds = 0.0

        def log_metrics(self, metrics, step=None):
            start = time.perf_counter()
            super().log_metrics(metrics, step)
            TimedLogger.seconds += time.perf_counter() - start

    cfg = _compose(DESIGNS["DeMoN's design"])
    job = JobSettings.of(cfg)
    chain = build_chain(job)
    batch = training_batch(cfg, chain, 8)

    class Repeat(torch.utils.data.Dataset):
        def __len__(self):
            return steps

        def __getitem__(self, i):
            return {k: v[i % v.shape[0]] for k, v in batch.items()}

    with tempfile.TemporaryDirectory() as tmp, process_tracking_uri():  # the logger sets it process-wide
        tracker = Tracker(f"sqlite:///{tmp}/mlflow.db", "bench", f"{tmp}/artifacts")
        run_id = tracker.start("bench", {})
        logger = TimedLogger(tracking_uri=tracker.uri, run_id=run_id)
        module = stage_module(job, chain, "flow1")
        trainer = L.Trainer(max_steps=steps, logger=logger, log_every_n_steps=10, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
        start = time.perf_counter()
        trainer.fit(module, torch.utils.data.DataLoader(Repeat(), batch_size=8))
        return TimedLogger.seconds / (time.perf_counter() - start)


def bench_train(repeats: int) -> str:
    import warnings

    from demon_lab.nets.chain import DeMoN

    warnings.filterwarnings("ignore")
    peak = matmul_flops(repeats)
    start = time.perf_counter()
    bare = {design: bare_steps(overrides, repeats, peak) for design, overrides in DESIGNS.items()}
    loop = {design: loop_rates(overrides) for design, overrides in DESIGNS.items()}
    variants = variant_rows(repeats, peak)
    correlation = correlation_rows(repeats)
    share = logging_share()
    chain = DeMoN("v1", 1.0, (192, 256)).eval()
    images = torch.rand(1, 3, 192, 256) - 0.5
    K = torch.tensor([[0.89115971, 1.18821287, 0.5, 0.5]])
    with torch.no_grad():
        infer = measure(lambda: chain(images, images, K, iterations=3), max(3, repeats // 4), block_s=0.25)
    steps = " ".join(f"scale.steps.{k}={v}" for k, v in LOOP_STEPS.items())
    lines = [
        "## train",
        "",
        f"`python -m demon_lab.bench train` — {dt.date.today().isoformat()}, {machine_line()}; "
        f"{(time.perf_counter() - start) / 60:.0f} min.",
        "Each stage of each design at the `cpu` scale (128x96, width 0.25, batch 8; the iterative stage 8 new + "
        "8 queued). **The bare step**: the stage's module as the job builds it, on 8 of the design's training "
        "pairs (with their classical priors where the design has them, as the job's draws carry them), "
        "forward, backward, the gradients clipped and Adam with its learning-rate schedule, its ramped terms "
        "as past their ramps, no memo; its FLOP/s "
        "(torch.utils.flop_counter) against this machine's float32 matmul (2048x2048) in the same run, "
        f"{peak / 1e9:.0f} GFLOP/s, and its largest self times (torch.profiler, share of the step's CPU time). "
        f"**The job's loop**: `python -m demon_lab DESIGN {steps} iterations=0 trainer.profile=true` in a "
        "temporary stage cache and store (the scene cache as the user has it), each stage's loop once running "
        "(`stage/NAME/loop_steps_per_second`: from the end of its first tenth of batches to its last, the "
        "loading, held-apart scoring, checkpoints and logging between them included), the whole stage "
        "(`steps_per_second`: its set-up, first batches and end too), and the largest parts of its loop "
        "beside its batches (Lightning's "
        "SimpleProfiler, share of the stage's time: the loader, each callback, and the rest outside both). "
        "Designs: " + "; ".join(f"{d}: `{' '.join(o) or '(the default)'}`" for d, o in DESIGNS.items()) + ".",
        "",
        design_table(bare, loop, peak),
        "",
        "The correlation front (the learned design's flow1: batch 8, 16 channels at 32x24, [8, 2]), forward "
        "and backward (`demon_lab.nets.blocks.correlation`, `CORRELATION_VERSION`):",
        "",
        markdown_table(["operation", "ms", "speed-up"], correlation, "lrr"),
        "",
        "The profile's flow1 bare step in other layouts and compiled:",
        "",
        markdown_table(["design", "stage", "variant", "steps/s"], variants, "lllr"),
        "",
        f"Inference of the full chain (v1, full width, 256x192, bootstrap + 3 iterations + refinement, batch 1): "
        f"{1 / infer:.2f} pairs/s.",
        "",
        f"Share of a stage's wall time spent in MLflow logging (DeMoN's flow1, 300 steps through Lightning, "
        f"metrics every 10 steps to a fresh SQLite store): {share:.2%}.",
        "",
    ]
    return "\n".join(lines)
