"""One job of ``python -m demon_lab``: its MLflow run, the stages the cache lacks, evaluation, results.

:func:`run` is the job (called once per combination of a ``-m`` sweep); :func:`main_task` is the
Hydra task around it, which turns known errors into one line and keeps a failing job from stopping
its sweep. The tracking contract (what a run holds) is in docs/running.md, "Tracking".

A job of a sweep is a child of the sweep's parent run: the sweep's Hydra callback hands the parent
run id to the job in :data:`PARENT_RUN`, in the job's own process, just before the task runs
(:meth:`demon_lab.app.callbacks.MultirunTracking.on_job_start`).
"""

from __future__ import annotations

import json
import logging
import sys
import tempfile
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from demon_lab.core.metrics import UNITS_NOTE
from demon_lab.pipeline.config import ConfigError
from demon_lab.pipeline.methods import method
from demon_lab.pipeline.settings import JobSettings, TrackingSettings
from demon_lab.pipeline.validate import validate

log = logging.getLogger(__name__)

PARENT_RUN: ContextVar[str | None] = ContextVar("demon_lab_parent_run", default=None)
"""The sweep's parent run id for the job about to run, or None (a single run). Set in the job's
process by the sweep's callback (``MultirunTracking.on_job_start``, which joblib and SLURM launchers
carry into that process pickled), cleared by its ``on_job_end``."""

SWEEP_SERVER: ContextVar[str | None] = ContextVar("demon_lab_sweep_server", default=None)
"""The address of the MLflow server that the sweep's process started for its jobs
(``tracking=local_server``), or None. Handed over like :data:`PARENT_RUN`: a job whose store is that
server logs through it instead of starting its own."""


def job_tags(job: JobSettings, key: str) -> dict[str, str]:
    """The job run's tags: its identity, the study row it belongs to, the code, versions and device."""
    import platform

    import torch

    from demon_lab.pipeline.tracking import TAG, git_state, version_tags

    return {
        f"{TAG}run_key": key, f"{TAG}experiment": job.experiment, f"{TAG}row": str(job.row),
        f"{TAG}seed": str(job.seed), f"{TAG}scale": str(job.scale.name), f"{TAG}data": str(job.config["data"]["name"]),
        f"{TAG}iterations": str(job.iterations), f"{TAG}oracle": str(job.oracle), f"{TAG}method": str(job.method),
        **{f"{TAG}{k}": v for k, v in git_state().items()}, **version_tags(),
        f"{TAG}torch": torch.__version__, f"{TAG}cuda": str(torch.version.cuda),
        f"{TAG}device": "cuda" if torch.cuda.is_available() else "cpu", f"{TAG}host_python": platform.python_version(),
        f"{TAG}cpu_threads": str(torch.get_num_threads()),
    }


def run(cfg: DictConfig) -> dict[str, Any]:
    """One job. Returns {'status': 'finished'|'skipped'|'worker', 'run_id': ..., 'summary': ...}."""
    from demon_lab.pipeline.config import drop_missing_sources

    for note in drop_missing_sources(cfg, cfg.train):
        log.info("%s", note)
    job = validate(cfg)
    if job.threads is not None:
        from demon_lab.core.execution import set_threads

        set_threads(job.threads)
    if method(job.method).runs_chain:
        from demon_lab.core.execution import global_rank
        from demon_lab.pipeline.stages.training import prepare_chain

        if job.trainer.world > 1 and global_rank(job) != 0:  # a DDP worker: trains; rank 0 tracks and evaluates
            prepare_chain(job, None, progress=False)
            return {"status": "worker"}
    from demon_lab.pipeline.identity import run_key
    from demon_lab.pipeline.tracking import Tracker, flatten

    key = run_key(job)
    tracker = Tracker(job.tracking.uri, job.experiment, job.tracking.artifact_dir,
                      local_server=job.tracking.server is not None)
    if not job.force:
        existing = tracker.find_finished(key)
        if existing:
            log.info("skipped: run key %s already has the FINISHED run %s (experiment %r); pass force=true to run "
                     "it again", key, existing, job.experiment)
            _print_study_rows(cfg)
            return {"status": "skipped", "run_id": existing, "run_key": key}
    record = _run_id_file()
    persisted = record.read_text().strip() if record is not None and record.is_file() else None
    run_id = next((r for r in (persisted, tracker.find_interrupted(key)) if r and tracker.resumable(r, key)), None)
    if run_id is not None:
        tracker.resume(run_id)
        tracker.set_tags(run_id, job_tags(job, key))  # the code that finishes it (same run key)
        log.info("resuming the interrupted run %s (run key %s)", run_id, key)
    else:
        run_id = tracker.start(f"{job.experiment}-{key[:8]}", job_tags(job, key), parent_id=_parent_run())
    if record is not None:
        record.parent.mkdir(parents=True, exist_ok=True)
        record.write_text(run_id + "\n")
    try:
        tracker.log_params(run_id, flatten(job.config))
        tracker.log_text(run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        result = _train_and_evaluate(job, tracker, run_id)
        tracker.finish(run_id, "FINISHED")
        _print_study_rows(cfg)
        return {"status": "finished", "run_id": run_id, "run_key": key, **result}
    except BaseException as e:
        tracker.fail(run_id, e)
        raise


def _train_and_evaluate(job: JobSettings, tracker, run_id: str) -> dict[str, Any]:
    """The job's work in its run ``run_id``: the chain's stages (:func:`_train`), the test sets
    scored, and the results logged and printed (:func:`_record`)."""
    from demon_lab.pipeline.evaluate import evaluate_test_sets

    chain, stages, figures = _train(job, tracker, run_id) if method(job.method).runs_chain else (None, [], {})
    refined = _has_refinement(job, [s.name for s in stages])
    results = evaluate_test_sets(job, chain, refined)
    summary = {r.name: r.summary for r in results}
    _record(job, tracker, run_id, results, refined)
    return {"summary": summary, "figures": figures}


def _train(job: JobSettings, tracker, run_id: str) -> tuple[Any, list, dict[str, dict[str, float]]]:
    """The chain with its scheduled stages cached or trained; a stage that trains gets a child run of
    ``run_id`` (a killed one resumes its own) with Lightning's MLFlowLogger attached for its loss
    curves. The stages' keys and figures go to the job's run."""
    from demon_lab.pipeline.stages.training import prepare_chain
    from demon_lab.pipeline.tracking import TAG, process_tracking_uri

    stage_runs: list[str] = []

    def on_stage(stage, status):
        log.info("stage %s: %s", stage.name, f"cached {stage.path}" if status == "cached" else "training")
        if status == "cached":
            return None
        from lightning.pytorch.loggers import MLFlowLogger

        child = tracker.find_interrupted(stage.key, parent_id=run_id, tag="stage_key")
        if child is None:
            child = tracker.start(f"stage-{stage.name}", {f"{TAG}stage": stage.name, f"{TAG}stage_key": stage.key,
                                                         f"{TAG}kind": "stage"}, parent_id=run_id)
        stage_runs.append(child)
        return MLFlowLogger(tracking_uri=tracker.uri, run_id=child)

    try:
        with process_tracking_uri():  # MLFlowLogger sets it process-wide: keep it this job's business
            chain, stages, figures = prepare_chain(job, on_stage, progress=sys.stderr.isatty())
    except BaseException as e:
        for child in stage_runs:  # the stage that raised (its logger may have ended it FAILED), not the
            if tracker.client.get_run(child).info.status != "FINISHED":  # stages that finished before it
                tracker.fail(child, e)
        raise
    for child in stage_runs:
        tracker.finish(child)  # MLFlowLogger ends it FINISHED already; a no-op then
    stage_keys = {s.name: {"key": s.key, "path": str(s.path)} for s in stages}
    tracker.log_text(run_id, json.dumps(stage_keys, indent=2) + "\n", "stage_keys.json")
    tracker.log_metrics(run_id, {f"stage/{name}/{k}": v for name, fig in figures.items() for k, v in fig.items()})
    return chain, stages, figures


def _has_refinement(job: JobSettings, stages: list[str]) -> bool:
    """Whether the chain's refinement net is trained (its rows are scored): scheduled, or, for an
    untrained chain (``train=false``), in ``model.weights`` where the file is given."""
    refined = method(job.method).scores_passes and (not job.train or "refine" in stages)
    if refined and not job.train and job.model.weights:
        from demon_lab.pipeline.weights import read_nets

        refined = "refine_net" in read_nets(job.model.weights, mmap=True)
    return refined


def _record(job: JobSettings, tracker, run_id: str, results: list, refined: bool) -> None:
    """The test sets' results in the job's run (metrics, per-sample rows, pixel-error histograms,
    pictures, the table) and the table printed."""
    from demon_lab.reporting.tables import results_table
    from demon_lab.reporting.visualize import save_visuals

    summary = {r.name: r.summary for r in results}
    tracker.log_metrics(run_id, {f"test/{name}/{k}": v for name, values in summary.items() for k, v in values.items()})
    scored = method(job.method)
    priors = any(f"priors/{k}" in values for values in summary.values() for k in ("epe", "tran_deg"))
    passes = scored.passes(job.iterations, refined, priors)  # (the profile's priors alone first)
    if scored.scores_passes:
        what = f"{job.iterations} iterations{', oracle ' + str(job.oracle) if job.oracle else ''}"
        pictured = "refined depth" if refined else f"pass {job.iterations}"
    else:
        what, pictured = f"method {job.method}", job.method
    table = results_table(summary, passes)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for r in results:
            save_visuals(root, r.name, r.kept, job.eval.visualize, job.eval.point_clouds, pictured)
        (root / "per_sample_metrics.csv").write_text(_csv([{"dataset": r.name, **row} for r in results
                                                            for row in r.rows]))
        (root / "pixel_errors.json").write_text(json.dumps({r.name: r.histogram for r in results}) + "\n")
        for name in ("pixel_errors.json", "per_sample_metrics.csv", "images", "point_clouds"):
            if (root / name).exists():
                tracker.log_artifact(run_id, root / name)
    tracker.log_text(run_id, table + "\n", "results.txt")
    # the job's result: printed (not logged), so it shows whatever the logging configuration
    print(f"[demon_lab] results (scale {job.scale.name}, seed {job.seed}, {what}; {UNITS_NOTE}):\n{table}\n",
          flush=True)


def _csv(rows: list[dict[str, Any]]) -> str:
    """Rows with the union of their keys as columns, in first-seen order, written by pandas: each value
    as given (a float to full precision), a missing or NaN value empty."""
    import pandas as pd

    return pd.DataFrame(rows, dtype=object).to_csv(index=False, na_rep="", lineterminator="\n")


def _hydra_output_dir(multirun_only: bool = False) -> Path | None:
    """The job's Hydra output folder (deterministic: named after its overrides), or None outside
    Hydra (tests call :func:`run` directly) or, with ``multirun_only``, in a single run."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hydra_cfg = HydraConfig.get()
    except ValueError:
        return None
    if multirun_only and hydra_cfg.mode != RunMode.MULTIRUN:
        return None
    return Path(hydra_cfg.runtime.output_dir)


def _run_id_file() -> Path | None:
    """``run_id`` in the job's output folder: a re-issued job finds its run."""
    folder = _hydra_output_dir()
    return folder / "run_id" if folder is not None else None


def _print_study_rows(cfg: DictConfig) -> None:
    """A single job (not a sweep's: the sweep prints its own table) of an experiment that a study
    reports: the study's rows of that experiment from the store, this job's among them
    (:func:`demon_lab.reporting.report.study_rows`). A table that cannot be built is a warning."""
    if _parent_run() is not None:
        return
    from demon_lab.reporting import provenance, report

    study = None
    try:
        if report.study_of(str(cfg.experiment)) is None:  # no study reports it (the default experiment)
            return
        study = report.study_of(str(cfg.experiment), design=provenance.config_design(cfg))
        text = report.study_rows(study, cfg.tracking.uri, str(cfg.experiment))
    except Exception as e:  # the job's own result is recorded and printed either way
        log.warning("study %s: no table of its rows (%s: %s)", study, type(e).__name__, e)
        return
    if text:
        print(f"[demon_lab] {text}\n", flush=True)


def _parent_run() -> str | None:
    """The multirun's parent run id (created once per sweep by the Hydra callback), if any."""
    return PARENT_RUN.get()


def known_errors() -> tuple[type[BaseException], ...]:
    """Errors that are the user's to fix (a config, data, store or checkpoint problem, a diverged
    stage): one line, no traceback. A diverged stage is the training module's error, which a job refused
    before it trained has not imported (nor Lightning with it): it is looked up only where it is loaded."""
    from demon_lab.data.sample import DataError
    from demon_lab.pipeline.stages.cache import CheckpointError
    from demon_lab.pipeline.tracking import TrackingError

    training = sys.modules.get("demon_lab.pipeline.stages.training")
    diverged = (training.TrainingDiverged,) if training is not None else ()
    return ConfigError, DataError, TrackingError, CheckpointError, *diverged


def main_task(cfg: DictConfig) -> dict[str, Any] | None:
    """Hydra task. A single run exits non-zero with one line on a configuration, data,
    tracking-store or checkpoint error or diverged training, and with the traceback on anything
    else. In a multirun a failing job never stops the sweep: its run is FAILED with the error
    recorded, it prints one line, leaves ``error.txt`` (with the traceback) in its output folder and
    returns status ``FAILED`` rather than raising, since Hydra's basic sweeper stops at the first job
    that raises; the sweep goes on, and its end lists the failures and exits non-zero
    (:mod:`demon_lab.app.sweep`, :class:`demon_lab.app.callbacks.MultirunTracking`). Returns the job's
    status and run id (what the sweep's table of its jobs reads)."""
    import traceback

    job_dir = _hydra_output_dir(multirun_only=True)
    marker = job_dir / "error.txt" if job_dir is not None else None
    if marker is not None:
        marker.unlink(missing_ok=True)
    server = None
    try:
        from demon_lab.core.execution import global_rank

        settings = TrackingSettings.of(cfg.tracking, "tracking")
        if settings.server is not None and global_rank(cfg) == 0:  # DDP workers only train
            from demon_lab.pipeline.tracking import LocalServer

            server = LocalServer(**settings.server.arguments())
            if server.uri == SWEEP_SERVER.get():
                server = None  # the sweep's server is up and stops with the sweep
            else:
                server.start()
        result = run(cfg)
    except Exception as e:
        known = isinstance(e, known_errors())
        if marker is None:
            if not known:
                raise
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text("".join(traceback.format_exception(e)))
        line = str(e).strip().splitlines()[0] if str(e).strip() else ""
        what = line if known else f"{type(e).__name__}: {line}"
        print(f"error: {what} (traceback in {marker})", file=sys.stderr, flush=True)
        return {"status": "FAILED", "run_id": None}
    finally:
        if server is not None:
            server.stop()
    return {"status": result.get("status"), "run_id": result.get("run_id")}
