"""Terminal tables: the main command's results, the diagnosis, the data statistics.

Column names come from :data:`demon_lab.metrics.COLUMNS` (their ``text`` form).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

from demon_lab.metrics import RESULT_COLUMNS, column


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
