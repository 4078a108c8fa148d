"""Which runs a report counts and what its cells hold: the runs of a study's experiments from
MLflow as one DataFrame, the newest FINISHED run per (table, row, seed) of the spec's design and this
checkout's versions, their metrics per cell, the seeds aggregated and the paired differences."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from demon_lab.pipeline.tracking import TAG, metric_name, process_tracking_uri

CELL_KEYS = ("table", "dataset", "row", "column")
"""What one cell of a report table is keyed by (the index of ``build(...)["cells"]``)."""
INFO_COLUMNS = ("run_id", "experiment_id", "status", "artifact_uri", "start_time", "end_time")
"""The columns ``mlflow.search_runs`` returns for every run (it returns only these when none match)."""


def _column(runs: pd.DataFrame, name: str) -> pd.Series:
    """A column of the runs frame, or all None where no run has it (search_runs only makes columns
    for the tags, params and metrics some run has)."""
    return runs[name] if name in runs.columns else pd.Series(None, index=runs.index, dtype=object)


def field(runs: pd.DataFrame, key: str) -> pd.Series:
    """Per run, the tag ``demon_lab.<key>`` or else the param ``key``; None/NaN where neither exists."""
    tag = _column(runs, f"tags.{TAG}{key}")
    return tag.where(tag.notna(), _column(runs, f"params.{key}"))


def fetch_runs(uri: str, experiments: Sequence[str]) -> pd.DataFrame:
    """Every top-level job run (not stage runs, nor a sweep's parent) of the named experiments, any
    status: ``mlflow.search_runs``'s frame plus ``experiment`` (its name) and ``seed`` (an int, 0
    where untagged), ordered by experiment (as named) and newest first."""
    import mlflow
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    found = {name: exp.experiment_id for name in experiments if (exp := client.get_experiment_by_name(name))}
    if found:  # (search_runs given no experiment that exists would search the Default one)
        with process_tracking_uri(uri):
            runs = mlflow.search_runs(experiment_names=list(found), output_format="pandas")
    else:
        runs = pd.DataFrame(columns=list(INFO_COLUMNS))
    runs = runs[_column(runs, f"tags.{TAG}run_key").notna() & _column(runs, f"tags.{TAG}kind").ne("stage")]
    order = {name: i for i, name in enumerate(experiments)}
    runs = runs.assign(experiment=runs["experiment_id"].map({v: k for k, v in found.items()}),
                       seed=pd.to_numeric(field(runs, "seed"), errors="coerce").fillna(0).astype(int))
    # lexsort over several keys is stable: runs started in the same millisecond keep the store's order
    runs = runs.assign(_order=runs["experiment"].map(order)).sort_values(["_order", "start_time"],
                                                                         ascending=[True, False])
    return runs.drop(columns="_order").reset_index(drop=True)


def _mask(runs: pd.DataFrame, match: Mapping[str, Any] | None) -> pd.Series:
    """The runs whose tags/params equal every value of a row's ``match`` (None matches "None" and a run
    that has no such tag or param: an option added after it ran, or one its run left out)."""
    mask = pd.Series(True, index=runs.index)
    for k, v in (match or {}).items():
        found = field(runs, k)
        mask &= (found.eq("None") | found.isna()) if v is None else found.eq(str(v))
    return mask


def current_versions(runs: pd.DataFrame, current: Mapping[str, str]) -> pd.Series:
    """The runs tagged with this checkout's code and generator versions (the others are stale)."""
    mask = pd.Series(True, index=runs.index)
    for k, v in current.items():
        mask &= _column(runs, f"tags.{k}").eq(v)
    return mask


def of_design(runs: pd.DataFrame, design: str | None) -> pd.Series:
    """The runs that measure the shipped ``design`` (a spec's ``design``, :data:`provenance.SHIPPED`;
    every run where None), and the classical methods' runs, which measure no design."""
    from demon_lab.reporting import provenance

    if design is None or runs.empty:
        return pd.Series(True, index=runs.index)
    found = runs.apply(lambda run: provenance.run_design(provenance.run_params(run)), axis=1)
    return found.isin([*provenance.SHIPPED[design], provenance.CLASSICAL])


def choose(spec: Mapping[str, Any], runs: pd.DataFrame) -> pd.DataFrame:
    """The runs each table row counts: per (table, row, seed) the newest FINISHED run of the table's
    experiment that matches the row and measures the spec's ``design``; the runs' columns plus
    ``table`` and ``row`` (its label)."""
    finished = runs[runs["status"] == "FINISHED"]
    finished = finished[of_design(finished, spec.get("design"))]
    candidates = [finished[(finished["experiment"] == table["experiment"]) & _mask(finished, row.get("match"))]
                  .assign(table=table["name"], row=row["label"])
                  for table in spec["tables"] for row in table["rows"]]
    if not candidates:
        return runs.head(0).assign(table=None, row=None)
    together = pd.concat(candidates, ignore_index=True)
    newest = together.sort_values("start_time", ascending=False, kind="stable")
    return newest.drop_duplicates(["table", "row", "seed"]).sort_values("seed", kind="stable")


def metric_key(dataset: str, prefix: str, column: str) -> str:
    return metric_name(f"test/{dataset}/{prefix + '/' if prefix else ''}{column}")


def long_values(spec: Mapping[str, Any], chosen: pd.DataFrame) -> pd.DataFrame:
    """The values the cells aggregate, one per (table, dataset, row, column, seed): each counted run's
    metric of the row's pass, finite values only (a pass without a pixel of positive depth logs none)."""
    wanted = pd.DataFrame(
        [(table["name"], dataset, row["label"], c, "metrics." + metric_key(dataset, row.get("metrics", ""), c))
         for table in spec["tables"] for row in table["rows"] for dataset in spec["datasets"]
         for c in table["columns"]], columns=[*CELL_KEYS, "metric"])
    present = [m for m in wanted["metric"].unique() if m in chosen.columns]
    if not present or chosen.empty:
        return pd.DataFrame(columns=[*CELL_KEYS, "seed", "value"])
    values = chosen.melt(id_vars=["table", "row", "seed"], value_vars=present, var_name="metric", value_name="value")
    long = wanted.merge(values, on=["table", "row", "metric"])
    long["value"] = long["value"].astype(float)
    return long[np.isfinite(long["value"])][[*CELL_KEYS, "seed", "value"]].reset_index(drop=True)


def aggregate(values: pd.DataFrame, by: Sequence[str] = CELL_KEYS) -> pd.DataFrame:
    """Per group of ``by``: mean, sample std, n, the values (by seed) and the half-width of the 95 %
    t-interval of the mean, t.ppf(0.975, n - 1) * std / sqrt(n) (NaN for n < 2)."""
    from scipy.stats import t

    ordered = values.sort_values("seed", kind="stable") if "seed" in values.columns else values
    # Series.mean/std (numpy's sums, two-pass variance) rather than the groupby's own "mean"/"std",
    # whose compensated sums and running variance change the CSV's numbers in their last digit.
    cells = ordered.groupby(list(by))["value"].agg(mean=pd.Series.mean, std=pd.Series.std, n="count", values=list)
    n = cells["n"]
    cells["ci95"] = t.ppf(0.975, (n - 1).where(n > 1)) * cells["std"] / np.sqrt(n)
    return cells


def differences(spec: Mapping[str, Any], values: pd.DataFrame) -> pd.DataFrame:
    """The values of each table's ``differences`` (``{label, rows: [a, b]}``): per test set, column
    and seed, row ``a``'s value minus row ``b``'s, where both rows have that seed (a paired
    difference: the same seed's chain trained and untrained, say), aggregated like any row. What one
    row adds to another is then a measured difference with its own interval."""
    keys = ["dataset", "column", "seed"]
    out = []
    for table in spec["tables"]:
        mine = values[values["table"] == table["name"]]
        for d in table.get("differences", []):
            a, b = (mine[mine["row"] == r].set_index(keys)["value"] for r in d["rows"])
            diff = (a - b).dropna().rename("value").reset_index()
            out.append(diff.assign(table=table["name"], row=d["label"]))
    if not out:
        return values.head(0)
    return pd.concat(out, ignore_index=True)[[*CELL_KEYS, "seed", "value"]]


def build(spec: Mapping[str, Any], runs: pd.DataFrame) -> dict[str, Any]:
    """``cells``: the aggregate per (table, dataset, row, column); ``used``: the runs counted (one
    row per table row and seed); ``missing``: the (row, seed)s without a FINISHED run."""
    seeds = [int(s) for s in spec.get("seeds", [])]
    chosen = choose(spec, runs)
    missing: list[str] = []
    for table in spec["tables"]:
        for row in table["rows"]:
            have = set(chosen["seed"][(chosen["table"] == table["name"]) & (chosen["row"] == row["label"])])
            absent = [s for s in seeds if s not in have]
            if absent:
                missing.append(f"{table['name']} / {row['label']}: no FINISHED run for seed(s) "
                               f"{', '.join(map(str, absent))}")
    values = long_values(spec, chosen)
    return {"cells": aggregate(pd.concat([values, differences(spec, values)], ignore_index=True)), "used": chosen,
            "missing": missing}


def superseded(failed: pd.DataFrame, spec: Mapping[str, Any], runs: pd.DataFrame, used: pd.DataFrame) -> pd.Series:
    """Per FAILED run: whether its job was re-run to FINISHED (same run key), or its row and seed
    have a newer FINISHED run in a table (a later attempt, e.g. after a code change)."""
    rerun = field(failed, "run_key").isin(set(field(runs[runs["status"] == "FINISHED"], "run_key").dropna()))
    for table in spec["tables"]:
        for row in table["rows"]:
            counted = used[(used["table"] == table["name"]) & (used["row"] == row["label"])]
            mine = (failed["experiment"] == table["experiment"]) & _mask(failed, row.get("match"))
            if counted.empty or not mine.any():
                continue
            newest = failed["seed"].map(counted.set_index("seed")["start_time"])  # NaT: no run of that seed
            rerun |= mine & newest.notna() & (newest > failed["start_time"])
    return rerun


def run_value(run: pd.Series, key: str) -> str | None:
    """One run's tag ``demon_lab.<key>`` or else param ``key`` (None if neither)."""
    for name in (f"tags.{TAG}{key}", f"params.{key}"):
        value = run.get(name)
        if isinstance(value, str):
            return value
    return None
