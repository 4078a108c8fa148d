"""``python -m demon_lab.report NAME [--all] [--run]``: paper-style tables and figures from MLflow.

A study spec (``ablations/NAME.yaml``, named after its experiment) names the runs
(``runs``: the override lists of ``python -m demon_lab -m`` commands), the seeds expected, the test
sets (each mapped to the paper's dataset whose numbers stand beside it) and tables whose rows
select runs by tag or param (``match``) and read one pass's metrics (``metrics``: ``it<k>``,
``refined`` or ``""`` for the summary). The report reads FINISHED runs of this checkout's code and
scene-generator versions only (older ones are stale: counted and named, not used), keeps the newest
run per (row, seed), aggregates seeds (mean, sample std, 95 % t-interval, n) and writes
``reports/NAME.md``, ``.csv``, ``.tex`` and ``reports/figures/NAME_*.png``. FAILED runs (unless
their job, or their row and seed, has a newer FINISHED run) and seeds without a run are listed.

``--run`` first executes the spec's commands (skip-if-finished makes that incremental), each with
the ``--override KEY=VALUE`` options added; a spec's ``requires`` (``KEY: PLACEHOLDER``) names the
keys a user must pass so (a study on files the user supplies: ``released_model``).
:func:`publish` logs a study's report as artifacts of a run (a sweep's parent run).
``--import FILE`` first adds a run archive's runs to the store and ``--export FILE`` writes the named
studies' runs to one (:mod:`demon_lab.reporting.archive`).

The runs come from ``mlflow.search_runs`` as one DataFrame (``run_id``, ``status``,
``start_time``, ``artifact_uri``, ``tags.*``, ``params.*``, ``metrics.*``); rows are picked by
boolean masks on it and the seeds of a cell are aggregated with ``groupby``.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from demon_lab.core.metrics import UNITS_NOTE, column
from demon_lab.pipeline.tracking import TAG, metric_name, process_tracking_uri, version_tags
from demon_lab.reporting.tables import Cell, cell, has_values, paper_cells
from demon_lab.resources import STUDIES

FIGURES = ("iterations", "pixel_histograms", "motion_distributions", "qualitative", "time_to_accuracy")
CELL_KEYS = ("table", "dataset", "row", "column")
"""What one cell of a report table is keyed by (the index of ``build(...)["cells"]``)."""
INFO_COLUMNS = ("run_id", "experiment_id", "status", "artifact_uri", "start_time", "end_time")
"""The columns ``mlflow.search_runs`` returns for every run (it returns only these when none match)."""


class ReportError(ValueError):
    """A spec that cannot be read or does not fit the report's format."""


def _shown(name: str, directory: Path) -> str:
    """How messages name a spec file: ``ablations/NAME.yaml`` for the shipped ones."""
    return f"ablations/{name}.yaml" if Path(directory) == STUDIES else str(Path(directory) / f"{name}.yaml")


def study_of(experiment: str, directory: Path = STUDIES, design: str | None = None) -> str | None:
    """The study whose spec reports ``experiment``: with ``design`` (a short name of
    :data:`provenance.SHIPPED`), the first spec (by name, its own first) with a table of that
    experiment and that ``design``; else, or where none has it, its own spec (same name), else the
    first spec (by name) with a table of that experiment; None if no spec reports it. A spec that
    does not parse is passed over (``load_spec`` names its problem when it is reported)."""
    directory = Path(directory)
    names = sorted(p.stem for p in directory.glob("*.yaml"))
    if design is not None:
        for name in sorted(names, key=lambda n: n != experiment):
            try:
                spec = load_spec(name, directory)
            except (ReportError, yaml.YAMLError, KeyError, TypeError):
                continue
            if spec.get("design") == design and any(t.get("experiment") == experiment for t in spec["tables"]):
                return name
    if experiment in names:
        return experiment
    for name in names:
        try:
            spec = yaml.safe_load((directory / f"{name}.yaml").read_text()) or {}
        except yaml.YAMLError:
            continue
        tables = spec.get("tables") if isinstance(spec, Mapping) else None
        if any(isinstance(t, Mapping) and t.get("experiment") == experiment for t in tables or []):
            return name
    return None


def _read(name: str, directory: Path) -> dict[str, Any]:
    """A spec file as written, with its ``extends`` applied: the named spec's keys, then this one's
    (``drop_rows``: the inherited rows it leaves out, with the differences that read them)."""
    path = directory / f"{name}.yaml"
    if not path.is_file():
        owner = study_of(name, directory)
        if owner is not None:
            raise ReportError(f"{name} is reported by the study {owner}: python -m demon_lab.report {owner}")
        known = ", ".join(sorted(p.stem for p in directory.glob("*.yaml")))
        raise ReportError(f"study spec {name!r}: no {_shown(name, directory)}; known: {known}")
    spec = yaml.safe_load(path.read_text()) or {}
    base = spec.pop("extends", None)
    if base is None:
        return spec
    if base == name:
        raise ReportError(f"{_shown(name, directory)}: extends itself")
    dropped = set(spec.pop("drop_rows", None) or [])
    spec = {**_read(base, directory), **spec}
    tables = []
    for table in spec.get("tables", []):
        rows = [r for r in table["rows"] if r["label"] not in dropped]
        kept = [d for d in table.get("differences", []) if not set(d.get("rows", [])) & dropped]
        tables.append({**table, "rows": rows, **({"differences": kept} if "differences" in table else {})})
    return {**spec, "tables": tables}


def load_spec(name: str, directory: Path = STUDIES) -> dict[str, Any]:
    from demon_lab.reporting.provenance import SHIPPED

    directory = Path(directory)
    spec = _read(name, directory)
    for key in ("title", "tables", "datasets"):
        if key not in spec:
            raise ReportError(f"{_shown(name, directory)}: missing key {key!r}")
    if not isinstance(spec.get("requires") or {}, dict):
        raise ReportError(f"{_shown(name, directory)}: requires: expected KEY: PLACEHOLDER pairs")
    design = spec.get("design")
    if design is not None and design not in SHIPPED:
        raise ReportError(f"{_shown(name, directory)}: design: expected one of {sorted(SHIPPED)}, got {design!r}")
    if design not in (None, "profile"):  # the profile is the cpu scale's own design: no override
        spec["runs"] = [[*overrides, f"design={design}"] for overrides in spec.get("runs", [])]
    for table in spec["tables"]:
        labels = {row["label"] for row in table["rows"]}
        for d in table.get("differences", []):
            if len(d.get("rows", [])) != 2 or not set(d["rows"]) <= labels:
                raise ReportError(f"{_shown(name, directory)}: table {table['name']}: difference {d.get('label')!r}: "
                                  f"expected rows: [A, B], two of the table's row labels")
    for figure in spec.get("figures", []):
        if figure not in FIGURES:
            raise ReportError(f"{_shown(name, directory)}: figures: expected some of {FIGURES}, got {figure!r}")
    spec["name"] = name
    return spec


def paper_numbers(path: Path = STUDIES / "paper_numbers.csv") -> list[dict[str, str]]:
    # Kept as text rows (csv): pandas would turn the table numbers ("2") and empty cells into numbers
    # and NaN, and paper_cells compares and reads them as the CSV spells them.
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ----------------------------------------------------------------------------- runs


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
    """The runs whose tags/params equal every value of a row's ``match`` (None matches "None")."""
    mask = pd.Series(True, index=runs.index)
    for k, v in (match or {}).items():
        mask &= field(runs, k).eq("None" if v is None else str(v))
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


def _superseded(failed: pd.DataFrame, spec: Mapping[str, Any], runs: pd.DataFrame, used: pd.DataFrame) -> pd.Series:
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


def _get(run: pd.Series, key: str) -> str | None:
    """One run's tag ``demon_lab.<key>`` or else param ``key`` (None if neither)."""
    for name in (f"tags.{TAG}{key}", f"params.{key}"):
        value = run.get(name)
        if isinstance(value, str):
            return value
    return None


def _fmt(v: float, digits: int = 3) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.{digits}f}" if abs(v) < 1000 else f"{v:.0f}"


def _describe(spec: Mapping[str, Any], used: pd.DataFrame) -> dict[str, Any]:
    chosen = used.drop_duplicates("run_id")

    def values(key: str) -> list[str]:
        v = field(chosen, key)
        return sorted(set(v.where(v.notna() & v.ne(""), "?")))

    seeds = field(chosen, "seed")
    needed = [f"{k}={v}" for k, v in (spec.get("requires") or {}).items()]
    commands = [f"python -m demon_lab -m {' '.join([*overrides, *needed])}" for overrides in spec.get("runs", [])]
    return {"scale": ", ".join(values("scale")) or "-", "data": ", ".join(values("data")) or "-",
            "seeds": ", ".join(sorted(set(seeds.where(seeds.notna() & seeds.ne(""), "0")), key=int)) or "-",
            "runs": str(len(chosen)), "commands": commands}


def _cell_text(cell: Cell, row_n: int, pm: str, fewer: str) -> str:
    """Mean, ``pm`` and the CI half-width (with 2+ seeds), and ``fewer`` (a format with the cell's
    n) when fewer seeds than the row's logged a finite value here (say, no pixel of positive depth)."""
    text = _fmt(cell.mean) + (f"{pm}{_fmt(cell.ci95)}" if cell.n > 1 else "")
    return text + (fewer.format(cell.n) if 0 < cell.n < row_n else "")


def _row_cells(result, table, dataset, row) -> dict[str, Cell]:
    return {c: cell(result, table["name"], dataset, row["label"], c) for c in table["columns"]}


def write_markdown(spec, result, info, failed: pd.DataFrame, paper_rows) -> str:
    out = io.StringIO()
    w = out.write
    w(f"# {spec['title']}\n\n")
    report_cmd = spec.get("command") or f"python -m demon_lab.report {spec['name']}"
    w(f"Generated by `{report_cmd}` from the FINISHED runs in the MLflow store.\n\n")
    w(f"- scale: {info['scale']}; data: {info['data']}; seeds: {info['seeds']}; runs used: {info['runs']}\n")
    designs = "; ".join(dict.fromkeys(e["design"] for e in result.get("provenance", []))) or "-"
    w(f"- design: {designs} (per row, with the code and the runs: Provenance, below)\n")
    if info["commands"]:
        w("- reproduce: " + "; ".join(f"`{c}`" for c in info["commands"]) + f"; then `{report_cmd}`"
          + f" (or both at once: `{report_cmd} --run`)\n")
    w("- cells: mean ± 95 % confidence half-width (t-interval over seeds), n = seeds (a cell marked "
      "(n = k) has fewer: the other seeds' runs logged no finite value there, e.g. no pixel of positive "
      f"depth); {UNITS_NOTE}\n")
    if spec.get("paper_note"):
        w(f"- paper: {spec['paper_note']}\n")
    w("\n")
    for table in spec["tables"]:
        w(f"## {table['caption']}\n\n")
        for dataset, paper_dataset in spec["datasets"].items():
            if not has_values(result, table["name"], dataset):
                continue
            w(f"### {dataset}" + (f" (paper: {paper_dataset})" if paper_dataset else "") + "\n\n")
            header = ["row", "n", *[column(c).label for c in table["columns"]]]
            w("| " + " | ".join(header) + " |\n|" + "---|" * len(header) + "\n")
            for row in table["rows"]:
                entry = _row_cells(result, table, dataset, row)
                n = max((c.n for c in entry.values()), default=0)
                cells = [_cell_text(entry[c], n, " ± ", " (n = {})") for c in table["columns"]]
                w(f"| {row['label']} | {n} | " + " | ".join(cells) + " |\n")
                paper = paper_cells(paper_rows, row.get("paper"), paper_dataset, table["columns"])
                if paper:
                    values = " | ".join(_fmt(paper.get(c, math.nan)) for c in table["columns"])
                    w(f"| *{_paper_label(row)}* | | {values} |\n")
            for d in table.get("differences", []):
                entry = _row_cells(result, table, dataset, d)
                n = max((c.n for c in entry.values()), default=0)
                if n:
                    cells = [_cell_text(entry[c], n, " ± ", " (n = {})") for c in table["columns"]]
                    w(f"| *{d['label']}* | {n} | " + " | ".join(cells) + " |\n")
            w("\n")
    if spec.get("figures"):
        w("## Figures\n\n")
        for path in sorted(result.get("figures", [])):
            w(f"![{Path(path).stem}](figures/{Path(path).name})\n\n")
        lacking = result.get("without_artifacts", [])
        if lacking and set(spec["figures"]) - {"iterations"}:
            w(f"Figures drawn from run artifacts (per-pixel errors, per-sample motion errors, depth maps) leave "
              f"out {len(lacking)} of the {result['counted']} counted runs, whose artifacts are not in this "
              f"store's artifact location: {', '.join(lacking)}.\n\n")
    from demon_lab.reporting import provenance

    w(provenance.markdown(result.get("provenance", []), result["used"], result["versions"], result.get("archives", [])))
    w("\n## Runs not counted\n\n")
    if failed.empty and not result["missing"] and not result.get("rerun") and not result.get("stale"):
        w("None: every expected (row, seed) has a FINISHED run and no run failed.\n")
    for _, r in failed.iterrows():
        what = ", ".join(f"{k}={_get(r, k)}" for k in ("method", "oracle", "iterations")
                         if _get(r, k) not in (None, "None"))
        error = r.get(f"tags.{TAG}error")
        w(f"- FAILED run {r['run_id']} (experiment {r['experiment']}, seed {_get(r, 'seed')}, {what}): "
          f"{(error if isinstance(error, str) else 'no error recorded')[:300]}\n")
    for line in result["missing"]:
        w(f"- missing: {line}\n")
    if result.get("stale"):
        w(f"- {result['stale']} FINISHED run(s) of older code or scene-generator versions (this checkout: "
          f"{result['versions']}; runs without these tags predate them): stale, not counted\n")
    if result.get("rerun"):
        w(f"- {result['rerun']} FAILED run(s) followed by a FINISHED run of the same job, or of the same row "
          f"and seed, are not listed\n")
    return out.getvalue()


def _paper_label(row: Mapping[str, Any]) -> str:
    """A paper row's label: the spec's ``paper.label``, else ``paper: <row label>``."""
    return row["paper"].get("label") or f"paper: {row['label']}"


def write_csv(spec, result, paper_rows) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(["table", "dataset", "row", "metric", "mean", "std", "ci95", "n", "values", "paper", "design",
                     "config", "run_ids"])
    origin = {(e["table"], e["row"]): e for e in result.get("provenance", [])}
    for table in spec["tables"]:
        for dataset, paper_dataset in spec["datasets"].items():
            for row in [*table["rows"], *table.get("differences", [])]:
                paper = paper_cells(paper_rows, row.get("paper"), paper_dataset, table["columns"])
                source = origin.get((table["name"], row["label"]), {})
                for c, cl in _row_cells(result, table, dataset, row).items():
                    writer.writerow([table["name"], dataset, row["label"], c, cl.mean, cl.std, cl.ci95, cl.n,
                                     " ".join(f"{v:.6g}" for v in cl.values), paper.get(c, ""),
                                     source.get("design", ""), source.get("config", ""), source.get("runs", "")])
    return out.getvalue()


def write_tex(spec, result, info, paper_rows) -> str:
    esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
    out = io.StringIO()
    w = out.write
    w(f"% {spec['title']}\n% generated by {spec.get('command') or 'python -m demon_lab.report ' + spec['name']}; "
      f"scale {info['scale']}, "
      f"seeds {info['seeds']}, {info['runs']} runs\n% needs \\usepackage{{booktabs}}\n")
    for e in result.get("provenance", []):
        w(f"% {e['table']} / {e['row']}: {e['design']}; config {e['config']}; seeds {e['seeds']}; runs {e['runs']}\n")
    for table in spec["tables"]:
        for dataset, paper_dataset in spec["datasets"].items():
            if not has_values(result, table["name"], dataset):
                continue
            cols = table["columns"]
            w("\\begin{table}[t]\\centering\\small\n")
            w(f"\\caption{{{esc(table['caption'])}; {esc(dataset)}, mean $\\pm$ 95\\% CI over seeds"
              f"{'; paper (' + esc(paper_dataset) + ') in italics' if paper_dataset else ''}.}}\n")
            w("\\begin{tabular}{l" + "r" * len(cols) + "}\\toprule\n")
            w(" & ".join(["", *[column(c).tex for c in cols]]) + " \\\\\\midrule\n")
            for row in table["rows"]:
                entry = _row_cells(result, table, dataset, row)
                n = max((entry[c].n for c in cols), default=0)
                cells = [_cell_text(entry[c], n, " $\\pm$ ", " ($n={}$)") for c in cols]
                w(" & ".join([esc(row["label"]), *cells]) + " \\\\\n")
                paper = paper_cells(paper_rows, row.get("paper"), paper_dataset, cols)
                if paper:
                    label = esc(row["paper"]["label"]) if row["paper"].get("label") else "paper"
                    w(" & ".join([f"\\quad\\textit{{{label}}}", *[f"\\textit{{{_fmt(paper.get(c, math.nan))}}}"
                                                              for c in cols]]) + " \\\\\n")
            for d in table.get("differences", []):
                entry = _row_cells(result, table, dataset, d)
                n = max((entry[c].n for c in cols), default=0)
                if n:
                    cells = [_cell_text(entry[c], n, " $\\pm$ ", " ($n={}$)") for c in cols]
                    w(" & ".join([f"\\textit{{{esc(d['label'])}}}", *cells]) + " \\\\\n")
            w("\\bottomrule\\end{tabular}\n\\end{table}\n\n")
    return out.getvalue()


# ----------------------------------------------------------------------------- commands


EXPERIMENT_COLUMNS = ("l1_inv", "sc_inv", "rot_deg", "tran_deg", "epe")
"""The columns of an experiment's report without a study spec."""


def experiment_spec(experiment: str, uri: str) -> dict[str, Any]:
    """A study spec for any experiment's runs (``python -m demon_lab.report --experiment NAME``, the
    main command's ``default`` included): one table whose rows are the FINISHED runs of this checkout's
    versions grouped by the params that differ between them and change results (the seed aside:
    seeds are aggregated), each row reading its runs' last pass (``iterations``; the summary of a
    classical method), on every test set they logged. Params that only some runs have are not told
    apart."""
    from demon_lab.pipeline.identity import is_semantic

    runs = fetch_runs(uri, [experiment])
    finished = runs[current_versions(runs, version_tags()) & (runs["status"] == "FINISHED")]
    if finished.empty:
        raise ReportError(f"experiment {experiment!r}: no FINISHED run of this checkout's versions in {uri}")
    params = [c.removeprefix("params.") for c in finished.columns if c.startswith("params.")]
    varying = [k for k in params if k != "seed" and is_semantic(k) and finished[f"params.{k}"].notna().all()
               and finished[f"params.{k}"].nunique() > 1]
    groups = finished.groupby([f"params.{k}" for k in varying], sort=True) if varying else [((), finished)]
    rows = []
    for values, group in groups:
        match = dict(zip(varying, values if isinstance(values, tuple) else (values,), strict=True))
        method, iterations = (field(group, k).iloc[0] for k in ("method", "iterations"))
        rows.append({"label": ", ".join(f"{k}={v}" for k, v in match.items()) or "every run", "match": match,
                     "metrics": f"it{iterations}" if method == "demon" else ""})
    names = sorted({c.split("/")[1] for c in finished.columns if c.startswith("metrics.test/")})
    return {"name": f"experiment_{experiment}", "title": f"The runs of experiment {experiment}", "runs": [],
            "command": f"python -m demon_lab.report --experiment {experiment}",
            "seeds": sorted({int(s) for s in finished["seed"]}), "datasets": dict.fromkeys(names),
            "tables": [{"name": "runs", "experiment": experiment, "columns": list(EXPERIMENT_COLUMNS), "rows": rows,
                        "caption": f"The FINISHED runs of experiment {experiment}, grouped by "
                                   f"{', '.join(varying) or 'nothing (one configuration)'}; each row's last pass"}]}


def report(name: str, uri: str, out_dir: Path, directory: Path = STUDIES,
           spec: Mapping[str, Any] | None = None) -> dict[str, Path]:
    """Writes the report of one spec (``spec``: a spec built here rather than read from
    ``ablations/NAME.yaml``); returns the written paths."""
    directory = Path(directory)
    spec = load_spec(name, directory) if spec is None else dict(spec)
    experiments = sorted({t["experiment"] for t in spec["tables"]})
    current = version_tags()
    everything = fetch_runs(uri, experiments)
    same = current_versions(everything, current)
    runs = everything[same]
    result = build(spec, runs)
    result["stale"] = int((everything.loc[~same, "status"] == "FINISHED").sum())
    result["versions"] = ", ".join(f"{k.removeprefix(TAG)} {v}" for k, v in current.items())
    paper_rows = paper_numbers(directory / "paper_numbers.csv")
    from demon_lab.reporting import provenance

    try:
        result["provenance"] = provenance.rows(spec, result["used"])
    except provenance.DesignMixError as e:
        raise ReportError(str(e)) from None
    from demon_lab.reporting.archive import archived_experiments

    archives = sorted((out_dir / "runs").glob("*.zip")) if (out_dir / "runs").is_dir() else []
    result["archives"] = [f"runs/{a.name}" for a in archives  # (relative to the report)
                          if archived_experiments(a) & set(experiments)]
    failed = runs[runs["status"] == "FAILED"]
    superseded = _superseded(failed, spec, runs, result["used"])
    result["rerun"] = int(superseded.sum())
    failed = failed[~superseded]
    info = _describe(spec, result["used"])
    out_dir.mkdir(parents=True, exist_ok=True)
    figures_dir = out_dir / "figures"
    figures_dir.mkdir(exist_ok=True)
    from demon_lab.reporting.figures import study_figures

    for old in study_figures(figures_dir, name):  # this study's figures, drawn again below
        old.unlink()
    figures: list[Path] = []
    import matplotlib

    from demon_lab.reporting.figures import (
        figure_iterations,
        figure_motion_distributions,
        figure_pixel_histograms,
        figure_qualitative,
        figure_time_to_accuracy,
        local_artifact,
    )

    matplotlib.use("Agg")
    for figure in spec.get("figures", []):
        if figure == "iterations":
            figures += figure_iterations(spec, result, paper_rows, figures_dir)
        elif figure == "pixel_histograms":
            figures += figure_pixel_histograms(spec, result, figures_dir)
        elif figure == "motion_distributions":
            figures += figure_motion_distributions(spec, result, figures_dir)
        elif figure == "qualitative":
            figures += figure_qualitative(spec, result, figures_dir)
        elif figure == "time_to_accuracy":
            figures += figure_time_to_accuracy(spec, result, uri, figures_dir)
    footer = provenance.footer(result["provenance"], result["used"], result["versions"])
    for figure_path in figures:
        provenance.stamp_figure(figure_path, footer)
    result["figures"] = [str(p) for p in figures]
    used = result["used"].drop_duplicates("run_id")
    result["without_artifacts"] = sorted(r["run_id"] for _, r in used.iterrows() if local_artifact(r, "") is None)
    result["counted"] = len(used)
    if result["without_artifacts"] and set(spec.get("figures", [])) - {"iterations"}:
        print(f"[demon_lab.report] {name}: {len(result['without_artifacts'])} of {len(used)} counted runs have no "
              f"artifacts on this machine; the figures drawn from artifacts leave them out", file=sys.stderr)
    paths = {"md": out_dir / f"{name}.md", "csv": out_dir / f"{name}.csv", "tex": out_dir / f"{name}.tex"}
    paths["md"].write_text(write_markdown(spec, result, info, failed, paper_rows))
    paths["csv"].write_text(write_csv(spec, result, paper_rows))
    paths["tex"].write_text(write_tex(spec, result, info, paper_rows))
    return {**paths, **{p.name: p for p in figures}}


def study_rows(study: str, uri: str, experiment: str, directory: Path = STUDIES) -> str | None:
    """The tables of ``study`` that rows of ``experiment`` stand in, as the terminal shows them, from
    the FINISHED runs of this checkout's versions in the store at ``uri``: one test set (the first of
    the spec's that has values: synthetic_sun3d in the shipped specs), each row with its n and its
    cells (mean ± 95 % half-width). What a single job of an experiment prints after its own result,
    so that its row stands beside those it is compared with. None where no row has a run yet."""
    from demon_lab.reporting.tables import text_table

    spec = load_spec(study, directory)
    tables = [t for t in spec["tables"] if t["experiment"] == experiment]
    runs = fetch_runs(uri, [experiment])
    result = build({**spec, "tables": tables}, runs[current_versions(runs, version_tags())])
    parts = []
    for table in tables:
        dataset = next((d for d in spec["datasets"] if has_values(result, table["name"], d)), None)
        if dataset is None:
            continue
        rows = []
        for row in table["rows"]:
            entry = _row_cells(result, table, dataset, row)
            n = max((c.n for c in entry.values()), default=0)
            cells = [_cell_text(entry[c], n, " ± ", " (n = {})") for c in table["columns"]]
            rows.append([row["label"], str(n), *cells])
        header = ["row", "n", *[column(c).text for c in table["columns"]]]
        parts.append(f"{study} / {table['name']} on {dataset} (python -m demon_lab.report {study}):\n"
                     + text_table(header, rows))
    return "\n\n".join(parts) or None


def publish(study: str, uri: str, run_id: str, directory: Path = STUDIES) -> list[str]:
    """Build ``study``'s report (md, csv, tex, figures) from the store at ``uri`` in a temporary
    folder and log it as artifacts of the run ``run_id`` (a sweep's parent run) under ``report/``
    (figures under ``report/figures/``); returns the artifact paths. Nothing is written to ./reports."""
    from mlflow.tracking import MlflowClient

    with tempfile.TemporaryDirectory(prefix=f"demon_lab_report_{study}_") as tmp:
        root = Path(tmp)
        paths = report(study, uri, root, directory)
        MlflowClient(tracking_uri=uri).log_artifacts(run_id, str(root), artifact_path="report")
        return [f"report/{p.relative_to(root).as_posix()}" for p in paths.values()]


def run_spec(name: str, directory: Path = STUDIES, extra: Sequence[str] = ()) -> int:
    """Runs the spec's commands (finished jobs are skipped by run key); returns the worst exit code."""
    spec = load_spec(name, directory)
    given = {o.split("=", 1)[0].lstrip("+~") for o in extra}
    lacking = [f"--override {k}={v}" for k, v in (spec.get("requires") or {}).items() if k not in given]
    if lacking:
        raise ReportError(f"{name} runs on files you supply: pass {' '.join(lacking)}")
    worst = 0
    for overrides in spec.get("runs", []):
        command = [sys.executable, "-m", "demon_lab", "-m", *overrides, *extra]
        print("[demon_lab.report] running: " + " ".join(command[1:]), flush=True)
        worst = max(worst, subprocess.call(command))
    return worst


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.report", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="study specs (ablations/NAME.yaml)")
    parser.add_argument("--experiment", dest="experiments", action="append", default=[], metavar="NAME",
                        help="report an MLflow experiment's runs without a study spec (e.g. default, the main "
                             "command's): reports/experiment_NAME.{md,csv,tex}; repeatable")
    parser.add_argument("--all", action="store_true", help="every study spec in ablations/")
    parser.add_argument("--run", action="store_true", help="first run the spec's jobs that MLflow lacks")
    parser.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                        help="with --run: an override added to every command (e.g. data.root=DIR); repeatable")
    parser.add_argument("--import", dest="imports", action="append", default=[], type=Path, metavar="FILE",
                        help="first add a run archive's runs to the store (repeatable; runs there already are skipped)")
    parser.add_argument("--export", type=Path, metavar="FILE",
                        help="last write the named studies' runs to a run archive (a zip file)")
    parser.add_argument("--without-images", action="store_true",
                        help="with --export: leave out the jobs' depth panels (the qualitative figures' input)")
    parser.add_argument("--docs", action="store_true",
                        help="last write the result tables between <!-- report: STUDY TABLE SET --> markers in "
                             "README.md and docs/ from the reports (run from the repository's root)")
    parser.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"))
    parser.add_argument("--artifact-dir", default="mlartifacts",
                        help="with --import, a local store: where imported artifacts go (tracking.artifact_dir)")
    parser.add_argument("--out", type=Path, default=Path("reports"))
    parser.add_argument("--studies", type=Path, default=STUDIES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    names = sorted(p.stem for p in args.studies.glob("*.yaml")) if args.all else list(args.names)
    if not names and not args.imports and not args.experiments and not args.docs:
        parser.error("name a study spec, pass --all, --experiment NAME or --docs")
    if args.export and not names:
        parser.error("--export writes the runs of the studies named")
    from demon_lab.reporting.archive import export_runs, import_runs

    for archive in args.imports:
        if not archive.is_file():
            print(f"error: --import {archive}: no such file", file=sys.stderr)
            return 2
        added, there = import_runs(args.tracking_uri, archive, args.artifact_dir)
        print(f"[demon_lab.report] {archive}: {added} runs imported, {there} already in the store", flush=True)
    status = 0
    for name in names:
        try:
            if args.run:
                status = max(status, run_spec(name, args.studies, args.override))
            paths = report(name, args.tracking_uri, args.out, args.studies)
        except ReportError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"[demon_lab.report] {name}: " + ", ".join(str(p) for p in paths.values()), flush=True)
    for experiment in args.experiments:
        try:
            spec = experiment_spec(experiment, args.tracking_uri)
            paths = report(spec["name"], args.tracking_uri, args.out, args.studies, spec=spec)
        except ReportError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"[demon_lab.report] experiment {experiment}: " + ", ".join(str(p) for p in paths.values()), flush=True)
    if args.docs:
        from demon_lab.reporting import doc_tables

        root = args.out.resolve().parent
        written = {str(p.relative_to(root)): doc_tables.write_blocks(p, root) for p in doc_tables.pages(root)
                   if p.is_file()}
        print("[demon_lab.report] --docs: " + ", ".join(f"{p} ({n} tables)" for p, n in written.items() if n),
              flush=True)
    if args.export:
        experiments = sorted({t["experiment"] for name in names for t in load_spec(name, args.studies)["tables"]})
        count = export_runs(args.tracking_uri, experiments, args.export, images=not args.without_images)
        print(f"[demon_lab.report] {args.export}: {count} runs of {', '.join(experiments)}", flush=True)
    return status

