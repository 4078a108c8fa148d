"""Tables: the terminal tables of the main command's results, the diagnosis and the data
statistics, the Markdown tables of the reports, the docs and the benchmark (:func:`markdown_table`: pandas
writes them), and the cells of a study's result tables (:func:`demon_lab.reporting.selection.build`) with
the paper's values beside them, which the report's tables and figures read.

Column names come from :data:`demon_lab.core.metrics.COLUMNS` (their ``text`` form).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, NamedTuple

from demon_lab.core.metrics import RESULT_COLUMNS, column


def text_table(header: Sequence[str], rows: Iterable[Sequence[str]], left: int = 2) -> str:
    """A terminal table: the first ``left`` columns (names: test set, pass) left-aligned, the
    numbers after them right-aligned."""
    rows = [list(r) for r in rows]
    widths = [max(len(r[i]) for r in [list(header), *rows]) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        return "  ".join(c.rjust(w) if i >= left else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows)])


ALIGN = {"l": "left", "r": "right", "c": "center"}


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[str]], align: str = "") -> str:
    """A Markdown (pipe) table of cells' text, written by pandas (``DataFrame.to_markdown``, through
    tabulate), without a final newline. The cells stay as given (no number parsing: ``0.100`` stays
    ``0.100``; tabulate trims their outer spaces), a ``|`` in one escaped. ``align``: a letter per column,
    ``l`` (left), ``r`` (right) or ``c`` (centred), which the separator line marks with ``:``; columns past
    its end are left-aligned."""
    import pandas as pd

    def text(cells: Sequence[str]) -> list[str]:
        return [str(c).replace("|", r"\|") for c in cells]

    frame = pd.DataFrame([text(r) for r in rows], columns=range(len(header)), dtype=object)
    return frame.to_markdown(index=False, headers=text(header), disable_numparse=True,
                             colalign=[ALIGN[a] for a in align.ljust(len(header), "l")])


def number(value: float, digits: int = 3) -> str:
    """A table cell: ``-`` for a missing or non-finite value, else fixed point."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def results_table(summary: Mapping[str, Mapping[str, float]], passes: Sequence[int | str]) -> str:
    """The main command's table: one row per test set and pass (``k``: the k-th iterative pass,
    ``refined``: the refinement net's depth, ``priors``: the classical priors alone, no net,
    ``baseline``: a classical method's summary)."""
    header = ["test set", "pass", *[column(key).text for key in RESULT_COLUMNS]]
    rows = []
    for name, values in summary.items():
        for it in passes:
            prefix = {"refined": "refined/", "priors": "priors/", "baseline": ""}.get(str(it), f"it{it}/")
            rows.append([name, str(it), *[number(values.get(f"{prefix}{key}", math.nan)) for key in RESULT_COLUMNS]])
    return text_table(header, rows)


SWEEP_COLUMNS = ("l1_inv", "sc_inv", "rot_deg", "tran_deg", "epe")
"""The metrics a sweep's table of its jobs shows (of each job's last pass, on one test set)."""
SWEEP_TEST_SET = "synthetic_sun3d"
"""The test set a sweep's table shows where its jobs have it (else the first, by name)."""


def sweep_table(jobs: Sequence[Mapping[str, Any]], metrics: Mapping[str, Mapping[str, float]]) -> str:
    """The table a sweep prints when its jobs end: one row per job, the overrides that differ between
    its jobs as columns (all of them if none does), its status (finished, skipped: an earlier
    FINISHED run, FAILED), and :data:`SWEEP_COLUMNS` of the job's last pass (``pass``: its
    ``iterations``, ``baseline`` for a classical method) on one test set, read from its run's metrics
    (``metrics``: run id -> name -> value). ``jobs``: ``overrides``, ``status``, ``run_id`` (None for a
    failed job) and ``pass``."""
    values = [dict(o.lstrip("+~").split("=", 1) for o in job["overrides"] if "=" in o) for job in jobs]
    keys = list(dict.fromkeys(k for v in values for k in v))
    varying = [k for k in keys if len({v.get(k) for v in values}) > 1] or keys
    logged = {name.split("/")[1] for job in jobs for name in metrics.get(job.get("run_id") or "", {})
              if name.startswith("test/")}
    test_set = SWEEP_TEST_SET if SWEEP_TEST_SET in logged else min(logged, default="-")
    header = [*varying, "status", "pass", *[column(c).text for c in SWEEP_COLUMNS]]
    rows = []
    for job, given in zip(jobs, values, strict=True):
        found = metrics.get(job.get("run_id") or "", {})
        prefix = "" if job["pass"] == "baseline" else f"it{job['pass']}/"
        rows.append([*(given.get(k, "-") for k in varying), job["status"], str(job["pass"]),
                     *(number(found.get(f"test/{test_set}/{prefix}{c}", math.nan)) for c in SWEEP_COLUMNS)])
    return f"the sweep's jobs on {test_set}:\n" + text_table(header, rows, left=len(varying) + 2)


class Cell(NamedTuple):
    """One aggregated cell as plain Python numbers (``csv`` writes numpy floats as ``np.float64(...)``)."""

    mean: float = math.nan
    std: float = math.nan
    ci95: float = math.nan
    n: int = 0
    values: tuple[float, ...] = ()


def cell(result: Mapping[str, Any], table: str, dataset: str, row: str, col: str) -> Cell:
    """A cell of ``build``'s result; an empty one (n = 0) where no counted run logged a finite value."""
    cells = result["cells"]  # a pandas DataFrame indexed by (table, dataset, row, column)
    key = (table, dataset, row, col)
    if key not in cells.index:
        return Cell()
    c = cells.loc[key]
    return Cell(float(c["mean"]), float(c["std"]), float(c["ci95"]), int(c["n"]), tuple(map(float, c["values"])))


def has_values(result: Mapping[str, Any], table: str, dataset: str) -> bool:
    index = result["cells"].index
    return bool(((index.get_level_values("table") == table) & (index.get_level_values("dataset") == dataset)).any())


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
                paper = column(c).paper
                text = r.get(paper, "") if paper else ""
                if text not in ("", None) and c not in out:
                    out[c] = float(text)
    return out
