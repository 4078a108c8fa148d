"""``python -m demon_lab.report NAME [--all] [--run]``: paper-style tables and figures from MLflow.

An ablation spec (``ablations/NAME.yaml``) names the runs (``runs``: the override lists of
``python -m demon_lab -m`` commands), the seeds expected, the test sets (each mapped to the
paper's dataset whose numbers stand beside it) and tables whose rows select runs by tag or param
(``match``) and read one pass's metrics (``metrics``: ``it<k>``, ``refined`` or ``""`` for the
summary). The report reads FINISHED runs of this checkout's code and scene-generator versions
only (older ones are stale: counted and named, not used), keeps the newest run per (row, seed), aggregates
seeds (mean, sample std, 95 % t-interval, n) and writes ``reports/NAME.md``, ``.csv``, ``.tex``
and ``reports/figures/NAME_*.png``. FAILED runs (unless their job, or their row and seed, has a
newer FINISHED run) and seeds without a run are listed.

``--run`` first executes the spec's commands (skip-if-finished makes that incremental).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
import shutil
import subprocess
import sys
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from demon_lab.resources import STUDIES as ABLATIONS
from demon_lab.tracking import TAG, metric_name, version_tags

PAPER_COLUMNS = {"l1_inv": "L1-inv", "sc_inv": "sc-inv", "l1_rel": "L1-rel", "delta_1.25": "delta<1.25",
                 "delta_1.25_2": "delta<1.25^2", "delta_1.25_3": "delta<1.25^3", "rot_deg": "rot",
                 "tran_deg": "tran", "epe": "EPE"}
LABELS = {"l1_inv": "L1-inv", "sc_inv": "sc-inv", "l1_rel": "L1-rel", "delta_1.25": "δ<1.25",
          "delta_1.25_2": "δ<1.25²", "delta_1.25_3": "δ<1.25³", "rot_deg": "rot (°)", "tran_deg": "tran (°)",
          "epe": "EPE", "n_failed": "failed"}
FIGURES = ("iterations", "pixel_histograms", "motion_distributions", "qualitative")


class ReportError(ValueError):
    """A spec that cannot be read or does not fit the report's format."""


@dataclass
class Run:
    run_id: str
    experiment: str
    status: str
    tags: dict[str, str]
    params: dict[str, str]
    metrics: dict[str, float]
    start_time: int
    artifact_uri: str

    def get(self, key: str) -> str | None:
        """A tag (``demon_lab.<key>``) or else a param; None if neither exists."""
        if f"{TAG}{key}" in self.tags:
            return self.tags[f"{TAG}{key}"]
        return self.params.get(key)

    def artifact(self, path: str) -> Path | None:
        from urllib.parse import unquote, urlparse

        parsed = urlparse(self.artifact_uri)
        root = Path(unquote(parsed.path)) if parsed.scheme in ("file", "") else None
        target = root / path if root is not None else None
        return target if target is not None and target.exists() else None


@dataclass
class Cell:
    values: list[float] = field(default_factory=list)

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float:
        return sum(self.values) / self.n if self.n else math.nan

    @property
    def std(self) -> float:
        if self.n < 2:
            return math.nan
        m = self.mean
        return math.sqrt(sum((v - m) ** 2 for v in self.values) / (self.n - 1))

    @property
    def ci95(self) -> float:
        """Half-width of the 95 % t-interval of the mean (NaN below 2 values)."""
        if self.n < 2:
            return math.nan
        from scipy.stats import t

        return float(t.ppf(0.975, self.n - 1)) * self.std / math.sqrt(self.n)


def load_spec(name: str, directory: Path = ABLATIONS) -> dict[str, Any]:
    path = directory / f"{name}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in directory.glob("*.yaml")))
        raise ReportError(f"ablation {name!r}: no {path}; known: {known}")
    spec = yaml.safe_load(path.read_text()) or {}
    for key in ("title", "tables", "datasets"):
        if key not in spec:
            raise ReportError(f"ablations/{name}.yaml: missing key {key!r}")
    for figure in spec.get("figures", []):
        if figure not in FIGURES:
            raise ReportError(f"ablations/{name}.yaml: figures: expected some of {FIGURES}, got {figure!r}")
    spec["name"] = name
    return spec


def paper_numbers(path: Path = ABLATIONS / "paper_numbers.csv") -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def paper_cells(rows: Sequence[Mapping[str, str]], ref: Mapping[str, Any] | None, dataset: str | None,
                columns: Sequence[str]) -> dict[str, float]:
    """The paper's values for one row of a table on one paper dataset (merged over its CSV rows)."""
    if not ref or not dataset:
        return {}
    wanted = set(ref.get("rows") or [])
    out: dict[str, float] = {}
    for r in rows:
        if (r["table"] == str(ref["table"]) and r["dataset"] == dataset and r["method"] == ref["method"]
                and (not wanted or r["row"] in wanted)):
            for c in columns:
                text = r.get(PAPER_COLUMNS.get(c, ""), "")
                if text not in ("", None) and c not in out:
                    out[c] = float(text)
    return out


def fetch_runs(uri: str, experiments: Sequence[str]) -> list[Run]:
    """Every top-level job run (not stage runs) of the named experiments, any status."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    runs: list[Run] = []
    for name in experiments:
        exp = client.get_experiment_by_name(name)
        if exp is None:
            continue
        token = None
        while True:
            page = client.search_runs([exp.experiment_id], max_results=1000, page_token=token)
            for r in page:
                if r.data.tags.get(f"{TAG}kind") == "stage" or f"{TAG}run_key" not in r.data.tags:
                    continue
                runs.append(Run(r.info.run_id, name, r.info.status, dict(r.data.tags), dict(r.data.params),
                                dict(r.data.metrics), r.info.start_time or 0, r.info.artifact_uri))
            token = page.token
            if not token:
                break
    return runs


def _matches(run: Run, match: Mapping[str, Any]) -> bool:
    return all(run.get(k) == ("None" if v is None else str(v)) for k, v in (match or {}).items())


def select(runs: Sequence[Run], experiment: str, match: Mapping[str, Any]) -> dict[int, Run]:
    """The newest FINISHED run per seed of one row."""
    chosen: dict[int, Run] = {}
    for run in runs:
        if run.experiment != experiment or run.status != "FINISHED" or not _matches(run, match):
            continue
        seed = int(run.get("seed") or 0)
        if seed not in chosen or run.start_time > chosen[seed].start_time:
            chosen[seed] = run
    return chosen


def metric_key(dataset: str, prefix: str, column: str) -> str:
    return metric_name(f"test/{dataset}/{prefix + '/' if prefix else ''}{column}")


def build(spec: Mapping[str, Any], runs: Sequence[Run]) -> dict[str, Any]:
    """Aggregated cells: {table: {dataset: {row: {column: Cell}}}}, the runs used, missing seeds."""
    seeds = [int(s) for s in spec.get("seeds", [])]
    cells: dict[str, dict[str, dict[str, dict[str, Cell]]]] = {}
    used: dict[str, dict[str, dict[int, Run]]] = {}
    missing: list[str] = []
    for table in spec["tables"]:
        per_row = {row["label"]: select(runs, table["experiment"], row.get("match", {})) for row in table["rows"]}
        used[table["name"]] = per_row
        for row in table["rows"]:
            absent = [s for s in seeds if s not in per_row[row["label"]]]
            if absent:
                missing.append(f"{table['name']} / {row['label']}: no FINISHED run for seed(s) "
                               f"{', '.join(map(str, absent))}")
        cells[table["name"]] = {}
        for dataset in spec["datasets"]:
            cells[table["name"]][dataset] = {}
            for row in table["rows"]:
                entry = {}
                for column in table["columns"]:
                    cell = Cell()
                    for _, run in sorted(per_row[row["label"]].items()):
                        v = run.metrics.get(metric_key(dataset, row.get("metrics", ""), column))
                        if v is not None and math.isfinite(v):
                            cell.values.append(v)
                    entry[column] = cell
                cells[table["name"]][dataset][row["label"]] = entry
    return {"cells": cells, "used": used, "missing": missing}


def _superseded(failed: Run, spec: Mapping[str, Any], runs: Sequence[Run], used: Mapping[str, Any]) -> bool:
    """A FAILED run whose job was re-run to FINISHED (same run key), or whose row and seed have a
    newer FINISHED run in the table (a later attempt, e.g. after a code change)."""
    if any(r.status == "FINISHED" and r.get("run_key") == failed.get("run_key") for r in runs):
        return True
    seed = int(failed.get("seed") or 0)
    for table in spec["tables"]:
        if table["experiment"] != failed.experiment:
            continue
        for row in table["rows"]:
            chosen = used[table["name"]][row["label"]].get(seed)
            if chosen is not None and _matches(failed, row.get("match", {})) and chosen.start_time > failed.start_time:
                return True
    return False


def _fmt(v: float, digits: int = 3) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.{digits}f}" if abs(v) < 1000 else f"{v:.0f}"


def _describe(spec: Mapping[str, Any], runs: Sequence[Run], used: Mapping[str, Any]) -> dict[str, str]:
    chosen = [r for per_row in used.values() for per_seed in per_row.values() for r in per_seed.values()]
    values = lambda key: sorted({r.get(key) or "?" for r in chosen})  # noqa: E731
    commands = [f"python -m demon_lab -m {' '.join(overrides)}" for overrides in spec.get("runs", [])]
    return {"scale": ", ".join(values("scale")) or "-", "data": ", ".join(values("data")) or "-",
            "seeds": ", ".join(sorted({r.get("seed") or "0" for r in chosen}, key=int)) or "-",
            "runs": str(len({r.run_id for r in chosen})), "commands": commands}


def _cell_text(cell, row_n: int, pm: str, fewer: str) -> str:
    """Mean, ``pm`` and the CI half-width (with 2+ seeds), and ``fewer`` (a format with the cell's
    n) when fewer seeds than the row's logged a finite value here (say, no pixel of positive depth)."""
    text = _fmt(cell.mean) + (f"{pm}{_fmt(cell.ci95)}" if cell.n > 1 else "")
    return text + (fewer.format(cell.n) if 0 < cell.n < row_n else "")


def write_markdown(spec, result, info, failed, paper_rows) -> str:
    out = io.StringIO()
    w = out.write
    w(f"# {spec['title']}\n\n")
    w(f"Generated by `python -m demon_lab.report {spec['name']}` from the FINISHED runs in the MLflow store.\n\n")
    w(f"- scale: {info['scale']}; data: {info['data']}; seeds: {info['seeds']}; runs used: {info['runs']}\n")
    report_cmd = f"python -m demon_lab.report {spec['name']}"
    w("- reproduce: " + "; ".join(f"`{c}`" for c in info["commands"]) + f"; then `{report_cmd}`"
      + f" (or both at once: `{report_cmd} --run`)\n")
    w("- cells: mean ± 95 % confidence half-width (t-interval over seeds), n = seeds (a cell marked "
      "(n = k) has fewer: the other seeds' runs logged no finite value there, e.g. no pixel of positive "
      "depth); "
      "depth metrics on unit-baseline depth, rot/tran in degrees, EPE in normalised flow units\n")
    if spec.get("paper_note"):
        w(f"- paper: {spec['paper_note']}\n")
    w("\n")
    for table in spec["tables"]:
        w(f"## {table['caption']}\n\n")
        for dataset, paper_dataset in spec["datasets"].items():
            rows = result["cells"][table["name"]][dataset]
            if not any(c.n for r in rows.values() for c in r.values()):
                continue
            w(f"### {dataset}" + (f" (paper: {paper_dataset})" if paper_dataset else "") + "\n\n")
            header = ["row", "n", *[LABELS.get(c, c) for c in table["columns"]]]
            w("| " + " | ".join(header) + " |\n|" + "---|" * len(header) + "\n")
            for row in table["rows"]:
                entry = rows[row["label"]]
                n = max((c.n for c in entry.values()), default=0)
                cells = [_cell_text(entry[c], n, " ± ", " (n = {})") for c in table["columns"]]
                w(f"| {row['label']} | {n} | " + " | ".join(cells) + " |\n")
                paper = paper_cells(paper_rows, row.get("paper"), paper_dataset, table["columns"])
                if paper:
                    values = " | ".join(_fmt(paper.get(c, math.nan)) for c in table["columns"])
                    w(f"| *paper: {row['label']}* | | {values} |\n")
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
    w("## Runs not counted\n\n")
    if not failed and not result["missing"] and not result.get("rerun") and not result.get("stale"):
        w("None: every expected (row, seed) has a FINISHED run and no run failed.\n")
    for r in failed:
        what = ", ".join(f"{k}={r.get(k)}" for k in ("method", "oracle", "iterations")
                         if r.get(k) not in (None, "None"))
        w(f"- FAILED run {r.run_id} (experiment {r.experiment}, seed {r.get('seed')}, {what}): "
          f"{r.tags.get(f'{TAG}error', 'no error recorded')[:300]}\n")
    for line in result["missing"]:
        w(f"- missing: {line}\n")
    if result.get("stale"):
        w(f"- {result['stale']} FINISHED run(s) of older code or scene-generator versions (this checkout: "
          f"{result['versions']}; runs without these tags predate them): stale, not counted\n")
    if result.get("rerun"):
        w(f"- {result['rerun']} FAILED run(s) followed by a FINISHED run of the same job, or of the same row "
          f"and seed, are not listed\n")
    return out.getvalue()


def write_csv(spec, result, paper_rows) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(["table", "dataset", "row", "metric", "mean", "std", "ci95", "n", "values", "paper"])
    for table in spec["tables"]:
        for dataset, paper_dataset in spec["datasets"].items():
            for row in table["rows"]:
                paper = paper_cells(paper_rows, row.get("paper"), paper_dataset, table["columns"])
                for c in table["columns"]:
                    cell = result["cells"][table["name"]][dataset][row["label"]][c]
                    writer.writerow([table["name"], dataset, row["label"], c, cell.mean, cell.std, cell.ci95, cell.n,
                                     " ".join(f"{v:.6g}" for v in cell.values), paper.get(c, "")])
    return out.getvalue()


def write_tex(spec, result, info, paper_rows) -> str:
    esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
    tex_label = {"l1_inv": "L1-inv", "sc_inv": "sc-inv", "l1_rel": "L1-rel", "delta_1.25": r"$\delta<1.25$",
                 "delta_1.25_2": r"$\delta<1.25^2$", "delta_1.25_3": r"$\delta<1.25^3$", "rot_deg": "rot",
                 "tran_deg": "tran", "epe": "EPE", "n_failed": "failed"}
    out = io.StringIO()
    w = out.write
    w(f"% {spec['title']}\n% generated by python -m demon_lab.report {spec['name']}; scale {info['scale']}, "
      f"seeds {info['seeds']}, {info['runs']} runs\n% needs \\usepackage{{booktabs}}\n")
    for table in spec["tables"]:
        for dataset, paper_dataset in spec["datasets"].items():
            rows = result["cells"][table["name"]][dataset]
            if not any(c.n for r in rows.values() for c in r.values()):
                continue
            cols = table["columns"]
            w("\\begin{table}[t]\\centering\\small\n")
            w(f"\\caption{{{esc(table['caption'])}; {esc(dataset)}, mean $\\pm$ 95\\% CI over seeds"
              f"{'; paper (' + esc(paper_dataset) + ') in italics' if paper_dataset else ''}.}}\n")
            w("\\begin{tabular}{l" + "r" * len(cols) + "}\\toprule\n")
            w(" & ".join(["", *[tex_label.get(c, esc(c)) for c in cols]]) + " \\\\\\midrule\n")
            for row in table["rows"]:
                entry = rows[row["label"]]
                n = max((entry[c].n for c in cols), default=0)
                cells = [_cell_text(entry[c], n, " $\\pm$ ", " ($n={}$)") for c in cols]
                w(" & ".join([esc(row["label"]), *cells]) + " \\\\\n")
                paper = paper_cells(paper_rows, row.get("paper"), paper_dataset, cols)
                if paper:
                    w(" & ".join(["\\quad\\textit{paper}", *[f"\\textit{{{_fmt(paper.get(c, math.nan))}}}"
                                                              for c in cols]]) + " \\\\\n")
            w("\\bottomrule\\end{tabular}\n\\end{table}\n\n")
    return out.getvalue()


# ----------------------------------------------------------------------------- figures


def _per_sample_rows(run: Run) -> list[dict[str, str]]:
    path = run.artifact("per_sample_metrics.csv")
    if path is None:
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _save(fig, out: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def figure_iterations(spec, result, paper_rows, path: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    table = spec["tables"][0]
    columns = [c for c in ("l1_inv", "sc_inv", "l1_rel", "rot_deg", "tran_deg", "epe") if c in table["columns"]]
    datasets = [d for d in spec["datasets"] if any(c.n for r in result["cells"][table["name"]][d].values()
                                                   for c in r.values())]
    if not datasets or not columns:
        return []
    fig, axes = plt.subplots(1, len(columns), figsize=(3.2 * len(columns), 3.0), squeeze=False)
    iterations = list(range(len(table["rows"])))
    for ax, column in zip(axes[0], columns):
        for dataset in datasets:
            rows = result["cells"][table["name"]][dataset]
            means = [rows[r["label"]][column].mean for r in table["rows"]]
            errs = [rows[r["label"]][column].ci95 for r in table["rows"]]
            ax.errorbar(iterations, means, yerr=[0 if math.isnan(e) else e for e in errs], marker="o", ms=3,
                        capsize=2, label=dataset[:24])
        paper = [paper_cells(paper_rows, r.get("paper"), "SUN3D", [column]).get(column, math.nan)
                 for r in table["rows"]]
        if any(math.isfinite(p) for p in paper):
            ax.plot(iterations, paper, "k--", marker="s", ms=3, label="paper (SUN3D)")
        ax.set_title(LABELS.get(column, column))
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=6)
    return [_save(fig, path / f"{spec['name']}_iterations.png")]


def figure_pixel_histograms(spec, result, path: Path) -> list[Path]:
    import matplotlib.pyplot as plt
    import numpy as np

    table = spec["tables"][0]
    per_row = result["used"][table["name"]]
    outputs = []
    for dataset in spec["datasets"]:
        merged: dict[str, dict[str, Any]] = {}
        for label, per_seed in per_row.items():
            for run in per_seed.values():
                artifact = run.artifact("pixel_errors.json")
                if artifact is None:
                    continue
                hist = json.loads(artifact.read_text()).get(dataset)
                if not hist:
                    continue
                for metric, h in hist.items():
                    m = merged.setdefault(label, {}).setdefault(metric, {"counts": np.zeros(h["bins"]), "sum": 0.0,
                                                                         "below": 0.0, "upper": h["upper"]})
                    m["counts"] += np.asarray(h["counts"])
                    m["sum"] += h["sum"]
                    m["below"] += h["sum_below_last_bin"]
        if not merged:
            continue
        metrics = ["l1_inv", "l1_rel"]
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
        for ax, metric in zip(axes, metrics):
            for label, hists in merged.items():
                h = hists[metric]
                total = h["counts"].sum()
                if total == 0:
                    continue
                edges = np.linspace(0, h["upper"], len(h["counts"]) + 1)
                below = total - h["counts"][-1]
                ax.stairs(h["counts"] / total, edges,
                          label=f"{label}: mean {h['sum'] / total:.3f} ({h['below'] / max(below, 1):.3f})")
            ax.set_title(f"{dataset}: per-pixel {LABELS[metric]} (last bin: above range)", fontsize=8)
            ax.set_ylabel("fraction of pixels")
            ax.legend(fontsize=6)
        outputs.append(_save(fig, path / f"{spec['name']}_pixel_errors_{dataset}.png"))
    return outputs


def figure_motion_distributions(spec, result, path: Path) -> list[Path]:
    import matplotlib.pyplot as plt
    import numpy as np

    table = spec["tables"][0]
    per_row = result["used"][table["name"]]
    outputs = []
    row_pass = {r["label"]: r.get("metrics", "") for r in table["rows"]}
    tables = {run.run_id: _per_sample_rows(run) for per_seed in per_row.values() for run in per_seed.values()}
    for dataset in spec["datasets"]:
        values: dict[str, dict[str, list[float]]] = defaultdict(lambda: {"rot_deg": [], "tran_deg": []})
        for label, per_seed in per_row.items():
            for run in per_seed.values():
                rows = [r for r in tables[run.run_id] if r.get("dataset") == dataset]
                wanted = row_pass[label].removeprefix("it") if row_pass[label].startswith("it") else None
                if wanted is None:  # the summary: the refined depth's motion (last pass), or a baseline's
                    passes = {r["it"] for r in rows}
                    wanted = "refined" if "refined" in passes else ("baseline" if "baseline" in passes
                                                                    else max(passes, default="0", key=str))
                for r in rows:
                    if r["it"] == wanted:
                        for k in ("rot_deg", "tran_deg"):
                            if r.get(k) not in (None, "", "nan"):
                                values[label][k].append(float(r[k]))
        if not any(v["rot_deg"] for v in values.values()):
            continue
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
        for ax, metric, top in zip(axes, ("rot_deg", "tran_deg"), (20.0, 120.0)):
            edges = np.linspace(0, top, 31)
            for label, v in values.items():
                x = np.minimum(np.asarray(v[metric]), top - 1e-9)
                if len(x):
                    ax.hist(x, bins=edges, histtype="step", density=False, weights=np.full(len(x), 1 / len(x)),
                            label=f"{label} (mean {np.mean(v[metric]):.1f}°, n={len(x)})")
            ax.set_title(f"{dataset}: {LABELS[metric]} per sample (last bin: above range)", fontsize=8)
            ax.set_ylabel("fraction of samples")
            ax.legend(fontsize=6)
        outputs.append(_save(fig, path / f"{spec['name']}_motion_{dataset}.png"))
    return outputs


def figure_qualitative(spec, result, path: Path, per_row_limit: int = 1) -> list[Path]:
    """Copies the first depth visualisation of each row's lowest seed (image | GT | prediction |
    flow | normals) for every test set."""
    table = spec["tables"][0]
    outputs = []
    for label, per_seed in result["used"][table["name"]].items():
        if not per_seed:
            continue
        run = per_seed[min(per_seed)]
        images = run.artifact("images")
        if images is None:
            continue
        for dataset in spec["datasets"]:
            safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in dataset)
            found = sorted(images.glob(f"{safe}_0_*.png"))[:per_row_limit]
            for f in found:
                row_safe = "".join(c if c.isalnum() else "_" for c in label)
                out = path / f"{spec['name']}_qualitative_{row_safe}_{safe}.png"
                shutil.copyfile(f, out)
                outputs.append(out)
    return outputs


def report(name: str, uri: str, out_dir: Path, directory: Path = ABLATIONS) -> dict[str, Path]:
    """Writes the report of one spec; returns the written paths."""
    spec = load_spec(name, directory)
    experiments = sorted({t["experiment"] for t in spec["tables"]})
    current = version_tags()
    runs, stale = [], []
    for r in fetch_runs(uri, experiments):
        (runs if all(r.tags.get(k) == v for k, v in current.items()) else stale).append(r)
    result = build(spec, runs)
    result["stale"] = sum(r.status == "FINISHED" for r in stale)
    result["versions"] = ", ".join(f"{k.removeprefix(TAG)} {v}" for k, v in current.items())
    paper_rows = paper_numbers(directory / "paper_numbers.csv")
    failed, result["rerun"] = [], 0
    for r in (r for r in runs if r.status == "FAILED"):
        if _superseded(r, spec, runs, result["used"]):
            result["rerun"] += 1
        else:
            failed.append(r)
    info = _describe(spec, runs, result["used"])
    out_dir.mkdir(parents=True, exist_ok=True)
    figures_dir = out_dir / "figures"
    figures_dir.mkdir(exist_ok=True)
    for old in figures_dir.glob(f"{name}_*.png"):
        old.unlink()
    figures: list[Path] = []
    import matplotlib

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
    result["figures"] = [str(p) for p in figures]
    used = {r.run_id: r for per_row in result["used"].values() for per_seed in per_row.values()
            for r in per_seed.values()}
    result["without_artifacts"] = sorted(i for i, r in used.items() if r.artifact("") is None)
    result["counted"] = len(used)
    if result["without_artifacts"] and set(spec.get("figures", [])) - {"iterations"}:
        print(f"[demon_lab.report] {name}: {len(result['without_artifacts'])} of {len(used)} counted runs have no "
              f"artifacts on this machine; the figures drawn from artifacts leave them out", file=sys.stderr)
    paths = {"md": out_dir / f"{name}.md", "csv": out_dir / f"{name}.csv", "tex": out_dir / f"{name}.tex"}
    paths["md"].write_text(write_markdown(spec, result, info, failed, paper_rows))
    paths["csv"].write_text(write_csv(spec, result, paper_rows))
    paths["tex"].write_text(write_tex(spec, result, info, paper_rows))
    return {**paths, **{p.name: p for p in figures}}


def run_spec(name: str, directory: Path = ABLATIONS, extra: Sequence[str] = ()) -> int:
    """Runs the spec's commands (finished jobs are skipped by run key); returns the worst exit code."""
    spec = load_spec(name, directory)
    worst = 0
    for overrides in spec.get("runs", []):
        command = [sys.executable, "-m", "demon_lab", "-m", *overrides, *extra]
        print("[demon_lab.report] running: " + " ".join(command[1:]), flush=True)
        worst = max(worst, subprocess.call(command))
    return worst


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.report", description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="ablation specs (ablations/NAME.yaml)")
    parser.add_argument("--all", action="store_true", help="every spec in ablations/")
    parser.add_argument("--run", action="store_true", help="first run the spec's jobs that MLflow lacks")
    parser.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"))
    parser.add_argument("--out", type=Path, default=Path("reports"))
    parser.add_argument("--ablations", type=Path, default=ABLATIONS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    names = sorted(p.stem for p in args.ablations.glob("*.yaml")) if args.all else list(args.names)
    if not names:
        parser.error("name an ablation spec or pass --all")
    status = 0
    for name in names:
        try:
            if args.run:
                status = max(status, run_spec(name, args.ablations))
            paths = report(name, args.tracking_uri, args.out, args.ablations)
        except ReportError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"[demon_lab.report] {name}: " + ", ".join(str(p) for p in paths.values()), flush=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
