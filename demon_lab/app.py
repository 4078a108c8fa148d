"""The main job: validate, track, train what the stage cache lacks, evaluate, report.

``run(cfg)`` is what ``python -m demon_lab`` executes for each (multirun) job.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from demon_lab.config import ConfigError
from demon_lab.validate import validate

TABLE_COLUMNS = (("l1_inv", "L1-inv"), ("sc_inv", "sc-inv"), ("l1_rel", "L1-rel"), ("delta_1.25", "d<1.25"),
                 ("rot_deg", "rot"), ("tran_deg", "tran"), ("epe", "EPE"))


def job_tags(cfg: DictConfig, key: str) -> dict[str, str]:
    import platform

    import torch

    from demon_lab.tracking import TAG, git_state, version_tags

    return {
        f"{TAG}run_key": key, f"{TAG}experiment": cfg.experiment, f"{TAG}row": str(cfg.row),
        f"{TAG}seed": str(cfg.seed), f"{TAG}scale": str(cfg.scale.name), f"{TAG}data": str(cfg.data.name),
        f"{TAG}iterations": str(cfg.iterations), f"{TAG}oracle": str(cfg.oracle), f"{TAG}method": str(cfg.method),
        **{f"{TAG}{k}": v for k, v in git_state().items()}, **version_tags(),
        f"{TAG}torch": torch.__version__, f"{TAG}cuda": str(torch.version.cuda),
        f"{TAG}device": "cuda" if torch.cuda.is_available() else "cpu", f"{TAG}host_python": platform.python_version(),
        f"{TAG}cpu_threads": str(torch.get_num_threads()),
    }


def format_table(summary: dict[str, dict[str, float]], iterations: int, refined: bool = True,
                 passes: list[str] | None = None) -> str:
    header = ["test set", "pass", *[label for _, label in TABLE_COLUMNS]]
    rows = []
    for name, values in summary.items():
        for it in passes or [*range(iterations + 1), *(["refined"] if refined else [])]:
            prefix = {"refined": "refined/", "baseline": ""}.get(str(it), f"it{it}/")
            cells = []
            for key, _ in TABLE_COLUMNS:
                v = values.get(f"{prefix}{key}", math.nan)
                cells.append("-" if v != v else f"{v:.3f}")
            rows.append([name, str(it), *cells])
    return text_table(header, rows)


def text_table(header: list[str], rows: list[list[str]]) -> str:
    """A terminal table: the first two columns (test set, pass) left-aligned, numbers right."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = lambda r: "  ".join(c.rjust(w) if i > 1 else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths)))  # noqa: E731
    return "\n".join([fmt(header), "  ".join("-" * w for w in widths), *map(fmt, rows)])


def run(cfg: DictConfig) -> dict[str, Any]:
    """One job. Returns {'status': 'finished'|'skipped', 'run_id': ..., 'summary': ...}."""
    validate(cfg)
    if cfg.get("threads") is not None:
        set_threads(int(cfg.threads))
    if cfg.method == "demon":
        from demon_lab.train import global_rank, prepare_chain, world_size

        if world_size(cfg) > 1 and global_rank(cfg) != 0:  # a DDP worker: trains; rank 0 tracks and evaluates
            prepare_chain(cfg, None, progress=False)
            return {"status": "worker"}
    from demon_lab.tracking import Tracker, flatten, run_key

    key = run_key(cfg)
    tracker = Tracker(cfg.tracking.uri, cfg.experiment, cfg.tracking.artifact_dir)
    if not cfg.force:
        existing = tracker.find_finished(key)
        if existing:
            print(f"[demon_lab] skipped: run key {key} already has the FINISHED run {existing} "
                  f"(experiment {cfg.experiment!r}); pass force=true to run it again")
            return {"status": "skipped", "run_id": existing, "run_key": key}
    parent = _parent_run()
    record = _run_id_file()
    persisted = record.read_text().strip() if record is not None and record.is_file() else None
    run_id = next((r for r in (persisted, tracker.find_interrupted(key)) if r and tracker.resumable(r, key)), None)
    if run_id is not None:
        tracker.resume(run_id)
        tracker.set_tags(run_id, job_tags(cfg, key))  # the code that finishes it (same run key)
        print(f"[demon_lab] resuming the interrupted run {run_id} (run key {key})", flush=True)
    else:
        run_id = tracker.start(f"{cfg.experiment}-{key[:8]}", job_tags(cfg, key), parent_id=parent)
    if record is not None:
        record.parent.mkdir(parents=True, exist_ok=True)
        record.write_text(run_id + "\n")
    try:
        resolved = OmegaConf.to_yaml(cfg, resolve=True)
        tracker.log_params(run_id, flatten(OmegaConf.to_container(cfg, resolve=True)))
        tracker.log_text(run_id, resolved, "config.yaml")
        result = _train_and_evaluate(cfg, tracker, run_id)
        tracker.finish(run_id, "FINISHED")
        return {"status": "finished", "run_id": run_id, "run_key": key, **result}
    except BaseException as e:
        tracker.fail(run_id, e)
        raise


def _pause_point(name: str) -> None:
    """A named point where ``DEMON_LAB_PAUSE_AT=name`` holds the job (the robustness tests kill it
    there: in the middle of its MLflow logging)."""
    import os
    import time

    if os.environ.get("DEMON_LAB_PAUSE_AT") == name:
        print(f"[demon_lab] paused at {name}", flush=True)
        time.sleep(3600)


def _run_id_file() -> Path | None:
    """``run_id`` in the job's (deterministic) Hydra output folder: a re-issued job finds its run."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir) / "run_id"
    except ValueError:  # not under Hydra (tests call run() directly)
        return None


def _parent_run() -> str | None:
    """The multirun's parent run id (created once per sweep by the Hydra callback), if any."""
    import os

    from demon_lab.callbacks import PARENT_ENV

    return os.environ.get(PARENT_ENV) or None


def _train_and_evaluate(cfg: DictConfig, tracker, run_id: str) -> dict[str, Any]:
    from demon_lab.baselines import summarize_baseline
    from demon_lab.config import instantiate
    from demon_lab.evaluate import evaluate_dataset, summarize
    from demon_lab.metrics import PixelHistogram
    from demon_lab.tracking import TAG, stage_logger
    from demon_lab.train import prepare_chain

    loggers: list = []

    def on_stage(stage, status):
        print(f"[demon_lab] stage {stage.name}: {'cached ' + str(stage.path) if status == 'cached' else 'training'}",
              flush=True)
        if status == "cached":
            return None
        child = tracker.find_interrupted(stage.key, parent_id=run_id, tag="stage_key")  # a killed stage resumes
        if child is None:
            child = tracker.start(f"stage-{stage.name}", {f"{TAG}stage": stage.name, f"{TAG}stage_key": stage.key,
                                                         f"{TAG}kind": "stage"}, parent_id=run_id)
        logger = stage_logger(tracker, child, int(cfg.tracking.log_every_n_steps))
        loggers.append((child, logger))
        return logger

    needs_chain = cfg.method in ("demon", "base_mat_f")
    try:
        chain, stages, figures = (prepare_chain(cfg, on_stage, progress=sys.stderr.isatty()) if needs_chain
                                  else (None, [], {}))
    except BaseException as e:
        for child, _ in loggers:
            tracker.fail(child, e)
        raise
    for child, logger in loggers:
        logger.flush()
        tracker.finish(child)
    stage_keys = {s.name: {"key": s.key, "path": str(s.path)} for s in stages}
    tracker.log_text(run_id, json.dumps(stage_keys, indent=2) + "\n", "stage_keys.json")
    train_metrics = {}
    for name, fig in figures.items():
        for k, v in fig.items():
            train_metrics[f"stage/{name}/{k}"] = v
    logging_seconds = sum(logger.seconds for _, logger in loggers)
    train_seconds = sum(f.get("seconds", 0.0) for f in figures.values())
    if train_seconds > 0:
        train_metrics["train/logging_share"] = logging_seconds / train_seconds
    tracker.log_metrics(run_id, train_metrics)

    summary: dict[str, dict[str, float]] = {}
    all_rows = []
    with_refined = cfg.method == "demon" and (not cfg.train or "refine" in [s.name for s in stages])
    keep = max(int(cfg.eval.visualize), int(cfg.eval.point_clouds))
    histograms: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for entry in cfg.data.test:
            dataset = instantiate(entry)
            print(f"[demon_lab] evaluating on {dataset.name} ({len(dataset)} pairs)", flush=True)
            histogram = PixelHistogram()
            if cfg.method == "demon":
                rows, kept = evaluate_dataset(chain, dataset, int(cfg.iterations), cfg.oracle,
                                              int(cfg.eval.batch_size), cfg.eval.max_samples, keep=keep,
                                              refined=with_refined, histogram=histogram)
                summary[dataset.name] = summarize(rows, int(cfg.iterations))
            else:
                rows, kept = _evaluate_baseline(cfg, entry, dataset, chain, keep, histogram)
                summary[dataset.name] = summarize_baseline(rows)
            histograms[dataset.name] = histogram.to_dict()
            all_rows += [{"dataset": dataset.name, **r} for r in rows]
            _save_visuals(Path(tmp), dataset.name, kept, int(cfg.eval.visualize), int(cfg.eval.point_clouds))
        metrics = {f"test/{name}/{k}": v for name, values in summary.items() for k, v in values.items()}
        tracker.log_metrics(run_id, metrics)
        _pause_point("metrics_logged")
        (Path(tmp) / "per_sample_metrics.csv").write_text(_csv(all_rows))
        (Path(tmp) / "pixel_errors.json").write_text(json.dumps(histograms) + "\n")
        tracker.log_artifact(run_id, Path(tmp) / "pixel_errors.json")
        tracker.log_artifact(run_id, Path(tmp) / "per_sample_metrics.csv")
        for sub in ("images", "point_clouds"):
            if (Path(tmp) / sub).is_dir():
                tracker.log_artifact(run_id, Path(tmp) / sub)
    if cfg.method == "demon":
        table = format_table(summary, int(cfg.iterations), with_refined)
    else:
        table = format_table(summary, 0, refined=False, passes=["baseline"])
    tracker.log_text(run_id, table + "\n", "results.txt")
    what = (f"{cfg.iterations} iterations{', oracle ' + str(cfg.oracle) if cfg.oracle else ''}"
            if cfg.method == "demon" else f"method {cfg.method}")
    print(f"\n[demon_lab] results (scale {cfg.scale.name}, seed {cfg.seed}, {what}; depth metrics on "
          f"unit-baseline depth, rot/tran in degrees, EPE in normalised flow units):\n{table}\n", flush=True)
    return {"summary": summary, "figures": figures}


def _evaluate_baseline(cfg: DictConfig, entry: DictConfig, dataset, chain, keep: int, histogram):
    """A classical baseline on one test set (``base_oracle`` reads the same samples at
    ``baseline.oracle_scale`` times the resolution)."""
    from demon_lab.baselines import BaselineConfig, evaluate_baseline
    from demon_lab.config import instantiate

    params = BaselineConfig(**{**OmegaConf.to_container(cfg.baseline, resolve=True), "seed": int(cfg.seed)})
    hires = None
    if cfg.method == "base_oracle":
        hires = instantiate(entry, size=[int(s) * params.oracle_scale for s in cfg.data.size])
    return evaluate_baseline(cfg.method, dataset, params, chain=chain, iterations=int(cfg.iterations),
                             hires_dataset=hires, max_samples=cfg.eval.max_samples, keep=keep,
                             histogram=histogram)


def _csv(rows: list[dict[str, Any]]) -> str:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=keys)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def _save_visuals(root: Path, name: str, kept: list[dict], n_images: int, n_clouds: int) -> None:
    import cv2
    import numpy as np
    import torch

    from demon_lab import geometry as geo

    def colour(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
        v = np.nan_to_num((x - lo) / max(hi - lo, 1e-9), nan=0.0).clip(0, 1)
        return cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_MAGMA)

    for i, s in enumerate(kept[:n_images]):
        (root / "images").mkdir(exist_ok=True)
        gt = s["gt_inv_depth"].numpy()
        lo, hi = float(np.nanmin(gt)), float(np.nanmax(gt))
        h, w = gt.shape
        pred = cv2.resize(s["inv_depth"].numpy(), (w, h), interpolation=cv2.INTER_NEAREST)
        image = ((s["image1"].permute(1, 2, 0).numpy() + 0.5) * 255).clip(0, 255).astype(np.uint8)[:, :, ::-1]
        flow = np.nan_to_num(s["flow"].numpy())  # a diverged net's NaN flow is drawn black
        mag, ang = cv2.cartToPolar(flow[0] * w, flow[1] * h)
        hsv = np.zeros((*flow.shape[1:], 3), np.uint8)
        hsv[..., 0], hsv[..., 1] = (ang * 90 / np.pi).astype(np.uint8), 255
        hsv[..., 2] = (mag / max(float(mag.max()), 1e-6) * 255).astype(np.uint8)
        flow_img = cv2.resize(cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR), (w, h), interpolation=cv2.INTER_NEAREST)
        normals = cv2.resize(((np.nan_to_num(s["normals"].numpy().transpose(1, 2, 0)) + 1) * 127.5).clip(0, 255)
                             .astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST)
        row = np.concatenate([image, colour(gt, lo, hi), colour(pred, lo, hi), flow_img, normals], 1)
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{name}_{i}_{s['id']}")
        cv2.imwrite(str(root / "images" / f"{safe}.png"), row)
    for i, s in enumerate(kept[:n_clouds]):
        (root / "point_clouds").mkdir(exist_ok=True)
        inv = s["inv_depth"][None, None].double()
        h, w = inv.shape[2:]
        rays = geo._rays(h, w, s["intrinsics"][None].double())[0]
        valid = (inv[0, 0] > 0) & torch.isfinite(inv[0, 0])
        points = (rays / inv[0]).permute(1, 2, 0)[valid].numpy()
        img = cv2.resize(((s["image1"].permute(1, 2, 0).numpy() + 0.5) * 255).clip(0, 255).astype(np.uint8), (w, h),
                         interpolation=cv2.INTER_AREA)[valid.numpy()]
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{name}_{i}_{s['id']}")
        lines = [f"{x:.5f} {y:.5f} {z:.5f} {r} {g} {b}" for (x, y, z), (r, g, b) in zip(points, img)]
        header = ["ply", "format ascii 1.0", f"element vertex {len(lines)}", "property float x", "property float y",
                  "property float z", "property uchar red", "property uchar green", "property uchar blue", "end_header"]
        (root / "point_clouds" / f"{safe}.ply").write_text("\n".join(header + lines) + "\n")


def _known_errors() -> tuple[type[BaseException], ...]:
    from demon_lab.data.sample import DataError
    from demon_lab.stages.cache import CheckpointError
    from demon_lab.tracking import TrackingError
    from demon_lab.train import TrainingDiverged

    return ConfigError, DataError, TrackingError, CheckpointError, TrainingDiverged


def set_threads(n: int) -> None:
    """Limit this process's torch and OpenCV CPU threads: processes that share cores, each running
    a thread per core, slow each other down far more than the share they give up."""
    import cv2
    import torch

    torch.set_num_threads(n)
    cv2.setNumThreads(n)


def _multirun_job_dir() -> Path | None:
    """The job's output folder when it runs as part of a multirun (None for a single run)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hydra_cfg = HydraConfig.get()
        return Path(hydra_cfg.runtime.output_dir) if hydra_cfg.mode == RunMode.MULTIRUN else None
    except ValueError:
        return None


def main_task(cfg: DictConfig) -> None:
    """Hydra task. A single run exits non-zero with one line on a configuration, data,
    tracking-store or checkpoint error or diverged training, and with the traceback on anything
    else. In a multirun a failing job never stops the sweep: its run is
    FAILED with the error recorded, it prints one line, leaves ``error.txt`` (with the traceback)
    in its output folder, and the sweep goes on; the sweep's end lists the failures and exits
    non-zero (:class:`demon_lab.callbacks.MultirunTracking`)."""
    import traceback

    job_dir = _multirun_job_dir()
    marker = job_dir / "error.txt" if job_dir is not None else None
    if marker is not None:
        marker.unlink(missing_ok=True)
    server = None
    try:
        from demon_lab.train import global_rank

        if cfg.tracking.get("server") and global_rank(cfg) == 0:  # DDP workers only train
            from demon_lab.tracking import LocalServer

            server = LocalServer(cfg.tracking.server)
            server.start()
        run(cfg)
    except Exception as e:
        known = isinstance(e, _known_errors())
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
    finally:
        if server is not None:
            server.stop()
