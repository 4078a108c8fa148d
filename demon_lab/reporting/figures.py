"""The figures of a study's report (``python -m demon_lab.report``): metrics against the number of
iterative passes (the supplementary's Figure 5 / Table 3), per-pixel depth-error histograms
(Figure 6), per-sample motion-error distributions (Figure 7), each row's qualitative panels, and
the bootstrap flow net's held-apart error against the wall-clock minutes of its stage.

Each figure function takes the study spec and the report's ``build`` result and returns the PNG
files it wrote; those drawn from run artifacts read them where the store keeps them on this machine.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import numbers
import shutil
from collections import defaultdict
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from demon_lab.core.metrics import column
from demon_lab.reporting.tables import cell, has_values, paper_cells
from demon_lab.reporting.visualize import safe_name

FIGURE_KINDS = ("iterations", "pixel_errors", "motion", "qualitative", "time_to_accuracy")
"""Every figure of a study is ``<study>_<kind>[_...].png`` in the report's figures folder."""


def study_figures(folder: Path, study: str) -> list[Path]:
    """The figures of ``study`` in ``folder``: those of a study whose name extends it
    (gt_flow_oracle_long beside gt_flow_oracle) are not among them."""
    return [p for p in sorted(folder.glob(f"{study}_*.png"))
            if p.stem[len(study) + 1:].startswith(FIGURE_KINDS)]


def _axis(key: str) -> str:
    """A figure axis: the metric's label and its unit (``metrics.COLUMNS``)."""
    c = column(key)
    return f"{c.label} ({c.unit})" if c.unit else c.label


def local_artifact(run: Mapping[str, Any], path: str) -> Path | None:
    """A run's artifact as a file here, or None. MLflow's artifact API answers by downloading (a
    copy, or a transfer from a server); the figures only read artifacts already on this machine."""
    from urllib.parse import unquote, urlparse

    parsed = urlparse(str(run["artifact_uri"]))
    root = Path(unquote(parsed.path)) if parsed.scheme in ("file", "") else None
    target = root / path if root is not None else None
    return target if target is not None and target.exists() else None


def _per_sample_rows(run) -> list[dict[str, str]]:
    path = local_artifact(run, "per_sample_metrics.csv")
    if path is None:
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _counted(result: Mapping[str, Any], table: Mapping[str, Any]) -> Iterator[tuple[str, pd.DataFrame]]:
    """(row label, its counted runs by seed) for each row of a table, in the table's order."""
    used = result["used"]
    for row in table["rows"]:
        yield row["label"], used[(used["table"] == table["name"]) & (used["row"] == row["label"])]


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
    datasets = [d for d in spec["datasets"] if has_values(result, table["name"], d)]
    if not datasets or not columns:
        return []
    fig, axes = plt.subplots(1, len(columns), figsize=(3.2 * len(columns), 3.3), squeeze=False)
    iterations = list(range(len(table["rows"])))
    for ax, c in zip(axes[0], columns):
        for dataset in datasets:
            cells = [cell(result, table["name"], dataset, r["label"], c) for r in table["rows"]]
            ax.errorbar(iterations, [x.mean for x in cells], yerr=[0 if math.isnan(x.ci95) else x.ci95 for x in cells],
                        marker="o", ms=3, capsize=2, label=dataset[:24])
        paper = [paper_cells(paper_rows, r.get("paper"), "SUN3D", [c]).get(c, math.nan) for r in table["rows"]]
        if any(math.isfinite(p) for p in paper):
            ax.plot(iterations, paper, "k--", marker="s", ms=3, label="paper (SUN3D)")
        ax.set_title(column(c).label)
        ax.set_xlabel("pass (0: bootstrap net, k: k-th iterative pass)")
        ax.set_xticks(iterations)
        ax.set_ylabel(_axis(c), fontsize=8)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=6)
    fig.suptitle(f"{spec['title']}: error after each pass, mean ± 95 % CI over seeds per test set", fontsize=9)
    return [_save(fig, path / f"{spec['name']}_iterations.png")]


def figure_pixel_histograms(spec, result, path: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    table = spec["tables"][0]
    outputs = []
    for dataset in spec["datasets"]:
        merged: dict[str, dict[str, Any]] = {}
        for label, runs in _counted(result, table):
            for _, run in runs.iterrows():
                artifact = local_artifact(run, "pixel_errors.json")
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
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
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
            ax.set_title(f"{dataset}: per-pixel {column(metric).label} (last bin: above range)", fontsize=8)
            ax.set_xlabel(f"per-pixel {_axis(metric)}", fontsize=8)
            ax.set_ylabel("fraction of pixels")
            ax.legend(fontsize=6)
        fig.suptitle(f"{spec['title']}: per-pixel depth errors on {dataset}, all counted runs "
                     f"(legend: mean, and mean below the last bin)", fontsize=9)
        outputs.append(_save(fig, path / f"{spec['name']}_pixel_errors_{dataset}.png"))
    return outputs


def figure_motion_distributions(spec, result, path: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    table = spec["tables"][0]
    outputs = []
    row_pass = {r["label"]: r.get("metrics", "") for r in table["rows"]}
    used = result["used"]
    tables = {run["run_id"]: _per_sample_rows(run) for _, run in used.drop_duplicates("run_id").iterrows()}
    for dataset in spec["datasets"]:
        values: dict[str, dict[str, list[float]]] = defaultdict(lambda: {"rot_deg": [], "tran_deg": []})
        for label, runs in _counted(result, table):
            for _, run in runs.iterrows():
                rows = [r for r in tables[run["run_id"]] if r.get("dataset") == dataset]
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
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
        for ax, metric, top in zip(axes, ("rot_deg", "tran_deg"), (20.0, 120.0)):
            edges = np.linspace(0, top, 31)
            for label, v in values.items():
                x = np.minimum(np.asarray(v[metric]), top - 1e-9)
                if len(x):
                    ax.hist(x, bins=edges, histtype="step", density=False, weights=np.full(len(x), 1 / len(x)),
                            label=f"{label} (mean {np.mean(v[metric]):.1f}°, n={len(x)})")
            ax.set_title(f"{dataset}: {column(metric).label} per sample (last bin: above range)", fontsize=8)
            ax.set_xlabel(_axis(metric), fontsize=8)
            ax.set_ylabel("fraction of samples")
            ax.legend(fontsize=6)
        fig.suptitle(f"{spec['title']}: per-sample motion errors on {dataset}, all counted runs", fontsize=9)
        outputs.append(_save(fig, path / f"{spec['name']}_motion_{dataset}.png"))
    return outputs


def figure_qualitative(spec, result, path: Path, per_row_limit: int = 1) -> list[Path]:
    """Copies the first depth visualisation of each row's lowest seed (image | GT | prediction |
    flow | normals) for every test set."""
    table = spec["tables"][0]
    outputs = []
    for label, runs in _counted(result, table):
        if runs.empty:
            continue
        run = runs.loc[runs["seed"].idxmin()]
        images = local_artifact(run, "images")
        if images is None:
            continue
        for dataset in spec["datasets"]:
            safe = safe_name(dataset)  # the name visualize.save_visuals gives the set's pictures
            found = sorted(images.glob(f"{safe}_0_*.png"))[:per_row_limit]
            for f in found:
                row_safe = "".join(c if c.isalnum() else "_" for c in label)
                out = path / f"{spec['name']}_qualitative_{row_safe}_{safe}.png"
                shutil.copyfile(f, out)
                outputs.append(out)
    return outputs


def _started(run: Mapping[str, Any]) -> int | None:
    """A job run's start in epoch milliseconds (``mlflow.search_runs`` gives a timestamp), or None."""
    value = run.get("start_time") if hasattr(run, "get") else None
    if isinstance(value, numbers.Real):
        return None if math.isnan(value) else int(value)
    return None if value is None or pd.isna(value) else int(pd.Timestamp(value).value // 1_000_000)


def stage_runs(client, run: Mapping[str, Any], stage: str = "flow1") -> list:
    """The ended MLflow runs that trained the ``stage`` net a job run read, oldest first: the runs of its
    stage key up to the job's own child run, or, where the job found the stage in the cache, those
    started before the job (a stage stopped and resumed has several; a stage trained again later, for
    another job, is not the one this job read); [] if the store has none."""
    from demon_lab.pipeline.tracking import TAG
    from demon_lab.reporting.archive import ENDED  # (the runs an archive carries: a RUNNING one was stopped unawares)

    children = client.search_runs([run["experiment_id"]], filter_string=(
        f"tags.`mlflow.parentRunId` = '{run['run_id']}' and tags.`{TAG}stage` = '{stage}'"))
    key = children[0].data.tags.get(f"{TAG}stage_key") if children else None
    if key is None:
        keys = local_artifact(run, "stage_keys.json")
        key = json.loads(keys.read_text()).get(stage, {}).get("key") if keys is not None else None
    if key is None:
        return [c for c in children[:1] if c.info.status in ENDED]
    experiments = [e.experiment_id for e in client.search_experiments()]
    found = [r for r in client.search_runs(experiments, filter_string=f"tags.`{TAG}stage_key` = '{key}'",
                                           order_by=["attributes.start_time ASC"]) if r.info.status in ENDED]
    if children:
        until = children[0].info.start_time
        return [r for r in found if r.info.start_time <= until]
    started = _started(run)
    return [r for r in found if started is None or r.info.start_time < started]


CURVES_DATASET = "synthetic_sun3d"
"""The held-apart set whose curves the time-to-accuracy figure draws."""

TIME_PANELS = (("flow1", "epe", "held-apart EPE / zero-flow EPE"), ("dm1", "tran_deg", "held-apart translation (°)"))
"""The time-to-accuracy figure's panels: a stage, its held-apart metric, the axis label."""


def _pieces(client, run, key: str) -> list[tuple[int, list[tuple[int, int, float]]]]:
    """A stage run's history of ``key`` as (start in ms, [(timestamp, step, value)]) pieces: one per
    process that trained it. A stage resumed in its own run (its job stopped unawares and run again)
    logs the steps again from its checkpoint: the history is cut where the step falls, and a later
    piece starts where the run's training loss starts again (else at its own first point)."""
    history = sorted((m.timestamp, m.step, m.value) for m in client.get_metric_history(run.info.run_id, key))
    cuts = [i for i in range(1, len(history)) if history[i][1] <= history[i - 1][1]]
    if not cuts:
        return [(run.info.start_time, history)] if history else []
    loss = sorted((m.timestamp, m.step) for m in client.get_metric_history(run.info.run_id, "train/loss"))
    restarts = [loss[i][0] for i in range(1, len(loss)) if loss[i][1] <= loss[i - 1][1]]
    bounds = [0, *cuts, len(history)]
    pieces = []
    for a, b in itertools.pairwise(bounds):
        part = history[a:b]
        if a == 0:
            pieces.append((run.info.start_time, part))
            continue
        between = [t for t in restarts if history[a - 1][0] < t <= part[0][0]]
        pieces.append((between[0] if between else part[0][0], part))
    return pieces


def _joined_curve(client, runs: list, key: str, zero_key: str | None) -> dict[str, Any] | None:
    """One stage's held-apart curve over its runs (oldest first) and their :func:`_pieces`: minutes of
    the stage's training, steps, values (divided by the run's first ``zero_key`` value where given), and
    the runs that gave its points (``runs``). A piece that starts past the first point so far resumed
    the stage: the points it trained again are dropped and its minutes follow the last point kept (the
    pause between the two, and the steps trained again, are not counted); a piece that starts at or
    before it trained the stage again from its start: it replaces them."""
    points: list[tuple[float, int, float]] = []
    used: list = []
    for run in runs:
        zero = client.get_metric_history(run.info.run_id, zero_key) if zero_key is not None else None
        if zero is not None and not (zero and zero[0].value > 0):
            continue
        scale = zero[0].value if zero else 1.0
        for start, part in _pieces(client, run, key):
            first_step = part[0][1]
            resumed = bool(points) and first_step > points[0][1]
            points = [p for p in points if p[1] < first_step] if resumed else []
            used = [*used, run] if resumed else [run]
            offset = points[-1][0] if points else 0.0
            points += [(offset + (t - start) / 60000, step, v / scale) for t, step, v in part]
    if not points:
        return None
    return {"minutes": [m for m, _, _ in points], "steps": [s for _, s, _ in points],
            "values": [v for _, _, v in points], "runs": list(dict.fromkeys(used))}


def _kept(client, run) -> str:
    """Which nets a stage kept: ``step N`` (``keep_best``: the stage run's ``stage/keep_best_step``, or,
    for runs logged before stage runs carried it, the ``stage/<stage>/keep_best_step`` of the job that
    trained it, the stage run's parent), ``last`` where the stage logged its figures without one, ``not
    logged`` where its job stopped before logging them, or is not in the store."""
    from mlflow.exceptions import MlflowException

    from demon_lab.pipeline.tracking import TAG

    if "stage/seconds" in run.data.metrics:
        value = run.data.metrics.get("stage/keep_best_step")
        return "last" if value is None else f"step {int(value):,}"
    parent = run.data.tags.get("mlflow.parentRunId")
    try:
        job = client.get_run(parent) if parent is not None else None
    except MlflowException:
        job = None
    value = job.data.metrics.get(f"stage/{run.data.tags.get(f'{TAG}stage')}/keep_best_step") if job else None
    if value is not None:
        return f"step {int(value):,}"
    return "last" if job is not None and job.info.status == "FINISHED" else "not logged"


def held_apart_curves(spec, result, uri: str, dataset: str = CURVES_DATASET) -> list[list[dict[str, Any]]]:
    """The held-apart curves of each row's bootstrap stages, per panel of :data:`TIME_PANELS`, for the
    rows of the spec's ``curves`` tables (by default its first): one entry per set of rows whose jobs
    read the same stages (``labels``), holding each seed's curve
    (``seed``; ``minutes`` of the stage's training, ``steps`` and ``values``: ``flow1``'s
    ``val/<dataset>/epe`` as a multiple of that set's zero-flow EPE, ``dm1``'s
    ``val/<dataset>/tran_deg``) and which nets the stage kept (``kept``, :func:`_kept`).
    Logged by the stages every ``tracking.val_every_n_steps``."""
    from mlflow.tracking import MlflowClient

    from demon_lab.pipeline.tracking import TAG

    client = MlflowClient(tracking_uri=uri)
    named = spec.get("curves", [spec["tables"][0]["name"]])
    rows = [counted for table in spec["tables"] if table["name"] in named for counted in _counted(result, table)]
    panels = []
    for stage, metric, _ in TIME_PANELS:
        by_stage: dict[str, dict[str, Any]] = {}  # stage key -> the rows reading it, a seed, its runs
        for label, runs in rows:
            for _, run in runs.sort_values("seed").iterrows():
                found = stage_runs(client, run, stage)
                if found:
                    entry = by_stage.setdefault(found[0].data.tags.get(f"{TAG}stage_key", found[0].info.run_id),
                                                {"labels": [], "seed": int(run["seed"]), "runs": found})
                    if label not in entry["labels"]:
                        entry["labels"].append(label)
        lines: dict[tuple[str, ...], list[dict[str, Any]]] = {}
        for entry in by_stage.values():
            curve = _joined_curve(client, entry["runs"], f"val/{dataset}/{metric}",
                                  f"val/{dataset}/zero_flow_epe" if metric == "epe" else None)
            if curve is not None:
                used = curve.pop("runs")
                lines.setdefault(tuple(entry["labels"]), []).append(
                    {"seed": entry["seed"], **curve, "kept": _kept(client, used[-1])})
        panels.append([{"labels": list(labels), "seeds": sorted(seeds, key=lambda c: c["seed"])}
                       for labels, seeds in lines.items()])
    return panels


def curve_end_points(curves: list[list[dict[str, Any]]]) -> pd.DataFrame:
    """One row per stage, set of rows and seed of :func:`held_apart_curves`: the curve's first point,
    its last and its best (lowest) point with their step and minute, and which nets the stage kept."""
    def point(c: dict[str, list], i: int) -> str:
        return f"{c['values'][i]:.3f} (step {c['steps'][i]:,}, {c['minutes'][i]:.1f} min)"

    rows = []
    for (stage, metric, _), lines in zip(TIME_PANELS, curves, strict=True):
        what = "EPE / zero flow" if metric == "epe" else "translation (°)"
        for line in lines:
            for c in line["seeds"]:
                rows.append({"stage": stage, "held-apart": what, "rows": "; ".join(line["labels"]), "seed": c["seed"],
                             "first": point(c, 0), "last": point(c, -1),
                             "best": point(c, int(np.nanargmin(c["values"]))), "kept": c["kept"]})
    return pd.DataFrame(rows, columns=["stage", "held-apart", "rows", "seed", "first", "last", "best", "kept"])


def figure_time_to_accuracy(curves: list[list[dict[str, Any]]], spec, path: Path,
                            dataset: str = CURVES_DATASET) -> list[Path]:
    """:func:`held_apart_curves` against the minutes since each stage's run started, one line per seed
    (rows whose jobs read the same stages share them): how soon a design leaves the zero-flow plateau
    (``flow1``), and how soon its motion reads the flow (``dm1``, where the rows trained it)."""
    import matplotlib.pyplot as plt

    panels = [i for i, lines in enumerate(curves) if lines]
    if not panels:
        return []
    fig, axes = plt.subplots(1, len(panels), figsize=(7.5 * len(panels), 4.2), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    firsts = list(dict.fromkeys(line["labels"][0] for lines in curves for line in lines))  # a row: one colour
    for ax, i in zip(axes[0], panels, strict=True):
        stage, metric, ylabel = TIME_PANELS[i]
        for line in curves[i]:
            colour = colours[firsts.index(line["labels"][0]) % len(colours)]
            for n, c in enumerate(line["seeds"]):
                ax.plot(c["minutes"], c["values"], color=colour, lw=1.2, marker="o", ms=2,
                        label="; ".join(line["labels"]) if n == 0 else None)
        if metric == "epe":
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
            ax.axhline(0.5, color="k", lw=0.8, ls="--")
        ax.set_xlabel(f"wall-clock minutes of the {stage} stage "
                      "(held-apart scoring included; a resumed stage's runs joined)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    shown = " and ".join(("flow1's held-apart EPE", "dm1's held-apart translation")[i] for i in panels)
    fig.suptitle(f"{spec['title']}\n{shown} on {dataset}'s validation scenes against time, one line per seed "
                 "(rows that share a stage share its lines)", fontsize=8)
    return [_save(fig, path / f"{spec['name']}_time_to_accuracy.png")]
