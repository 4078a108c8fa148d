"""Hydra callbacks: one MLflow parent run per multirun.

``on_multirun_start`` creates the tracking store and the experiment once, before any job starts
(parallel jobs racing to create a fresh SQLite database is a known MLflow failure), and a parent
run whose id the jobs find in ``DEMON_LAB_PARENT_RUN`` (they tag themselves with
``mlflow.parentRunId``). ``on_multirun_end`` marks the parent FINISHED.
"""

from __future__ import annotations

import os
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

PARENT_ENV = "DEMON_LAB_PARENT_RUN"


class MultirunTracking(Callback):
    def __init__(self) -> None:
        self.tracker = None
        self.parent: str | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from demon_lab.tracking import TAG, Tracker

        try:
            self.tracker = Tracker(config.tracking.uri, config.experiment, config.tracking.artifact_dir)
        except Exception:  # a bad store is reported by each job with one line
            return
        overrides = " ".join(config.hydra.overrides.task)
        self.parent = self.tracker.start(f"sweep {config.experiment}: {overrides}"[:250],
                                         {f"{TAG}kind": "sweep", f"{TAG}sweep": overrides,
                                          f"{TAG}experiment": config.experiment})
        os.environ[PARENT_ENV] = self.parent

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self.tracker is not None and self.parent is not None:
            self.tracker.finish(self.parent)
            os.environ.pop(PARENT_ENV, None)
