"""Train the schedule's stages that the stage cache lacks, in order, and load them all.

Used by the job (:mod:`demon_lab.app.job`), which tracks every trained stage as a child run of its
MLflow run with the stage's loss curves. Also where a job's processes are counted: with
``trainer.devices x trainer.num_nodes > 1`` each stage trains with DDP, the global batch split
over the processes.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L

from demon_lab.core.execution import (
    global_rank,
    normalize_precision,
    plain_state,
    resolve_accelerator,
)
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.kinds import FlowStage
from demon_lab.pipeline.settings import JobSettings
from demon_lab.pipeline.stages.base import StageModule
from demon_lab.pipeline.stages.cache import StageDir, atomic_checkpoint_io, load_checkpoint
from demon_lab.pipeline.stages.priors import PairPriors, PriorTable, warm_priors
from demon_lab.pipeline.stages.schedule import build_chain, load_stage, stage_dirs

log = logging.getLogger(__name__)


class LoopClock(L.Callback):
    """The time at the end of each batch a stage trains: the rate of its loop once running
    (:func:`loop_rate`), without what a stage does once (the trainer's set-up, the first batches, the
    nets kept and saved at the end)."""

    def __init__(self):
        self.ends: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.ends.append(time.perf_counter())


def loop_rate(ends: Sequence[float], skip: float = 0.1) -> float | None:
    """Steps per second between the end of the batch after the first ``skip`` of ``ends`` and the last:
    every batch of that stretch with what the loop does beside it (loading, held-apart scoring,
    checkpoints, logging). None for fewer than 10 batches."""
    if len(ends) < 10:
        return None
    first = max(1, int(skip * len(ends)))
    return (len(ends) - first) / max(ends[-1] - ends[first - 1], 1e-9)


class TrainingDiverged(FloatingPointError):
    """A stage's loss became NaN or infinite: the message names the stage, the step and every
    loss term (one line)."""


def build_datamodule(job: JobSettings, batch_size: int, samples: int, skip: int = 0,
                     easy_first=None, pin_memory: bool = False, layers_first: float | None = None,
                     fresh_scenes: float = 0.0, priors: PriorTable | None = None):
    """Training data for ``samples`` draws in batches of ``batch_size`` (global: under DDP each
    process loads its share of every batch); ``easy_first``, ``layers_first``, ``fresh_scenes``: a
    stage's curriculum (MixtureSampler: the easiest samples first; fresh 2-D layers for the first part
    of the stage; new synthetic scenes at a steady rate per draw);
    ``pin_memory``: batches in page-locked memory (faster copies to a CUDA device); ``priors``: each
    pair's classical priors, computed once per pair (:mod:`demon_lab.pipeline.stages.priors`). ``job``:
    the job's settings."""
    from demon_lab.data.datamodule import DemonDataModule, Draws
    from demon_lab.pipeline.config import instantiate

    train = [{"weight": e.weight, "dataset": instantiate(e.dataset)} for e in job.data.train]
    world = job.trainer.world
    draws = Draws(batch_size=batch_size // world, samples_per_epoch=samples, seed=job.seed, skip=skip,
                  rank=global_rank(job), world=world, easy_first=None if easy_first is None else tuple(easy_first),
                  layers_first=layers_first, layers_size=job.data.size, fresh_scenes=float(fresh_scenes))
    return DemonDataModule(train, draws, num_workers=job.data.num_workers, pin_memory=pin_memory, fields=priors)


def stage_module(job: JobSettings, chain: DeMoN, name: str) -> StageModule:
    """The LightningModule that trains stage ``name`` of ``job``'s schedule on ``chain``."""
    return StageModule(chain, job.stages[name], weights=dict(job.loss), lr_schedule=job.schedule.lr_schedule,
                       weight_decay=job.schedule.weight_decay, channels_last=job.model.channels_last,
                       reuse_frozen=job.trainer.reuse_frozen)


def train_stage(job: JobSettings, chain: DeMoN, stage: StageDir, logger: L.pytorch.loggers.Logger | None,
                progress: bool = True, priors: PriorTable | None = None) -> dict[str, float]:
    """Train one stage into ``stage`` (resuming from its last checkpoint), its pairs carrying their
    classical ``priors`` where given; returns figures. ``job``: the job's settings."""
    spec = job.stages[stage.name]
    if spec.steps == 0:  # trains nothing: the nets as they are (from model.weights or an earlier stage)
        if global_rank(job) == 0:
            stage.save({net: plain_state(getattr(chain, net)) for net in spec.trained_nets()})
        log.info("stage %s: 0 steps: keeps %s as they are (from model.weights or an earlier stage)", stage.name,
                 ", ".join(spec.trained_nets()))
        return _logged(job, logger, {"seconds": 0.0, "steps_per_second": 0.0, "resumed_from_step": 0}, 0)
    module = stage_module(job, chain, stage.name)
    batch = spec.batch_size or job.data.batch_size
    resume = stage.last_checkpoint if stage.last_checkpoint.is_file() else None
    if resume is None and isinstance(spec, FlowStage) and spec.restarts is not None:
        resume = screen_restarts(job, chain, stage, module, logger, priors)
    start_step = _checkpoint_step(resume) if resume is not None else 0
    # A resumed stage continues the sample sequence where the checkpoint left it: same batches,
    # same result as an uninterrupted run (on the CPU).
    # With DDP the global batch is the configured one, each process taking its slice of every batch
    # (demon_lab's sampler deals them, not Lightning's, which would reshuffle the sequence).
    datamodule = build_datamodule(job, batch, spec.steps * batch, skip=start_step * batch,
                                  **spec.curriculum(), priors=priors,
                                  pin_memory=resolve_accelerator(job.trainer.accelerator) == "cuda")
    callbacks, keep, clock = _stage_callbacks(job, spec, stage, logger)
    profiler = L.pytorch.profilers.SimpleProfiler() if job.trainer.profile else None
    trainer = _trainer(job, spec.steps, logger=logger if logger is not None else False, callbacks=callbacks,
                       enable_progress_bar=progress, profiler=profiler)
    if resume is not None:
        log.info("resuming stage %s from step %d (%s)", stage.name, start_step, resume)
    loader = datamodule.train_dataloader()  # (an easy_first curriculum orders its sources here: not timed)
    rendered, render_seconds = _render_fresh_scenes(datamodule)
    start = time.perf_counter()
    try:
        trainer.fit(module, train_dataloaders=loader, ckpt_path=resume)
    except FloatingPointError as e:
        raise TrainingDiverged(f"stage {stage.name}: {e}") from e
    seconds = time.perf_counter() - start
    kept = keep.restore(chain) if keep is not None else {}
    if kept:
        log.info("stage %s: keeps its nets of step %d of %d (held-apart %s %.4f; scoring took %.0f s)", stage.name,
                 kept.get("keep_best_step", spec.steps), spec.steps, keep.metric,
                 kept.get(f"keep_best_{keep.metric}", float("nan")), kept["keep_best_seconds"])
    if global_rank(job) == 0:
        stage.save({net: plain_state(getattr(chain, net)) for net in spec.trained_nets()})
    figures = {"seconds": seconds, "steps_per_second": (spec.steps - start_step) / max(seconds, 1e-9),
               "resumed_from_step": start_step, **{f"final/{k}": v for k, v in module.last_terms.items()}, **kept,
               **_loop_figures(clock, profiler, module, seconds),
               **({"fresh_scenes_rendered": rendered, "fresh_scenes_seconds": render_seconds} if rendered else {})}
    # The trainer and the module refer to each other: collect them (and the loader's memo of frozen
    # outputs) now rather than let every stage of a job keep its own until the next GC pass.
    del trainer, module, datamodule
    gc.collect()
    return _logged(job, logger, figures, spec.steps)


def _stage_callbacks(job: JobSettings, spec, stage: StageDir, logger) -> tuple[list, Any, LoopClock]:
    """A stage's callbacks: its checkpoints, its held-apart scoring (where it logs or keeps its best nets;
    rank 0 only) and ``keep_best`` (None without it), and the clock of its loop."""
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(
        dirpath=stage.path, filename="step{step}", save_last=True, save_top_k=0,
        every_n_train_steps=max(1, job.scale.checkpoint_every), auto_insert_metric_name=False)
    callbacks: list = [checkpoint]
    keep = None
    if (logger is not None or spec.keep_best) and job.data.val and global_rank(job) == 0:
        from demon_lab.pipeline.config import instantiate
        from demon_lab.pipeline.stages.validation import KeepBest, StageValidation

        scorer = StageValidation(spec, [instantiate(e) for e in job.data.val],
                                 job.tracking.val_every_n_steps if logger is not None else 0)
        callbacks.append(scorer)
        if spec.keep_best:
            keep = KeepBest(scorer, spec.best_metric, spec.keep_best, stage.path / "best.pt", spec.trained_nets())
            callbacks.append(keep)
    clock = LoopClock()
    return [*callbacks, clock], keep, clock


def _loop_figures(clock: LoopClock, profiler, module, seconds: float) -> dict[str, float]:
    """What a stage's loop logs besides its time: its rate once running, its largest parts
    (``trainer.profile``) and the hit rate of the frozen nets' memo (``trainer.reuse_frozen``)."""
    figures = {}
    if (rate := loop_rate(clock.ends)) is not None:
        figures["loop_steps_per_second"] = rate
    if profiler is not None:
        figures.update(loop_parts(profiler.recorded_durations, seconds))
    if module.memo is not None and module.memo.hits + module.memo.misses:
        figures["reuse_frozen_hits"] = module.memo.hits / (module.memo.hits + module.memo.misses)
    return figures


def _render_fresh_scenes(datamodule) -> tuple[int, float]:
    """Render the fresh scenes a stage's draws will meet (``fresh_scenes``) into the scene cache before
    it trains, in one process per core, where the loader would render each at its first draw on the
    cores the stage trains on. They are the next scenes of each set's split, the same for every seed
    and row, so a scene is rendered once per cache. Returns the number rendered and the seconds."""
    from demon_lab.data.datasets import keep_in_memory, warm_cache

    start = time.perf_counter()
    fresh = datamodule.fresh_scenes()
    rendered = warm_cache(fresh)
    if rendered:
        log.info("rendered %d fresh scenes into the cache in %.0f s", rendered, time.perf_counter() - start)
    keep_in_memory(fresh)
    return rendered, time.perf_counter() - start


LOOP_PARTS = 8
"""How many parts of a profiled stage's loop it logs (``trainer.profile``): the largest by time."""


def loop_parts(durations: Mapping[str, Sequence[float]], seconds: float) -> dict[str, float]:
    """The largest parts of a stage's loop as Lightning's SimpleProfiler timed them (``durations``: the
    seconds of each call of each action), as figures ``profile/<part>_seconds``, an action's name made a
    metric name (``[Callback]KeepBest.on_train_batch_end`` -> ``callback.KeepBest.on_train_batch_end``);
    and ``profile/outside_seconds``: the stage's time (``seconds``) outside its batches
    (``run_training_batch``: forward, backward, optimiser) and its loader (``train_dataloader_next``)."""
    totals = {name: float(sum(times)) for name, times in durations.items() if times and name != "run_training_epoch"}

    def metric(name: str) -> str:
        name = re.sub(r"^\[(\w+)\]\.?", lambda m: m[1].strip("_").lower() + ".", name)
        return re.sub(r"[^A-Za-z0-9_.-]+", ".", name).strip(".")

    largest = sorted(totals, key=totals.__getitem__, reverse=True)[:LOOP_PARTS]
    figures = {f"profile/{metric(name)}_seconds": totals[name] for name in largest}
    inside = totals.get("run_training_batch", 0.0) + sum(v for n, v in totals.items()
                                                         if n.endswith("train_dataloader_next"))
    figures["profile/outside_seconds"] = max(seconds - inside, 0.0)
    return figures


def _logged(job: JobSettings, logger, figures: dict[str, float], step: int) -> dict[str, float]:
    """``figures``, logged on the stage's own run too (``stage/<name>``), whatever becomes of the job."""
    if logger is not None and global_rank(job) == 0:
        logger.log_metrics({f"stage/{k}": v for k, v in figures.items()}, step=step)
    return figures


def _trainer(job: JobSettings, steps: int, **kwargs) -> L.Trainer:
    """A stage's Trainer: its devices, precision and gradient clipping, as DeMoN's optimiser does."""
    return L.Trainer(
        max_steps=steps, accelerator=job.trainer.accelerator, devices=job.trainer.devices,
        num_nodes=job.trainer.num_nodes, strategy="ddp" if job.trainer.world > 1 else "auto",
        precision=normalize_precision(job.precision),
        log_every_n_steps=job.tracking.log_every_n_steps, gradient_clip_val=job.schedule.grad_clip,
        gradient_clip_algorithm="value", enable_model_summary=False,
        num_sanity_val_steps=0, limit_val_batches=0, deterministic="warn", benchmark=False,
        use_distributed_sampler=False, plugins=[atomic_checkpoint_io()], **kwargs)


def screen_restarts(job: JobSettings, chain: DeMoN, stage: StageDir, module: L.LightningModule,
                    logger: L.pytorch.loggers.Logger | None, priors: PriorTable | None = None) -> Path:
    """The stage option ``restarts: [k, steps]`` (PWC-Net's practice of restarting a flow net stuck at
    a poor start): train ``k`` starts of the stage's net for its first ``steps`` steps, each on the
    stage's own first batches and learning rates, score each on the held-apart sets (``data.val``,
    the mean flow EPE of the pass the stage trains), and return the checkpoint of the best, from
    which the stage continues to its end. Start 0 is the chain's own initialisation, start ``i``
    the net drawn anew from seed ``(seed, i)``. Each start's score is logged on the stage's run
    (``restart/val_epe`` at step ``i``, ``restart/chosen``)."""
    import torch

    from demon_lab.nets.blocks import initialise
    from demon_lab.pipeline.config import instantiate
    from demon_lab.pipeline.stages.validation import StageValidation

    spec = job.stages[stage.name]
    starts, steps = spec.restarts
    batch = spec.batch_size or job.data.batch_size
    (net_name,) = spec.trained_nets()
    net = getattr(chain, net_name)
    scorer = StageValidation(spec, [instantiate(e) for e in job.data.val], 0, iterations=0)
    scores = []
    for i in range(starts):
        if i > 0:  # (start 0: the net as the chain holds it)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(job.seed * 1_000_003 + i)
                net.apply(initialise)
        data = build_datamodule(job, batch, spec.steps * batch, **spec.curriculum(), priors=priors)
        # saved at its last step inside the epoch, as the stage's own checkpoints: the stage resumes from it
        saved = L.pytorch.callbacks.ModelCheckpoint(dirpath=stage.path, filename=f"restart{i}", save_top_k=-1,
                                                    every_n_train_steps=steps, enable_version_counter=False)
        trainer = _trainer(job, steps, logger=False, callbacks=[saved], enable_progress_bar=False)
        trainer.fit(module, train_dataloaders=data.train_dataloader())
        chain.eval()
        with torch.no_grad():
            epe = [scorer._scores(chain, scorer.batches(chain, which), module.channels_last)["epe"]
                   for which in range(len(scorer.datasets))]
        scores.append(sum(epe) / len(epe))
        log.info("stage %s: start %d of %d: held-apart EPE %.4f after %d steps", stage.name, i + 1, starts,
                 scores[-1], steps)
        if logger is not None:
            logger.log_metrics({"restart/val_epe": scores[-1]}, step=i)
    best = min(range(starts), key=scores.__getitem__)
    for i in range(starts):
        if i != best:
            (stage.path / f"restart{i}.ckpt").unlink()
    if logger is not None:
        logger.log_metrics({"restart/chosen": float(best)}, step=starts)
    log.info("stage %s: continues from start %d (held-apart EPE %.4f)", stage.name, best + 1, scores[best])
    return stage.path / f"restart{best}.ckpt"


def _checkpoint_step(path) -> int:
    return int(load_checkpoint(path).get("global_step", 0))


def _quiet_lightning() -> None:
    import logging
    import warnings

    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.pytorch.accelerators.cuda"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message=".*LeafSpec.*")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    # The data stream resumes itself: build_datamodule(skip=...) starts the sampler at the
    # checkpoint's step, so Lightning's "dataloader is not resumable" warning does not apply.
    warnings.filterwarnings("ignore", message=".*dataloader is not resumable.*")


def prepare_chain(job: JobSettings, on_stage: Callable[[StageDir, str], L.pytorch.loggers.Logger | None]
                  | None = None, progress: bool = True) -> tuple[DeMoN, list[StageDir], dict[str, dict]]:
    """Build the chain, train the stages the cache lacks and load every stage in order.

    ``on_stage(stage, status)`` is called with status 'cached' or 'train' and may return a logger
    for the stage's training curves. Returns the chain, the stage entries and per-stage figures.
    """
    _quiet_lightning()
    L.seed_everything(job.seed, workers=True, verbose=False)
    chain = build_chain(job)
    figures: dict[str, dict] = {}
    if job.model.weights:
        log.info("model.weights: %s loaded into the chain%s", job.model.weights,
                 "" if not job.train else " (the stages train from it)")
    if not job.train:
        if not job.model.weights:
            log.info("train=false: evaluating the untrained chain")
        return chain.eval(), [], figures
    table = None
    if not all(stage.done() for stage in stage_dirs(job)):
        from demon_lab.data.datasets import keep_in_memory, warm_cache
        from demon_lab.pipeline.config import instantiate

        start = time.perf_counter()
        train = [instantiate(e.dataset) for e in job.data.train]
        rendered = warm_cache(train)
        if rendered:
            log.info("rendered %d synthetic training scenes into the cache in %.0f s", rendered,
                     time.perf_counter() - start)
        priors = PairPriors.of(chain)
        if priors is not None:
            start = time.perf_counter()
            table, computed = warm_priors(train, priors)
            if computed:
                log.info("computed the classical priors of %d training scenes' pairs into the cache in %.0f s",
                         computed, time.perf_counter() - start)
        keep_in_memory(train)  # every stage, and the loader workers it forks, reads the scenes from memory
    for stage in stage_dirs(job):
        # Under DDP only rank 0 takes the lock (the other ranks join its training collectively).
        with stage.lock() if global_rank(job) == 0 else contextlib.nullcontext():
            if stage.done():
                if on_stage:
                    on_stage(stage, "cached")
                load_stage(chain, stage)
                figures[stage.name] = {"cached": 1.0}
                continue
            logger = on_stage(stage, "train") if on_stage else None
            log.info("training stage %s (%s steps) -> %s", stage.name, job.stages[stage.name].steps, stage.path)
            figures[stage.name] = train_stage(job, chain, stage, logger, progress, table)
    from demon_lab.data.datasets import MEMORY

    MEMORY.clear()  # the training scenes: the evaluation reads other sets
    chain.eval()
    return chain, stage_dirs(job), figures
