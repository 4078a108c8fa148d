"""Helpers of the report tests: a store of fake runs, the versions' tags, a study spec in a folder."""

from __future__ import annotations

from pathlib import Path

import yaml

from demon_lab.pipeline import tracking
from demon_lab.pipeline.tracking import TAG, Tracker
from demon_lab.reporting import report

ROOT = Path(__file__).resolve().parents[1]


def _fake_store(tmp: Path) -> str:
    """Runs with known metrics, logged through demon_lab's tracking layer: 3 seeds of one row,
    2 of another, a FAILED run and an older duplicate that must be superseded."""
    uri = f"sqlite:///{tmp}/mlflow.db"
    tracker = Tracker(uri, "study", str(tmp / "artifacts"))

    def add(row: str, seed: int, value: float, status: str = "FINISHED", **versions):
        run = tracker.start(f"{row}-{seed}", {f"{TAG}run_key": f"{row}{seed}", f"{TAG}row": row,
                                              f"{TAG}seed": str(seed), **version_tags(**versions)})
        tracker.log_metrics(run, {"test/setA/it0/l1_inv": value, "test/setA/it0/tran_deg": 10 * value})
        if status == "FINISHED":
            tracker.finish(run, "FINISHED")
        else:
            tracker.fail(run, RuntimeError("NaN loss at step 7"))

    add("a", 0, 99.0)  # superseded by the newer seed-0 run below
    for seed, value in enumerate([1.0, 2.0, 3.0]):
        add("a", seed, value)
    for seed, value in enumerate([10.0, 14.0]):
        add("b", seed, value)
    add("b", 2, 0.0, status="FAILED")
    add("a", 2, 555.0, generator_version="3")  # newest, but of another scene generator: stale
    add("b", 2, 777.0, code_version=None)  # a run from before runs were tagged with versions: stale
    old = tracker.start("a-1-old", {f"{TAG}run_key": "a1-old", f"{TAG}row": "a", f"{TAG}seed": "1",
                                    **version_tags()})
    tracker.fail(old, RuntimeError("killed"))  # an attempt of row a, seed 1 under another run key...
    run = tracker.start("a-1-again", {f"{TAG}run_key": "a1-again", f"{TAG}row": "a", f"{TAG}seed": "1",
                                      **version_tags()})
    tracker.log_metrics(run, {"test/setA/it0/l1_inv": 2.0, "test/setA/it0/tran_deg": 20.0})
    tracker.finish(run, "FINISHED")  # ...superseded by this newer FINISHED run (same value as before)
    return uri


def version_tags(**changed: str | None) -> dict[str, str]:
    """This checkout's version tags, with some changed (None: left out)."""
    tags = {**tracking.version_tags(), **{f"{TAG}{k}": v for k, v in changed.items()}}
    return {k: v for k, v in tags.items() if v is not None}


def _spec(directory: Path, **extra) -> None:
    (directory / "paper_numbers.csv").write_text((report.STUDIES / "paper_numbers.csv").read_text())
    spec = {**extra, "title": "A study", "runs": [["+experiment=study"]], "seeds": [0, 1, 2],
            "datasets": {"setA": "SUN3D"},
            "tables": [{"name": "t", "caption": "cap", "experiment": "study", "columns": ["l1_inv", "tran_deg"],
                        "rows": [{"label": "row a", "match": {"row": "a"}, "metrics": "it0",
                                  "paper": {"table": "2", "method": "depth-motion net", "rows": ["no GT"]}},
                                 {"label": "row b", "match": {"row": "b"}, "metrics": "it0"}]}]}
    (directory / "study.yaml").write_text(yaml.safe_dump(spec))
