"""Run archives: a study's tracked runs as one file, to move between MLflow stores.

A study trained on a cluster is reported on a laptop, and one whose seeds were trained on different
machines or days is reported as one: ``python -m demon_lab.report NAME --export FILE`` writes the
runs of the study's experiments, and ``python -m demon_lab.report --import FILE`` adds them to
another store (docs/running.md, "Run archives"; docs/guides/archives.md).

An archive is a zip file: ``runs.json`` (per run: its experiment's name, run name, status, start and
end times, tags, params and every metric's full history with steps and timestamps) and
``artifacts/<run id>/...`` (the run's artifacts but its point clouds and a sweep's report, which no report
reads, and, with ``images=False``, but its depth panels: what the tables and histograms read stays). It holds
the FINISHED, FAILED and KILLED runs of the named experiments, every stage run among them included, and
the stage runs of other experiments whose trained stages a job of them read from the stage cache
(a job's ``stage_keys.json``), so the figures that read a stage's curves find them; such a stage run
carries the figures its own job logged of it (its time, the nets it kept). Unfinished runs are
left out: they are resumable only beside the stage cache they checkpoint into.

Importing keeps each run's times, tags and histories; the run gets a new id in the store and the tag
``demon_lab.imported_from`` with the id it was first tracked under, a child run's
``mlflow.parentRunId`` points at its parent's new id (or, while the parent is in no store the import
has seen, ``demon_lab.imported_parent`` names it, and the import that brings the parent links them),
and a run already in the store (same id, or imported before, from any archive) is skipped, so
importing twice, or an archive that went round two stores, adds nothing. A run gets its run key and
``imported_from`` last, just before it ends: an import stopped half-way leaves a RUNNING run that no
job resumes and no report reads, and the next import brings that run again. A job finds an imported
FINISHED run of its run key and skips, as it would its own.
"""

from __future__ import annotations

import json
import tempfile
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from demon_lab.pipeline.tracking import TAG, Tracker, _quiet_mlflow

IMPORTED_FROM = f"{TAG}imported_from"
IMPORTED_PARENT = f"{TAG}imported_parent"
RUN_KEY = f"{TAG}run_key"
PARENT = "mlflow.parentRunId"
ENDED = ("FINISHED", "FAILED", "KILLED")
LEFT_OUT = ("point_clouds", "report")
"""Artifact folders an archive leaves out: 3-D viewer files and the report a sweep logs on its parent run
(large, and no report reads them)."""
IMAGES = "images"
"""The depth panels of a job (the qualitative figures read them): ``images=False`` leaves them out."""
BATCH_METRICS, BATCH_PARAMS = 1000, 100  # MLflow's limits per log_batch call


def _client(uri: str):
    _quiet_mlflow()
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=uri)


def _experiments(client) -> dict[str, str]:
    """Every experiment of the store: id -> name, page by page."""
    found, token = {}, None
    while True:
        page = client.search_experiments(max_results=1000, page_token=token)
        found.update({e.experiment_id: e.name for e in page})
        token = page.token
        if not token:
            return found


def _search(client, experiment_ids: Sequence[str], query: str = "") -> Iterator[Any]:
    """Every run of the experiments that matches ``query``, page by page."""
    token = None
    while experiment_ids:
        page = client.search_runs(list(experiment_ids), filter_string=query, max_results=1000, page_token=token)
        yield from page
        token = page.token
        if not token:
            return


def _record(client, run, experiment: str) -> dict[str, Any]:
    metrics = {key: [[m.step, m.timestamp, m.value] for m in client.get_metric_history(run.info.run_id, key)]
               for key in run.data.metrics}
    return {"run_id": run.info.run_id, "experiment": experiment, "name": run.info.run_name,
            "status": run.info.status, "start_time": run.info.start_time, "end_time": run.info.end_time,
            "tags": dict(run.data.tags), "params": dict(run.data.params), "metrics": metrics}


def _carry_job_figures(client, record: dict[str, Any], exported: Mapping[str, Any]) -> None:
    """A stage run whose job stays out of the archive (a job of another experiment, whose stage a job
    of the study read from the cache) takes along the figures that job logged of its stage
    (``stage/<stage>/...`` there, ``stage/...`` here, as stage runs log them themselves since they carry
    them): its time and which nets it kept, which the time-to-accuracy report reads."""
    from mlflow.exceptions import MlflowException

    tags, metrics = record["tags"], record["metrics"]
    parent = tags.get(PARENT)
    if tags.get(f"{TAG}kind") != "stage" or parent is None or parent in exported or "stage/seconds" in metrics:
        return
    try:
        job = client.get_run(parent)
    except MlflowException:
        return  # (deleted from the store)
    prefix = f"stage/{tags.get(f'{TAG}stage')}/"
    for key in job.data.metrics:
        if key.startswith(prefix):
            metrics["stage/" + key.removeprefix(prefix)] = [[m.step, m.timestamp, m.value]
                                                          for m in client.get_metric_history(parent, key)]


def _stage_keys(client, run_id: str, into: Path) -> list[str]:
    """The stage keys a job read or trained (its ``stage_keys.json``), or none."""
    from mlflow.exceptions import MlflowException

    if not any(item.path == "stage_keys.json" for item in client.list_artifacts(run_id)):
        return []  # a baseline, a stage run, a sweep
    try:
        path = client.download_artifacts(run_id, "stage_keys.json", str(into))
    except (OSError, MlflowException) as e:
        raise OSError(f"run {run_id}: cannot read its stage_keys.json ({e})") from None
    return [entry["key"] for entry in json.loads(Path(path).read_text()).values() if entry.get("key")]


def export_runs(uri: str, experiments: Sequence[str], path: Path, images: bool = True) -> int:
    """Writes the archive of ``experiments``' ended runs (and the stage runs they read) to ``path``,
    with each job's depth panels if ``images``; returns the number of runs written."""
    left_out = LEFT_OUT if images else (*LEFT_OUT, IMAGES)
    client = _client(uri)
    names = _experiments(client)
    wanted = [i for i, name in names.items() if name in experiments]
    runs = {r.info.run_id: r for r in _search(client, wanted) if r.info.status in ENDED}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="demon_lab_archive_") as tmp:
        keys = {k for run_id in list(runs) for k in _stage_keys(client, run_id, Path(tmp) / "keys" / run_id)}
        for key in sorted(keys):
            for run in _search(client, list(names), f"tags.`{TAG}stage_key` = '{key}'"):
                if run.info.status in ENDED:
                    runs.setdefault(run.info.run_id, run)
        records = [_record(client, run, names[run.info.experiment_id])
                   for run in sorted(runs.values(), key=lambda r: (r.info.start_time, r.info.run_id))]
        for record in records:
            _carry_job_figures(client, record, runs)
        with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            archive.comment = " ".join(sorted(experiments)).encode()  # what archived_experiments reads
            archive.writestr("runs.json", json.dumps(records, indent=1, sort_keys=True) + "\n")
            for run_id in runs:
                local = Path(tmp) / "artifacts" / run_id
                local.mkdir(parents=True)
                for item in client.list_artifacts(run_id):
                    if item.path not in left_out:
                        client.download_artifacts(run_id, item.path, str(local))
                for file in sorted(p for p in local.rglob("*") if p.is_file()):
                    archive.write(file, f"artifacts/{run_id}/{file.relative_to(local).as_posix()}")
    return len(records)


def archived_experiments(path: Path) -> set[str]:
    """The experiments whose job runs an archive holds: its comment (written by :func:`export_runs`),
    or the experiment of each run in its ``runs.json`` but the stage runs of other experiments that
    came with them; nothing if the file is not an archive."""
    try:
        with zipfile.ZipFile(path) as archive:
            if archive.comment:
                return set(archive.comment.decode().split())
            records = json.loads(archive.read("runs.json"))
            return {r["experiment"] for r in records if r["tags"].get(f"{TAG}kind") != "stage"}
    except (zipfile.BadZipFile, KeyError, ValueError):
        return set()


def _parents_first(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    ids = {r["run_id"]: r for r in records}

    def depth(record: dict[str, Any]) -> int:
        parent = record["tags"].get(PARENT)
        return 0 if parent not in ids else 1 + depth(ids[parent])

    return sorted(records, key=lambda r: (depth(r), r["start_time"] or 0, r["run_id"]))


def import_runs(uri: str, path: Path, artifact_dir: str | Path = "mlartifacts") -> tuple[int, int]:
    """Adds the archive's runs to the store at ``uri`` (artifacts of a local store under
    ``artifact_dir``, as the jobs' own); returns (runs imported, runs already there)."""
    from mlflow.entities import Metric, Param

    with zipfile.ZipFile(path) as archive, tempfile.TemporaryDirectory(prefix="demon_lab_import_") as tmp:
        records = _parents_first(json.loads(archive.read("runs.json")))
        client = _client(uri)
        present: dict[str, str] = {}  # an id a run was tracked under (here or in an archive) -> its id here
        for run in _search(client, list(_experiments(client))):
            present[run.info.run_id] = run.info.run_id
            if IMPORTED_FROM in run.data.tags:
                present[run.data.tags[IMPORTED_FROM]] = run.info.run_id
        experiments: dict[str, str] = {}
        imported = 0
        for record in records:
            old, tags = record["run_id"], dict(record["tags"])
            origin = tags.pop(IMPORTED_FROM, old)
            if old in present or origin in present:
                present.setdefault(old, present.get(origin, present.get(old)))
                continue
            if record["experiment"] not in experiments:
                experiments[record["experiment"]] = Tracker(uri, record["experiment"], artifact_dir).experiment_id
            last = {IMPORTED_FROM: origin, **({RUN_KEY: tags.pop(RUN_KEY)} if RUN_KEY in tags else {})}
            parent = tags.pop(PARENT, None) or tags.get(IMPORTED_PARENT)
            tags.pop("mlflow.runName", None)
            tags.pop(IMPORTED_PARENT, None)
            if parent in present:
                tags[PARENT] = present[parent]
            elif parent:
                tags[IMPORTED_PARENT] = parent
            run_id = client.create_run(experiments[record["experiment"]], start_time=record["start_time"],
                                       tags=tags, run_name=record["name"]).info.run_id
            params = [Param(k, v) for k, v in record["params"].items()]
            metrics = [Metric(key, value, timestamp, step) for key, history in record["metrics"].items()
                       for step, timestamp, value in history]
            for i in range(0, len(params), BATCH_PARAMS):
                client.log_batch(run_id, params=params[i:i + BATCH_PARAMS])
            for i in range(0, len(metrics), BATCH_METRICS):
                client.log_batch(run_id, metrics=metrics[i:i + BATCH_METRICS])
            prefix = f"artifacts/{old}/"
            members = [m for m in archive.namelist() if m.startswith(prefix)]
            if members:
                archive.extractall(tmp, members)
                client.log_artifacts(run_id, str(Path(tmp) / prefix))
            for key, value in last.items():
                client.set_tag(run_id, key, value)
            client.set_terminated(run_id, status=record["status"], end_time=record["end_time"])
            present[old] = present[origin] = run_id
            imported += 1
        for run in _search(client, list(_experiments(client)), f"tags.`{IMPORTED_PARENT}` != ''"):
            if PARENT not in run.data.tags and run.data.tags[IMPORTED_PARENT] in present:
                client.set_tag(run.info.run_id, PARENT, present[run.data.tags[IMPORTED_PARENT]])
                client.delete_tag(run.info.run_id, IMPORTED_PARENT)
        return imported, len(records) - imported
