"""The held-apart curves a report draws: a stage's runs joined across a resume, the stage runs of a job,
the kept nets."""

from __future__ import annotations

import json

import pytest


class _Metric:
    def __init__(self, timestamp, step, value):
        self.timestamp, self.step, self.value = timestamp, step, value


class _Run:
    def __init__(self, run_id, start_minute, metrics=None, tags=None, status="FINISHED", experiment="e"):
        from types import SimpleNamespace

        self.info = SimpleNamespace(run_id=run_id, start_time=start_minute * 60000, status=status,
                                    experiment_id=experiment)
        self.data = SimpleNamespace(metrics=metrics or {}, tags=tags or {})


class _Client:
    """The calls of MlflowClient the held-apart curves make, over in-memory runs (histories in minutes)."""

    def __init__(self, histories, runs=()):
        self.histories, self.runs = histories, {r.info.run_id: r for r in runs}

    def get_metric_history(self, run_id, key):
        return [_Metric(t * 60000, s, v) for t, s, v in self.histories.get((run_id, key), [])]

    def get_run(self, run_id):
        from mlflow.exceptions import MlflowException

        if run_id not in self.runs:
            raise MlflowException(f"Run '{run_id}' not found")
        return self.runs[run_id]

    def search_experiments(self):
        from types import SimpleNamespace

        return [SimpleNamespace(experiment_id=e) for e in sorted({r.info.experiment_id for r in self.runs.values()})]

    def search_runs(self, experiments, filter_string, order_by=None):
        import re

        wanted = dict(re.findall(r"tags\.`([^`]+)` = '([^']*)'", filter_string))
        found = [r for r in self.runs.values() if r.info.experiment_id in experiments
                 and all(r.data.tags.get(k) == v for k, v in wanted.items())]
        return sorted(found, key=lambda r: r.info.start_time)


def test_a_resumed_stages_curve_joins_its_runs_and_a_retrained_one_starts_again():
    """A stage stopped at step 300 and resumed from its step-200 checkpoint in a new run: the resumed
    run's points follow the first run's last point before step 250 (its first), the steps trained again
    and the pause between the runs not counted; a run that starts at the first step again replaces them."""
    from demon_lab.reporting.figures import _joined_curve

    first, resumed = _Run("a", 0), _Run("b", 100)  # the second run starts 100 minutes later
    key, zero = "val/s/epe", "val/s/zero_flow_epe"
    client = _Client({("a", key): [(1, 100, 0.9), (2, 200, 0.8), (3, 300, 0.7)], ("a", zero): [(1, 100, 2.0)],
                      ("b", key): [(101, 250, 0.6), (102, 350, 0.5)], ("b", zero): [(101, 250, 2.0)]})
    curve = _joined_curve(client, [first, resumed], key, zero)
    assert curve["steps"] == [100, 200, 250, 350]
    assert curve["values"] == pytest.approx([0.45, 0.4, 0.3, 0.25])
    assert curve["minutes"] == pytest.approx([1, 2, 3, 4])
    assert curve["runs"] == [first, resumed]
    again = _Run("c", 200)
    client.histories[("c", key)] = [(201, 100, 0.95)]
    client.histories[("c", zero)] = [(201, 100, 1.0)]
    assert _joined_curve(client, [first, resumed, again], key, zero) == {
        "minutes": [pytest.approx(1.0)], "steps": [100], "values": [pytest.approx(0.95)], "runs": [again]}
    empty = _Run("d", 300)  # a run that logged no point (stopped before its first scoring) adds nothing
    assert _joined_curve(client, [first, resumed, empty], key, zero)["runs"] == [first, resumed]
    assert _joined_curve(client, [first], "val/s/tran_deg", None) is None


def test_a_stage_resumed_in_its_own_run_is_cut_where_its_steps_start_again():
    """A job stopped unawares and run again resumes its stage's own run: the run's history logs steps
    250 and 300 again. The curve drops the first process's points from step 250 on, and the second
    process's minutes start where its training loss starts again (minute 50), not at the run's start."""
    from demon_lab.reporting.figures import _joined_curve

    run = _Run("a", 0)
    key = "val/s/tran_deg"
    client = _Client({("a", key): [(1, 100, 90.0), (2, 200, 80.0), (3, 300, 75.0), (52, 250, 70.0), (53, 350, 60.0)],
                      ("a", "train/loss"): [(0.5, 50, 1.0), (2.5, 250, 0.8), (50, 200, 0.9), (52.5, 300, 0.7)]})
    curve = _joined_curve(client, [run], key, None)
    assert curve["steps"] == [100, 200, 250, 350]
    assert curve["values"] == [90.0, 80.0, 70.0, 60.0]
    assert curve["minutes"] == pytest.approx([1, 2, 4, 5])  # 2 + (52 - 50), 2 + (53 - 50)


def test_a_jobs_stage_runs_are_those_of_its_stage_before_it_read_the_stage(tmp_path, monkeypatch):
    """The runs of a job's stage key: up to its own child run (an earlier stopped run of the same key
    included), or, for a stage found in the cache, those started before the job; a run of the key
    trained again later for another job, and a RUNNING one (stopped unawares), are left out."""
    from demon_lab.reporting import figures

    def stage(run_id, minute, parent, status="FINISHED"):
        return _Run(run_id, minute, tags={"demon_lab.stage": "flow1", "demon_lab.stage_key": "k",
                                          "mlflow.parentRunId": parent}, status=status)

    stopped, own, running, later = (stage("s0", 0, "j0", "FAILED"), stage("s1", 10, "j1"),
                                    stage("s3", 5, "j5", "RUNNING"), stage("s2", 90, "j9"))
    client = _Client({}, [stopped, own, running, later])
    assert figures.stage_runs(client, {"run_id": "j1", "experiment_id": "e"}) == [stopped, own]
    (tmp_path / "stage_keys.json").write_text(json.dumps({"flow1": {"key": "k"}}))  # a job that found it cached
    monkeypatch.setattr(figures, "local_artifact", lambda run, path: tmp_path / path)
    cached = {"run_id": "j2", "experiment_id": "e", "start_time": 50 * 60000}
    assert figures.stage_runs(client, cached) == [stopped, own]
    assert figures.stage_runs(client, {**cached, "start_time": None}) == [stopped, own, later]  # (no start known)


def test_the_kept_nets_are_read_from_the_stage_run_else_from_the_job_that_trained_it():
    from demon_lab.reporting.figures import _kept

    tags = {"demon_lab.stage": "dm1", "mlflow.parentRunId": "job"}
    client = _Client({}, [_Run("job", 0, {"stage/dm1/keep_best_step": 2250.0})])
    assert _kept(client, _Run("s", 0, {"stage/seconds": 9.0, "stage/keep_best_step": 3500.0}, tags)) == "step 3,500"
    assert _kept(client, _Run("s", 0, {"stage/seconds": 9.0}, tags)) == "last"
    assert _kept(client, _Run("s", 0, {}, tags)) == "step 2,250"  # a stage run logged before it carried its figures
    client.runs["job"] = _Run("job", 0, {}, status="FINISHED")
    assert _kept(client, _Run("s", 0, {}, tags)) == "last"
    client.runs["job"] = _Run("job", 0, {}, status="FAILED")
    assert _kept(client, _Run("s", 0, {}, tags)) == "not logged"
    del client.runs["job"]  # (removed from the store)
    assert _kept(client, _Run("s", 0, {}, tags)) == "not logged"
