"""Tables: the terminal tables of the main command's results, the diagnosis and the data
statistics, and the cells of a study's result tables (:func:`demon_lab.reporting.report.build`) with the
paper's values beside them, which the report's tables and figures read.

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


def number(value: float, digits: int = 3) -> str:
    """A table cell: ``-`` for a missing or non-finite value, else fixed point."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def results_table(summary: Mapping[str, Mapping[str, float]], passes: Sequence[int | str]) -> str:
    """The main command's table: one row per test set and pass (``k``: the k-th iterative pass,
    ``refined``: the refinement net's depth, ``baseline``: a classical method's summary)."""
    header = ["test set", "pass", *[column(key).text for key in RESULT_COLUMNS]]
    rows = []
    for name, values in summary.items():
        for it in passes:
            prefix = {"refined": "refined/", "baseline": ""}.get(str(it), f"it{it}/")
            rows.append([name, str(it), *[number(values.get(f"{prefix}{key}", math.nan)) for key in RESULT_COLUMNS]])
    return text_table(header, rows)


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
