"""Hydra callbacks: one MLflow parent run per multirun, the study's report on it, the sweep's verdict.

``on_multirun_start`` (Hydra calls it before the sweeper starts) checks every job of the sweep
(:func:`demon_lab.app.sweep.check_sweep`: one line and exit status 2 on the first bad one), then creates
the tracking store and the experiment once, before any job starts (parallel jobs racing to create a
fresh SQLite database is a known MLflow failure), and the parent run; with ``tracking=local_server``
it starts the sweep's one MLflow server. ``on_job_start`` hands the parent run id and the server's
address to the job in the job's own process (``demon_lab.app.job.PARENT_RUN`` and ``SWEEP_SERVER``;
with the joblib and SLURM launchers this callback travels there pickled, both with it), and the job
tags itself with ``mlflow.parentRunId``.
The same sweep command issued again (after a kill, a failure or a cluster pre-emption) continues
the same parent run, so its children are every job of the sweep: the finished ones (skipped this
time) and the ones run now.

A failing job never stops the sweep: it records its failure and returns
(``demon_lab.app.job.main_task``), and Hydra's basic sweeper launches the rest. ``on_job_end``, in the
job's own process, leaves the job's outcome in its folder (:func:`demon_lab.app.sweep.write_record`),
marked with the sweep's id; ``on_multirun_end``, in the sweep's process, reads its jobs' records
(:mod:`demon_lab.app.sweep`), attaches the study's report (its tables and figures, from every FINISHED run in the store:
``report/`` in the parent run's artifacts, so the dashboard shows it), prints the table of the
sweep's own jobs and logs it on the parent run (``jobs.txt``), lists the jobs that failed this time,
marks the parent FINISHED or FAILED and exits non-zero if any failed.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

log = logging.getLogger(__name__)


class MultirunTracking(Callback):
    def __init__(self) -> None:
        self.tracker = None
        self.parent: str | None = None
        self.records: Path | None = None  # where this sweep's jobs leave their outcomes (app.sweep.records_dir)
        self.jobs: list[dict[str, Any]] = []  # this sweep's jobs: overrides, status, run id, pass (from their records)
        self.server = None
        self.served: str | None = None  # the address of self.server, which travels with the jobs

    def __getstate__(self) -> dict[str, Any]:
        """Launchers that run jobs in other processes (joblib, submitit) pickle the callbacks with
        each job: the store client and the server process stay with the sweep's own process."""
        return {**self.__dict__, "tracker": None, "server": None}

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Before the sweeper starts: every job of the sweep checked (one line and exit status 2 on the
        first bad one, before any job starts or any run is created), then the local server, if the
        sweep asks for one, and the sweep's parent run (a sweep issued again continues its run)."""
        import uuid

        from hydra.core.global_hydra import GlobalHydra

        from demon_lab.app.sweep import check_sweep, records_dir
        from demon_lab.pipeline.settings import TrackingSettings

        self.parent, self.records = None, records_dir(config.hydra.sweep.dir, uuid.uuid4().hex)
        error = check_sweep(config, GlobalHydra.instance().config_loader())
        if error:
            print(f"error: {error}", file=sys.stderr, flush=True)
            sys.exit(2)
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
        try:  # (Hydra turns a callback's exception into a warning: the sweep would go on without its run)
            self.parent = self.tracker.find_sweep(key)
            if self.parent is not None:
                self.tracker.reopen(self.parent)
                log.info("continuing the sweep run %s: finished jobs are skipped", self.parent)
            else:
                self.parent = self.tracker.start(f"sweep {config.experiment}: {overrides}"[:250],
                                                 {f"{TAG}kind": "sweep", f"{TAG}sweep": overrides,
                                                  f"{TAG}sweep_key": key, f"{TAG}experiment": config.experiment})
        except Exception as e:
            print(f"error: the sweep's run in {config.tracking.uri}: {str(e).strip().splitlines()[0]}",
                  file=sys.stderr, flush=True)
            sys.exit(2)

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        """In the job's process, just before the task: the sweep's parent run and the address of the
        server it started, for the job (None in a single run, which has no multirun start)."""
        from demon_lab.app.job import PARENT_RUN, SWEEP_SERVER

        PARENT_RUN.set(self.parent)
        SWEEP_SERVER.set(self.served)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """In the job's process, after the task: in a sweep, the job's outcome in its folder, for the
        sweep's end (:func:`demon_lab.app.sweep.write_record`)."""
        from demon_lab.app.job import PARENT_RUN, SWEEP_SERVER
        from demon_lab.app.sweep import write_record

        PARENT_RUN.set(None)
        SWEEP_SERVER.set(None)
        if self.records is not None and job_return.hydra_cfg is not None:
            write_record(job_return, self.records)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """In the sweep's process, after its last job: its jobs' records read, the study's report on the
        parent run, the table of its jobs, the parent FINISHED or FAILED, the failed jobs' folders
        listed and exit status 1 if any failed."""
        from demon_lab.app.sweep import read_records
        from demon_lab.pipeline.tracking import TAG

        records = read_records(self.records) if self.records is not None else []
        if self.records is not None:  # (read once: the folder is this sweep's alone)
            import shutil

            shutil.rmtree(self.records, ignore_errors=True)
        self.jobs = [{k: r[k] for k in ("overrides", "run_id", "status", "pass")} for r in records]
        failed = sorted(_shown(Path(r["folder"])) for r in records if r["status"] == "FAILED")
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


def _shown(folder: Path) -> str:
    """A job's folder as the command line shows it: relative to the working directory where under it."""
    return str(folder.relative_to(Path.cwd()) if folder.is_relative_to(Path.cwd()) else folder)
