"""MLflow tracking (DESIGN.md section 6 is the contract).

One job = one MLflow run in the experiment named after the ablation (``experiment``), tagged with
its run key (a hash of the resolved semantic config), seed, scale, git commit, versions and
device; params are the flattened config and the resolved config is an artifact. Stage trainings
are child runs with their loss curves. Final metrics are ``test/<set>/<metric>``,
``test/<set>/it<k>/<metric>`` and ``test/<set>/refined/<metric>``. A run ends FINISHED only when
the job completed and FAILED (error recorded) when it raised; a job whose run key already has a
FINISHED run is skipped unless forced.

The default store is ``sqlite:///mlflow.db`` in the working directory with artifacts in
``./mlartifacts``; a team points ``tracking.uri`` (or ``MLFLOW_TRACKING_URI``) at a server.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

TAG = "demon_lab."
# Config keys that do not change what a job computes (so they are not part of its run key).
NON_SEMANTIC = ("tracking", "force", "hydra", "cache_dir", "eval.visualize", "eval.point_clouds", "row",
                "data.num_workers")


def metric_name(key: str) -> str:
    """MLflow's allowed characters: ``delta_1.25^2`` is logged as ``delta_1.25_2``."""
    return re.sub(r"[^A-Za-z0-9_\-. :/]", "_", key)


def _quiet_mlflow() -> None:
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    os.environ.setdefault("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")
    os.environ.setdefault("MLFLOW_LOGGING_LEVEL", "ERROR")
    import logging
    import warnings

    import mlflow  # noqa: F401  (it configures its loggers on import: quieten them afterwards)

    logging.getLogger("mlflow").setLevel(logging.ERROR)
    logging.getLogger("alembic").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", module="mlflow")
    warnings.filterwarnings("ignore", category=DeprecationWarning, module="sqlalchemy")


def semantic_config(cfg: DictConfig) -> dict[str, Any]:
    plain = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(plain, dict)
    for dotted in NON_SEMANTIC:
        node = plain
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.get(p, {})
        if isinstance(node, dict):
            node.pop(leaf, None)
    return plain


def run_key(cfg: DictConfig) -> str:
    """Hash of the semantic config and the stage cache's code version (a change of the training
    code that changes results bumps it, so old FINISHED runs no longer count as this job)."""
    from demon_lab.stages.cache import CODE_VERSION

    payload = {"config": semantic_config(cfg), "code_version": CODE_VERSION}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        elif isinstance(v, list) and v and isinstance(v[0], Mapping):
            for i, item in enumerate(v):
                out.update(flatten(item, f"{key}.{i}."))
        else:
            out[key] = str(v)[:500]
    return out


def git_state() -> dict[str, str]:
    try:
        here = Path(__file__).resolve().parent
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                                timeout=5).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return {"git_commit": commit or "unknown", "git_dirty": str(bool(dirty)).lower()}
    except (OSError, subprocess.SubprocessError):
        return {"git_commit": "unknown", "git_dirty": "unknown"}


class TrackingError(RuntimeError):
    """The tracking store cannot be used: one line naming the URI and the problem."""


class Tracker:
    """A thin layer over ``MlflowClient``: no global active-run state, batched metrics."""

    def __init__(self, uri: str, experiment: str, artifact_dir: str | Path = "mlartifacts"):
        _quiet_mlflow()
        from mlflow.tracking import MlflowClient

        self.uri = _absolute_sqlite(uri)
        try:
            self.client = MlflowClient(tracking_uri=self.uri)
        except Exception as e:
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise TrackingError(f"tracking.uri {self.uri!r}: cannot use the tracking store ({first[:200]})") from None
        self.experiment_name = experiment
        self.artifact_dir = Path(artifact_dir).resolve()
        self.experiment_id = self._ensure_experiment()

    def _ensure_experiment(self) -> str:
        last: Exception | None = None
        for attempt in range(5):  # parallel jobs may race to create it
            try:
                exp = self.client.get_experiment_by_name(self.experiment_name)
                if exp is not None:
                    return exp.experiment_id
                location = None
                if self.uri.startswith(("sqlite:", "file:")) or "://" not in self.uri:
                    location = (self.artifact_dir / self.experiment_name).as_uri()
                return self.client.create_experiment(self.experiment_name, artifact_location=location)
            except Exception as e:
                last = e
                time.sleep(0.2 * (attempt + 1))
        message = str(last).splitlines()[0] if last else "unknown error"
        raise TrackingError(f"tracking.uri {self.uri!r}: cannot use the tracking store ({message})")

    def find_finished(self, key: str) -> str | None:
        query = f"tags.`{TAG}run_key` = '{key}' and attributes.status = 'FINISHED'"
        runs = self.client.search_runs([self.experiment_id], filter_string=query, max_results=1)
        return runs[0].info.run_id if runs else None

    def find_interrupted(self, key: str, parent_id: str | None = None, tag: str = "run_key") -> str | None:
        """The newest RUNNING run whose ``demon_lab.<tag>`` is ``key`` (under ``parent_id`` if
        given): a job (or stage) that was killed and never reached FINISHED or FAILED."""
        query = f"tags.`{TAG}{tag}` = '{key}' and attributes.status = 'RUNNING'"
        if parent_id:
            query += f" and tags.`mlflow.parentRunId` = '{parent_id}'"
        runs = self.client.search_runs([self.experiment_id], filter_string=query, max_results=1,
                                       order_by=["attributes.start_time DESC"])
        return runs[0].info.run_id if runs else None

    def resumable(self, run_id: str, key: str) -> bool:
        """Whether ``run_id`` exists in this experiment, has run key ``key`` and is not terminated."""
        try:
            run = self.client.get_run(run_id)
        except Exception:
            return False
        return (run.info.experiment_id == self.experiment_id and run.info.status == "RUNNING"
                and run.data.tags.get(f"{TAG}run_key") == key)

    def resume(self, run_id: str) -> None:
        run = self.client.get_run(run_id)
        count = int(run.data.tags.get(f"{TAG}resumed", "0")) + 1
        self.client.set_tag(run_id, f"{TAG}resumed", str(count))

    def start(self, name: str, tags: Mapping[str, str], parent_id: str | None = None) -> str:
        all_tags = {str(k): str(v) for k, v in tags.items()}
        if parent_id:
            all_tags["mlflow.parentRunId"] = parent_id
        run = self.client.create_run(self.experiment_id, tags=all_tags, run_name=name)
        return run.info.run_id

    def log_params(self, run_id: str, params: Mapping[str, str]) -> None:
        from mlflow.entities import Param

        items = [Param(k, v) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i:i + 100])

    def log_metrics(self, run_id: str, values: Mapping[str, float], step: int = 0) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(metric_name(k), float(v), now, step) for k, v in values.items() if v == v]  # drop NaN
        for i in range(0, len(items), 500):
            self.client.log_batch(run_id, metrics=items[i:i + 500])

    def set_tags(self, run_id: str, tags: Mapping[str, str]) -> None:
        for k, v in tags.items():
            self.client.set_tag(run_id, k, str(v))

    def log_artifact(self, run_id: str, path: str | Path, artifact_path: str | None = None) -> None:
        self.client.log_artifact(run_id, str(path), artifact_path)

    def log_text(self, run_id: str, text: str, file: str) -> None:
        self.client.log_text(run_id, text, file)

    def finish(self, run_id: str, status: str = "FINISHED") -> None:
        self.client.set_terminated(run_id, status=status)

    def fail(self, run_id: str, error: BaseException) -> None:
        message = f"{type(error).__name__}: {error}"
        try:
            self.client.set_tag(run_id, f"{TAG}error", message[:5000])
            self.client.log_text(run_id, message + "\n", "error.txt")
        finally:
            self.client.set_terminated(run_id, status="FAILED")


def _absolute_sqlite(uri: str) -> str:
    """sqlite:///relative.db -> an absolute path, so jobs in other directories share the store."""
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not uri[len(prefix):].startswith("/"):
        return prefix + str(Path(uri[len(prefix):]).resolve())
    return uri


def stage_logger(tracker: Tracker, run_id: str, every: int):
    """A Lightning logger sending a stage's training curves to its MLflow run in batches."""
    from lightning.pytorch.loggers.logger import Logger, rank_zero_experiment

    class StageLogger(Logger):
        def __init__(self):
            super().__init__()
            self.buffer: list[tuple[dict[str, float], int]] = []
            self.seconds = 0.0

        @property
        def name(self) -> str:
            return "mlflow"

        @property
        def version(self) -> str:
            return run_id

        @property
        @rank_zero_experiment
        def experiment(self):
            return tracker.client

        def log_hyperparams(self, params, *args, **kwargs) -> None:
            pass

        def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
            self.buffer.append(({k: float(v) for k, v in metrics.items()}, int(step or 0)))
            if len(self.buffer) >= max(1, 50 // max(every, 1)):
                self.flush()

        def flush(self) -> None:
            if not self.buffer:
                return
            from mlflow.entities import Metric

            start = time.perf_counter()
            now = int(time.time() * 1000)
            items = [Metric(metric_name(k), v, now, s) for values, s in self.buffer for k, v in values.items()
                     if v == v]
            for i in range(0, len(items), 500):
                tracker.client.log_batch(run_id, metrics=items[i:i + 500])
            self.buffer.clear()
            self.seconds += time.perf_counter() - start

        def finalize(self, status: str) -> None:
            self.flush()

    return StageLogger()
