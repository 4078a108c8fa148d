"""Hydra callbacks: one MLflow parent run per multirun, and the sweep's verdict.

``on_multirun_start`` creates the tracking store and the experiment once, before any job starts
(parallel jobs racing to create a fresh SQLite database is a known MLflow failure), and the parent
run whose id the jobs find in ``DEMON_LAB_PARENT_RUN`` (they tag themselves with
``mlflow.parentRunId``). The same sweep command issued again (after a kill, a failure or a
cluster pre-emption) continues the same parent run, so its children are every job of the sweep:
the finished ones (skipped this time) and the ones run now.

A failing job never stops the sweep (``demon_lab.app.main_task``); ``on_multirun_end`` lists the
jobs that failed this time, marks the parent FINISHED or FAILED and exits non-zero if any failed.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

PARENT_ENV = "DEMON_LAB_PARENT_RUN"


def _changes_results(override: str) -> bool:
    """False for an override of a key that is not part of a job's run key (tracking.NON_SEMANTIC:
    launcher, store, thread count, cache folder...), e.g. ``hydra/launcher=joblib``, ``threads=1``."""
    from demon_lab.tracking import NON_SEMANTIC

    key = override.lstrip("+~").split("=", 1)[0].replace("/", ".")
    return not any(key == k or key.startswith(k + ".") for k in NON_SEMANTIC)


def sweep_key(config: DictConfig) -> str:
    """The sweep's identity: its experiment, the command-line overrides that change what its
    jobs compute and the code and scene-generator versions (as in every run key), so the same
    sweep re-issued with another thread count, store address or launcher continues its parent
    run, and one re-issued after a version change starts a new parent."""
    from demon_lab.stages.cache import versions

    overrides = sorted(o for o in config.hydra.overrides.task if _changes_results(o))
    blob = json.dumps({"experiment": str(config.experiment), "overrides": overrides, **versions()})
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


class MultirunTracking(Callback):
    def __init__(self) -> None:
        self.tracker = None
        self.parent: str | None = None
        self.started = 0.0
        self.server = None

    def __getstate__(self) -> dict[str, Any]:
        """Launchers that run jobs in other processes (joblib, submitit) pickle the callbacks with
        each job: the store client and the server process stay with the sweep's own process."""
        return {**self.__dict__, "tracker": None, "server": None}

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from demon_lab.tracking import TAG, Tracker

        self.started = time.time() - 1.0
        if config.tracking.get("server"):
            from demon_lab.tracking import LocalServer, TrackingError

            self.server = LocalServer(config.tracking.server)
            try:
                self.server.start()
            except TrackingError as e:
                print(f"error: {e}", file=sys.stderr, flush=True)
                sys.exit(2)
        try:
            self.tracker = Tracker(config.tracking.uri, config.experiment, config.tracking.artifact_dir)
        except Exception:  # a bad store is reported by each job with one line
            return
        key = sweep_key(config)
        overrides = " ".join(config.hydra.overrides.task)
        self.parent = self.tracker.find_sweep(key)
        if self.parent is not None:
            self.tracker.reopen(self.parent)
            print(f"[demon_lab] continuing the sweep run {self.parent}: finished jobs are skipped", flush=True)
        else:
            self.parent = self.tracker.start(f"sweep {config.experiment}: {overrides}"[:250],
                                             {f"{TAG}kind": "sweep", f"{TAG}sweep": overrides,
                                              f"{TAG}sweep_key": key, f"{TAG}experiment": config.experiment})
        os.environ[PARENT_ENV] = self.parent

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from demon_lab.tracking import TAG

        sweep_dir = Path(config.hydra.sweep.dir)
        failed = sorted(p.parent for p in sweep_dir.rglob("error.txt") if p.stat().st_mtime >= self.started)
        if self.tracker is not None and self.parent is not None:
            children = self.tracker.children(self.parent)
            counts = {s: sum(1 for r in children if r.info.status == s) for s in ("FINISHED", "FAILED", "RUNNING")}
            # a FAILED attempt (a crash, a SIGTERM) whose job has since FINISHED is not a failed job
            retried = sum(1 for r in children if r.info.status == "FAILED"
                          and self.tracker.find_finished(r.data.tags.get(f"{TAG}run_key", "")))
            self.tracker.set_tags(self.parent, {f"{TAG}jobs_finished": counts["FINISHED"],
                                                f"{TAG}jobs_failed_now": len(failed)})
            self.tracker.finish(self.parent, "FAILED" if failed else "FINISHED")
            os.environ.pop(PARENT_ENV, None)
            print(f"[demon_lab] sweep run {self.parent}: {counts['FINISHED']} job runs FINISHED, "
                  f"{counts['FAILED'] - retried} FAILED"
                  + (f" ({retried} earlier FAILED attempt(s) of jobs that have since FINISHED)" if retried else ""),
                  flush=True)
        if self.server is not None:
            self.server.stop()
        if failed:
            listing = "; ".join(str(p) for p in failed)
            print(f"error: {len(failed)} job(s) of the sweep failed (each folder has error.txt): {listing}",
                  file=sys.stderr, flush=True)
            sys.exit(1)
