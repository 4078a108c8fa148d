"""Hydra callbacks: one MLflow parent run per multirun, the study's report on it, the sweep's verdict.

``on_sweep_checked`` (called by demon_lab's sweeper once every job of the sweep is checked) creates
the tracking store and the experiment once, before any job starts (parallel jobs racing to create a
fresh SQLite database is a known MLflow failure), and the parent run; with ``tracking=local_server``
it starts the sweep's one MLflow server. ``on_job_start`` hands the parent run id and the server's
address to the job in the job's own process (``demon_lab.app.job.PARENT_RUN`` and ``SWEEP_SERVER``;
with the joblib and SLURM launchers this callback travels there pickled, both with it), and the job
tags itself with ``mlflow.parentRunId``.
The same sweep command issued again (after a kill, a failure or a cluster pre-emption) continues
the same parent run, so its children are every job of the sweep: the finished ones (skipped this
time) and the ones run now.

A failing job never stops the sweep: Hydra ends it ``FAILED`` (``demon_lab.app.job.main_task``) and
the sweeper launches the rest, handing each batch's JobReturns to ``on_jobs_returned`` in the
sweep's own process, whatever the launcher (:mod:`demon_lab.app.sweeper`). ``on_multirun_end``
attaches the study's report (its tables and figures, from every FINISHED run in the store:
``report/`` in the parent run's artifacts, so the dashboard shows it), prints the table of the
sweep's own jobs and logs it on the parent run (``jobs.txt``), lists the jobs that failed this time,
marks the parent FINISHED or FAILED and exits non-zero if any failed.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from demon_lab.pipeline.methods import method

log = logging.getLogger(__name__)


class MultirunTracking(Callback):
    def __init__(self) -> None:
        self.tracker = None
        self.parent: str | None = None
        self.failed: list[str] = []  # the folders of this sweep's failed jobs
        self.jobs: list[dict[str, Any]] = []  # every job of this sweep: overrides, status, run id, pass
        self.server = None
        self.served: str | None = None  # the address of self.server, which travels with the jobs

    def __getstate__(self) -> dict[str, Any]:
        """Launchers that run jobs in other processes (joblib, submitit) pickle the callbacks with
        each job: the store client and the server process stay with the sweep's own process."""
        return {**self.__dict__, "tracker": None, "server": None}

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self.failed, self.jobs, self.parent = [], [], None

    def on_sweep_checked(self, config: DictConfig, **kwargs: Any) -> None:
        """Once the sweeper has checked every job (:mod:`demon_lab.app.sweeper`), before the first
        launch: the local server, if the sweep asks for one, and the sweep's parent run (a sweep
        issued again continues its run)."""
        from demon_lab.pipeline.settings import TrackingSettings
        from demon_lab.pipeline.tracking import TAG, Tracker

        server = TrackingSettings.of(config.tracking, "tracking").server
        if server is not None:
            from demon_lab.pipeline.tracking import LocalServer, TrackingError

            self.server = LocalServer(**server.arguments())
            try:
                self.server.start()
            except TrackingError as e:
                print(f"error: {e}", file=sys.stderr, flush=True)
                sys.exit(2)
            self.served = self.server.uri
        try:
            self.tracker = Tracker(config.tracking.uri, config.experiment, config.tracking.artifact_dir,
                                   local_server=self.served is not None)
        except Exception:  # a bad store is reported by each job with one line
            return
        from demon_lab.pipeline.identity import sweep_key

        key = sweep_key(config.experiment, config.hydra.overrides.task)
        overrides = " ".join(config.hydra.overrides.task)
        self.parent = self.tracker.find_sweep(key)
        if self.parent is not None:
            self.tracker.reopen(self.parent)
            log.info("continuing the sweep run %s: finished jobs are skipped", self.parent)
        else:
            self.parent = self.tracker.start(f"sweep {config.experiment}: {overrides}"[:250],
                                             {f"{TAG}kind": "sweep", f"{TAG}sweep": overrides,
                                              f"{TAG}sweep_key": key, f"{TAG}experiment": config.experiment})

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """In the job's process, just before the task: the sweep's parent run and the address of the
        server it started, for the job (None in a single run, which has no multirun start)."""
        from demon_lab.app.job import PARENT_RUN, SWEEP_SERVER

        PARENT_RUN.set(self.parent)
        SWEEP_SERVER.set(self.served)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        from demon_lab.app.job import PARENT_RUN, SWEEP_SERVER

        PARENT_RUN.set(None)
        SWEEP_SERVER.set(None)

    def on_jobs_returned(self, config: DictConfig, job_returns: Sequence[JobReturn], **kwargs: Any) -> None:
        """In the sweep's process, after each batch (:mod:`demon_lab.app.sweeper`): the failed jobs'
        folders, each with its ``error.txt``, as the command line shows them."""
        for r in job_returns:
            returned = r.return_value if r.status == JobStatus.COMPLETED and isinstance(r._return_value, dict) else {}
            cfg = r.cfg  # (None where Hydra could not compose the job)
            chain = cfg is None or method(cfg.method).scores_passes  # (a classical method's summary has no passes)
            self.jobs.append({"overrides": list(r.overrides or []), "run_id": returned.get("run_id"),
                              "status": returned.get("status") or ("FAILED" if r.status == JobStatus.FAILED else "-"),
                              "pass": ("-" if cfg is None else cfg.iterations) if chain else "baseline"})
            if r.status == JobStatus.FAILED:
                folder = Path(r.hydra_cfg.hydra.runtime.output_dir)
                self.failed.append(str(folder.relative_to(Path.cwd()) if folder.is_relative_to(Path.cwd())
                                       else folder))

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from demon_lab.pipeline.tracking import TAG

        failed = sorted(self.failed)
        if self.tracker is not None and self.parent is not None:
            children = self.tracker.children(self.parent)
            counts = {s: sum(1 for r in children if r.info.status == s) for s in ("FINISHED", "FAILED", "RUNNING")}
            # a FAILED attempt (a crash, a SIGTERM) whose job has since FINISHED is not a failed job
            retried = sum(1 for r in children if r.info.status == "FAILED"
                          and self.tracker.find_finished(r.data.tags.get(f"{TAG}run_key", "")))
            self.tracker.set_tags(self.parent, {f"{TAG}jobs_finished": counts["FINISHED"],
                                                f"{TAG}jobs_failed_now": len(failed)})
            self._publish_study(config)
            self._jobs_table()
            self.tracker.finish(self.parent, "FAILED" if failed else "FINISHED")
            log.info("sweep run %s: %d job runs FINISHED, %d FAILED%s", self.parent, counts["FINISHED"],
                     counts["FAILED"] - retried,
                     f" ({retried} earlier FAILED attempt(s) of jobs that have since FINISHED)" if retried else "")
        if self.server is not None:
            self.server.stop()
        if failed:
            listing = "; ".join(failed)
            print(f"error: {len(failed)} job(s) of the sweep failed (each folder has error.txt): {listing}",
                  file=sys.stderr, flush=True)
            sys.exit(1)

    def _jobs_table(self) -> None:
        """The table of this sweep's own jobs (:func:`demon_lab.reporting.tables.sweep_table`): printed,
        and logged on the parent run as ``jobs.txt``."""
        from demon_lab.reporting.tables import sweep_table

        if not self.jobs:
            return
        metrics = {}
        for job in self.jobs:
            if job["run_id"]:
                try:
                    metrics[job["run_id"]] = self.tracker.client.get_run(job["run_id"]).data.metrics
                except Exception as e:  # (a run removed from the store meanwhile: its row shows no values)
                    log.warning("sweep table: run %s: %s", job["run_id"], e)
        table = sweep_table(self.jobs, metrics)
        print(f"[demon_lab] {table}\n", flush=True)
        self.tracker.log_text(self.parent, table + "\n", "jobs.txt")

    def _publish_study(self, config: DictConfig) -> None:
        """The study's report (``python -m demon_lab.report NAME``, from every FINISHED run in the
        store) as artifacts of the parent run; a sweep of an experiment without a study spec has
        none. A report that cannot be built is a warning: the sweep's own result stands."""
        from demon_lab.reporting import provenance, report

        study = None
        try:  # the study of the sweep's design where one reports it (design=learned: NAME_learned)
            design = provenance.config_design(config)
            study = report.study_of(str(config.get("experiment")), design=design)
            if study is None:
                return
            paths = report.publish(study, self.tracker.uri, self.parent)
        except Exception as e:  # the jobs' runs are recorded either way
            log.warning("study %s: no report on the sweep run (%s: %s)", study, type(e).__name__, e)
            return
        log.info("study %s: its report is on the sweep run %s (%d artifacts under report/)", study, self.parent,
                 len(paths))
