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
boolean masks on it and the seeds of a cell are aggregated with ``groupby``. The parts:
:mod:`~demon_lab.reporting.specs` reads a spec, :mod:`~demon_lab.reporting.selection` picks the runs
and builds the cells, :mod:`~demon_lab.reporting.writers` writes the files, and this module runs
them as the command.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from demon_lab.core.metrics import column
from demon_lab.pipeline.methods import METHODS
from demon_lab.pipeline.tracking import TAG, version_tags
from demon_lab.reporting.selection import (
    aggregate,
    build,
    choose,
    current_versions,
    fetch_runs,
    field,
    of_design,
    superseded,
)
from demon_lab.reporting.specs import FIGURES, ReportError, load_spec, paper_numbers, study_of
from demon_lab.reporting.tables import cell, has_values, paper_cells
from demon_lab.reporting.writers import cell_text, describe, row_cells, write_csv, write_markdown, write_tex
from demon_lab.resources import STUDIES

__all__ = ["FIGURES", "STUDIES", "ReportError", "aggregate", "build", "cell", "choose", "current_versions",
           "experiment_spec", "fetch_runs", "field", "load_spec", "main", "of_design", "paper_cells",
           "paper_numbers", "publish", "report", "run_spec", "study_of", "study_rows"]
"""The report's API: its commands and, from the modules it is made of, what their callers use."""


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
                     "metrics": METHODS[method].summary_metrics(iterations) if method in METHODS else ""})
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
    own = directory / "paper_numbers.csv"  # a folder of the user's own specs may bring its own, else the shipped
    paper_rows = paper_numbers(own if own.is_file() else STUDIES / "paper_numbers.csv")
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
    rerun = superseded(failed, spec, runs, result["used"])
    result["rerun"] = int(rerun.sum())
    failed = failed[~rerun]
    info = describe(spec, result["used"])
    out_dir.mkdir(parents=True, exist_ok=True)
    figures_dir = out_dir / "figures"
    figures_dir.mkdir(exist_ok=True)
    from demon_lab.reporting.figures import study_figures

    for old in study_figures(figures_dir, name):  # this study's figures, drawn again below
        old.unlink()
    figures: list[Path] = []
    import matplotlib

    from demon_lab.reporting.figures import (
        CURVES_DATASET,
        curve_end_points,
        figure_iterations,
        figure_motion_distributions,
        figure_pixel_histograms,
        figure_qualitative,
        figure_time_to_accuracy,
        held_apart_curves,
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
            curves = held_apart_curves(spec, result, uri, CURVES_DATASET)
            result["curve_ends"], result["curves_dataset"] = curve_end_points(curves), CURVES_DATASET
            figures += figure_time_to_accuracy(curves, spec, figures_dir, CURVES_DATASET)
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
            entry = row_cells(result, table, dataset, row)
            n = max((c.n for c in entry.values()), default=0)
            cells = [cell_text(entry[c], n, " ± ", " (n = {})") for c in table["columns"]]
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
    parser.add_argument("--data-stats", action="store_true",
                        help="write reports/data_stats.md: the synthetic presets' camera statistics (their "
                             "data_stats_*.json in --out) beside the supplementary's Table 1")
    parser.add_argument("--docs", action="store_true",
                        help="last write the result tables between <!-- report: STUDY TABLE SET --> markers in "
                             "README.md and docs/ from the reports (run from the repository's root)")
    parser.add_argument("--tracking-uri", help="the MLflow store (default: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db)")
    parser.add_argument("--artifact-dir", default="mlartifacts",
                        help="with --import, a local store: where imported artifacts go (tracking.artifact_dir)")
    parser.add_argument("--out", type=Path, default=Path("reports"))
    parser.add_argument("--studies", type=Path, default=STUDIES, metavar="FOLDER",
                        help="a folder of study specs of your own (its paper_numbers.csv, if it has one, else the "
                             "shipped one; default: the shipped ablations/)")
    args = parser.parse_args(argv)
    args.tracking_uri = args.tracking_uri or os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db")
    names = sorted(p.stem for p in args.studies.glob("*.yaml")) if args.all else list(args.names)
    if not names and not args.imports and not args.experiments and not args.docs and not args.data_stats:
        parser.error("name a study spec, pass --all, --experiment NAME, --data-stats or --docs")
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
    if args.data_stats:
        from demon_lab.reporting import doc_tables

        (args.out / "data_stats.md").write_text(doc_tables.camera_statistics(args.out))
        print(f"[demon_lab.report] {args.out / 'data_stats.md'}", flush=True)
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

