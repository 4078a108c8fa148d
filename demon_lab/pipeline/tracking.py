"""MLflow tracking (the contract: docs/running.md, "Tracking").

One job = one MLflow run in the experiment named after the study (``experiment``), tagged with
its run key (:func:`demon_lab.pipeline.identity.run_key`), seed, scale, versions and device, and
with MLflow's own source tags (the git commit among them); params are the flattened config and the
resolved config is an artifact. Stage trainings are child runs with their loss curves (Lightning's
``MLFlowLogger`` on the child run). Final metrics are ``test/<set>/<metric>``,
``test/<set>/it<k>/<metric>`` and ``test/<set>/refined/<metric>``. A run ends FINISHED only when the
job completed and FAILED (error recorded) when it raised; a job whose run key already has a
FINISHED run is skipped unless forced.

The default store is ``sqlite:///mlflow.db`` in the working directory with artifacts in
``./mlartifacts``; a team points ``tracking.uri`` (or ``MLFLOW_TRACKING_URI``) at a server.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
import subprocess
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from filelock import FileLock

TAG = "demon_lab."
log = logging.getLogger(__name__)


def metric_name(key: str) -> str:
    """MLflow's allowed characters: ``delta_1.25^2`` is logged as ``delta_1.25_2``."""
    return re.sub(r"[^A-Za-z0-9_\-. :/]", "_", key)


def _quiet_mlflow() -> None:
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    os.environ.setdefault("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")
    os.environ.setdefault("MLFLOW_LOGGING_LEVEL", "ERROR")
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    import logging
    import warnings

    import mlflow  # noqa: F401  (it configures its loggers on import: quieten them afterwards)

    logging.getLogger("mlflow").setLevel(logging.ERROR)
    logging.getLogger("alembic").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", module="mlflow")
    warnings.filterwarnings("ignore", category=DeprecationWarning, module="sqlalchemy")


def version_tags() -> dict[str, str]:
    """``demon_lab.code_version`` and ``demon_lab.generator_version`` of this code: the versions
    every run key includes (:func:`demon_lab.pipeline.identity.versions`), as tags, so a report can tell
    runs of older code or scenes apart."""
    from demon_lab.pipeline.identity import versions

    return {f"{TAG}{k}": str(v) for k, v in versions().items()}


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


@functools.cache
def _checkout():
    """The git checkout that demon_lab's own code runs from (GitPython's ``Repo``), or None: an
    installed package, perhaps inside some other repository, has no commit of its own."""
    try:
        import git  # GitPython, what MLflow reads its git tags with

        package = Path(__file__).resolve().parents[1]
        repo = git.Repo(package, search_parent_directories=True)
        repo.git.ls_files("--error-unmatch", str(package / "__init__.py"))
        return repo
    except Exception:
        return None


def source_tags() -> dict[str, str]:
    """A copy of :func:`_source_tags`, read once per process (every run a job starts carries them)."""
    return dict(_source_tags())


@functools.cache
def _source_tags() -> dict[str, str]:
    """MLflow's own context tags, as ``mlflow.start_run`` sets them (``MlflowClient.create_run`` does
    not): ``mlflow.user``, ``mlflow.source.name`` and ``mlflow.source.type``, and, when demon_lab runs
    from a git checkout, ``mlflow.source.git.commit``, ``.branch`` and ``.repoURL`` of that checkout
    (MLflow would read them from the entry point, ``sys.argv[0]``, which under a cluster launcher is the
    launcher's own file)."""
    from mlflow.tracking.context.registry import resolve_tags
    from mlflow.utils.git_utils import get_git_branch, get_git_commit, get_git_repo_url

    tags = {k: v for k, v in resolve_tags().items() if not k.startswith("mlflow.source.git.")}
    repo = _checkout()
    if repo is not None:
        where = str(repo.working_dir)
        for key, read in (("commit", get_git_commit), ("branch", get_git_branch), ("repoURL", get_git_repo_url)):
            value = read(where)
            if value:
                tags[f"mlflow.source.git.{key}"] = value
    return tags


def git_state() -> dict[str, str]:
    """``git_dirty``: whether the checkout demon_lab runs from has uncommitted changes to tracked files
    (``true`` or ``false``; ``unknown`` outside a checkout), the one git fact MLflow does not tag."""
    repo = _checkout()
    return {"git_dirty": "unknown" if repo is None else str(repo.is_dirty(untracked_files=False)).lower()}


class TrackingError(RuntimeError):
    """The tracking store cannot be used: one line naming the URI and the problem."""


class Tracker:
    """A thin layer over ``MlflowClient``: no global active-run state, batched metrics."""

    def __init__(self, uri: str, experiment: str, artifact_dir: str | Path = "mlartifacts",
                 local_server: bool = False):
        """``local_server``: ``uri`` is the loopback server of ``tracking=local_server``
        (:class:`LocalServer`), whose new experiments keep their artifacts in ``artifact_dir`` on
        disk, as a SQLite store's do, readable without the server."""
        _quiet_mlflow()
        self.local_server = local_server
        from mlflow.tracking import MlflowClient

        self.uri = _absolute_sqlite(uri)
        self.experiment_name = experiment
        self.artifact_dir = Path(artifact_dir).resolve()
        if self.uri.startswith(("http://", "https://")):
            check_server(self.uri)
        with _store_lock(self.uri):  # parallel jobs must not create or migrate a fresh SQLite file at once
            try:
                self.client = MlflowClient(tracking_uri=self.uri)
            except Exception as e:
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise TrackingError(f"tracking.uri {self.uri!r}: cannot use the tracking store "
                                    f"({first[:200]})") from None
            self.experiment_id = self._ensure_experiment()

    def _ensure_experiment(self) -> str:
        last: Exception | None = None
        for attempt in range(5):  # parallel jobs may race to create it
            try:
                exp = self.client.get_experiment_by_name(self.experiment_name)
                if exp is not None:
                    return exp.experiment_id
                location = None
                local = self.uri.startswith(("sqlite:", "file:")) or "://" not in self.uri
                if local or self.local_server:  # readable without the server
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

    def find_sweep(self, key: str) -> str | None:
        """The newest parent run of the sweep with this key (:func:`demon_lab.pipeline.identity.sweep_key`)."""
        query = f"tags.`{TAG}sweep_key` = '{key}'"
        runs = self.client.search_runs([self.experiment_id], filter_string=query, max_results=1,
                                       order_by=["attributes.start_time DESC"])
        return runs[0].info.run_id if runs else None

    def reopen(self, run_id: str) -> None:
        """Mark a terminated (or killed) run RUNNING again, counting the re-issues."""
        self.client.update_run(run_id, status="RUNNING")
        self.resume(run_id)

    def children(self, run_id: str) -> list:
        query = f"tags.`mlflow.parentRunId` = '{run_id}'"
        return self.client.search_runs([self.experiment_id], filter_string=query, max_results=5000)

    def resume(self, run_id: str) -> None:
        """Count the resumption and re-tag the run with the source (:func:`source_tags`) that finishes it."""
        run = self.client.get_run(run_id)
        count = int(run.data.tags.get(f"{TAG}resumed", "0")) + 1
        self.client.set_tag(run_id, f"{TAG}resumed", str(count))
        source = source_tags()
        self.set_tags(run_id, source)
        stale = {k for k in run.data.tags if k.startswith("mlflow.source.git.") or k == f"{TAG}git_commit"}
        for key in stale - source.keys():  # the git tags of a checkout this code is not run from
            self.client.delete_tag(run_id, key)

    def start(self, name: str, tags: Mapping[str, str], parent_id: str | None = None) -> str:
        """A new run tagged ``tags`` over MLflow's context tags (:func:`source_tags`)."""
        all_tags = {**source_tags(), **{str(k): str(v) for k, v in tags.items()}}
        if parent_id:
            all_tags["mlflow.parentRunId"] = parent_id
        run = self.client.create_run(self.experiment_id, tags=all_tags, run_name=name)
        return run.info.run_id

    def log_params(self, run_id: str, params: Mapping[str, str]) -> None:
        """Log ``params`` on ``run_id``. A resumed run already holds its first job's parameters, and
        MLflow refuses to change one: a parameter the resuming job sets to another value (one outside
        the run key, such as the path of a package installed elsewhere) keeps its first value, and
        the new value goes to the tag ``demon_lab.resumed_param.<name>``."""
        from mlflow.entities import Param

        logged = self.client.get_run(run_id).data.params
        changed = {k: v for k, v in params.items() if k in logged and logged[k] != str(v)}
        self.set_tags(run_id, {f"{TAG}resumed_param.{k}": v for k, v in changed.items()})
        items = [Param(k, v) for k, v in params.items() if k not in logged]
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
        """FAILED, with the error as a tag and its traceback as the artifact ``error.txt``."""
        import traceback

        message = f"{type(error).__name__}: {error}"
        try:
            self.client.set_tag(run_id, f"{TAG}error", message[:5000])
            self.client.log_text(run_id, "".join(traceback.format_exception(error)), "error.txt")
        finally:
            self.client.set_terminated(run_id, status="FAILED")


@contextlib.contextmanager
def process_tracking_uri(uri: str | None = None) -> Iterator[None]:
    """MLflow's process-wide tracking URI is ``uri`` in the block (unchanged if None) and what it
    was afterwards, ``MLFLOW_TRACKING_URI`` included: ``mlflow.set_tracking_uri`` exports that
    variable, which every process started later inherits (Lightning's ``MLFlowLogger`` calls it,
    and ``mlflow.search_runs`` reads only the process-wide URI)."""
    import mlflow

    previous = mlflow.get_tracking_uri() if mlflow.is_tracking_uri_set() else None
    env = os.environ.get("MLFLOW_TRACKING_URI")
    if uri is not None:
        mlflow.set_tracking_uri(uri)
    try:
        yield
    finally:
        mlflow.set_tracking_uri(previous)
        if env is None:
            os.environ.pop("MLFLOW_TRACKING_URI", None)
        else:
            os.environ["MLFLOW_TRACKING_URI"] = env


@contextlib.contextmanager
def _store_lock(uri: str) -> Iterator[None]:
    """An exclusive file lock beside a SQLite store (``mlflow.db.lock``) while a process opens it:
    MLflow creates and migrates a fresh database on first use, and processes doing that at the same
    time corrupt each other's migrations. Other stores need no lock."""
    prefix = "sqlite:///"
    if not uri.startswith(prefix):
        yield
        return
    with FileLock(uri[len(prefix):] + ".lock"):  # (creates the folder)
        yield


def check_server(uri: str, timeout: float = 10.0) -> None:
    """Fail fast, before any work, if a tracking server does not answer its ``/health`` check
    (MLflow's own client would retry for minutes, then drop the job's results)."""
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=timeout) as response:
            if response.status == 200:
                return
            problem = f"HTTP {response.status}"
    except urllib.error.HTTPError as e:
        problem = f"HTTP {e.code}"
    except (urllib.error.URLError, OSError) as e:
        problem = str(getattr(e, "reason", e))
    raise TrackingError(f"tracking.uri {uri!r}: the tracking server does not answer ({problem}); start it or "
                        f"point tracking.uri elsewhere")


def _absolute_sqlite(uri: str) -> str:
    """sqlite:///relative.db -> an absolute path, so jobs in other directories share the store."""
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not uri[len(prefix):].startswith("/"):
        return prefix + str(Path(uri[len(prefix):]).resolve())
    return uri


class LocalServer:
    """``tracking=local_server``: an MLflow server on 127.0.0.1 (loopback only, never a public
    interface) in front of a SQLite store, for the duration of one command. Parallel jobs then
    send their metrics to one process instead of each opening the database; the server stops when
    the command ends (atexit, even when a job failed)."""

    def __init__(self, port: int, backend_store_uri: str, artifacts_destination: str, startup_timeout: float = 120.0):
        self.port = port
        self.store = _absolute_sqlite(backend_store_uri)
        self.artifacts = Path(artifacts_destination).resolve()
        self.startup_timeout = startup_timeout
        self.process: subprocess.Popen | None = None
        self.uri = f"http://127.0.0.1:{self.port}"

    def start(self) -> None:
        import atexit
        import socket
        import sys

        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", self.port)) == 0:
                raise TrackingError(f"tracking.server.port {self.port}: the port is in use on 127.0.0.1; "
                                    f"choose another (tracking.server.port=...)")
        with _store_lock(self.store):  # create the database before the server's workers race for it
            from mlflow.tracking import MlflowClient

            MlflowClient(tracking_uri=self.store).search_experiments(max_results=1)
        env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", "MLFLOW_DISABLE_TELEMETRY": "true"}
        command = [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port", str(self.port),
                   "--workers", "1", "--backend-store-uri", self.store,
                   "--artifacts-destination", str(self.artifacts)]
        self.process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                        text=True, start_new_session=True)
        atexit.register(self.stop)
        deadline = time.time() + self.startup_timeout
        while time.time() < deadline:
            if self.process.poll() is not None:
                tail = (self.process.stderr.read() if self.process.stderr else "").strip().splitlines()[-1:]
                raise TrackingError(f"tracking=local_server: the MLflow server exited ({' '.join(tail)[:200]})")
            try:
                check_server(self.uri, timeout=2.0)
                break
            except TrackingError:
                time.sleep(0.5)
        else:
            self.stop()
            raise TrackingError(f"tracking=local_server: the MLflow server did not answer on {self.uri} "
                                f"within {self.startup_timeout:.0f} s")
        log.info("MLflow server on %s (store %s); it stops with this command", self.uri, self.store)

    def stop(self) -> None:
        import signal

        if self.process is None:
            return
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        self.process = None
