"""Result tables in the docs, written by the report command from the committed reports.

A page holds a table between two markers::

    <!-- report: learned_design bootstrap synthetic_sun3d -->
    ...
    <!-- /report -->

naming a study, one of its tables and a test set. ``python -m demon_lab.report --docs`` writes each
such block from ``reports/<study>.csv`` (the cells the report command wrote: mean ± 95 % half-width,
n), so a number a reader sees in the docs is a report's cell, and :func:`stale_blocks` names the
blocks that differ from what their report says now (a test runs it on README and docs/).
``<!-- report: bench SECTION K -->`` is the K-th table (from 1) of ``reports/bench.md``'s section
SECTION, which ``python -m demon_lab.bench SECTION`` writes, and ``<!-- report: data_stats table1 1 -->``
the presets' camera statistics beside the supplementary's Table 1 in ``reports/data_stats.md``
(:func:`camera_statistics`, ``python -m demon_lab.report --data-stats``);
``<!-- report: diagnose NAME SET -->`` is the per-pass diagnosis of test set SET in
``reports/diagnose/NAME_seed*.json``, which ``python -m demon_lab.diagnose seed=S --out FILE`` writes.
"""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterable
from pathlib import Path

from demon_lab.core.metrics import column
from demon_lab.reporting.tables import Cell, markdown_table
from demon_lab.reporting.writers import cell_text
from demon_lab.resources import STUDIES

PRESETS = {"synthetic_scenes11": "Scenes11", "synthetic_sun3d": "SUN3D", "synthetic_mvs": "MVS"}
"""The synthetic presets and the training set of the paper's Table 1 whose camera statistics each imitates."""

BLOCK = re.compile(r"(<!-- report: (\S+) (\S+) (\S+) -->\n)(.*?)(<!-- /report -->)", re.S)


def camera_statistics(reports: Path) -> str:
    """``reports/data_stats.md``: the presets' rotation and triangulation angles (mean ± standard
    deviation over the pairs the data_stats command rendered) beside the supplementary's Table 1."""
    import json

    with open(STUDIES / "paper_table1.csv", newline="") as f:
        paper = {r["dataset"]: r for r in csv.DictReader(f)}
    lines = ["# The synthetic presets' camera statistics beside the supplementary's Table 1", "",
             "Written by `python -m demon_lab.report --data-stats` from `reports/data_stats_<preset>.json`, which "
             "`python -m demon_lab.data_stats data=<preset> n=500 out=reports/data_stats_<preset>.json` writes, and "
             "`ablations/paper_table1.csv` (the supplementary's Table 1). Angles in degrees, mean ± standard "
             "deviation over the pairs.", "", "## table1", "",
             "| preset | pairs | rotation (°), mean ± std | paper | triangulation (°), mean ± std | paper "
             "| paper dataset |", "|---|---|---|---|---|---|---|"]
    for preset, dataset in PRESETS.items():
        stats = json.loads((Path(reports) / f"data_stats_{preset}.json").read_text())
        ref = paper[dataset]
        lines.append(f"| `{preset}` | {stats['n_pairs']} | {stats['rot_mean_deg']:.2f} ± {stats['rot_std_deg']:.2f} | "
                     f"{ref['rot_mean_deg']} ± {ref['rot_std_deg']} | {stats['tri_mean_deg']:.2f} ± "
                     f"{stats['tri_std_deg']:.2f} | {ref['tri_mean_deg']} ± {ref['tri_std_deg']} | {dataset} |")
    return "\n".join(lines) + "\n"


COPIED = {"bench": "python -m demon_lab.bench {section}", "data_stats": "python -m demon_lab.report --data-stats"}
"""The reports whose tables a block copies as written (``<!-- report: NAME SECTION K -->``: the K-th
table, from 1, of the section ``## SECTION`` of ``reports/NAME.md``), and the command that writes each."""


def render_copied(reports: Path, name: str, section: str, index: str) -> str:
    """The ``index``-th table of ``reports/<name>.md``'s section ``## section``, as written."""
    text = (Path(reports) / f"{name}.md").read_text()
    found = re.search(rf"^## {re.escape(section)}\n(.*?)(?=^## |\Z)", text, re.S | re.M)
    tables = re.findall(r"(?:^\|.*\n)+", found.group(1), re.M) if found else []
    if not 0 < int(index) <= len(tables):
        raise ValueError(f"{reports}/{name}.md: section {section!r} has no table {index}")
    command = COPIED[name].format(section=section)
    return (tables[int(index) - 1] + f"\n*From [reports/{name}.md](reports/{name}.md), section `{section}`; "
            f"`{command}` writes it, `python -m demon_lab.report --docs` this table.*\n")


def render_diagnose(reports: Path, name: str, dataset: str) -> str:
    """Per seed: pass 0's flow EPE, then per iterative pass the EPE of the flow the previous pass's
    depth and motion induce (the iterative flow net's prior) and of the pass's own flow."""
    import json

    files = sorted((Path(reports) / "diagnose").glob(f"{name}_seed*.json"))
    if not files:
        raise ValueError(f"{reports}/diagnose: no {name}_seed*.json")
    rows = []
    for path in files:
        found = json.loads(path.read_text())
        passes = [p for p in found["passes"][dataset] if isinstance(p["pass"], int)]  # (not the refined depth)
        cells = [f"{passes[0]['epe']:.3f}"] + [f"{p['prior_epe']:.3f} / {p['epe']:.3f}" for p in passes[1:]]
        rows.append((path.stem.rsplit("_seed", 1)[1], cells))
    width = max(len(cells) for _, cells in rows)
    header = ["seed", "pass 0 EPE", *[f"pass {k}: prior EPE / EPE" for k in range(1, width)]]
    table = markdown_table(header, [[seed, *cells] for seed, cells in rows], "lr")
    source = (f"*From reports/diagnose/{name}_seed*.json, {dataset}; `python -m demon_lab.diagnose seed=S --out FILE` "
              "writes one, `python -m demon_lab.report --docs` this table.*")
    return table + "\n\n" + source + "\n"


def render(reports: Path, study: str, table: str, dataset: str) -> str:
    """The Markdown table of ``study``'s ``table`` on ``dataset``, from ``reports/<study>.csv``: one line
    per row with n and each metric's cell as the report prints it (mean ± 95 % half-width; the mean
    alone for one seed; "(n = k)" where fewer seeds than the row's logged a value), and a last line
    naming its source (``data_stats table1 presets``: :func:`render_camera_statistics`)."""
    if study in COPIED:
        return render_copied(reports, study, table, dataset)
    if study == "diagnose":
        return render_diagnose(reports, table, dataset)
    path = Path(reports) / f"{study}.csv"
    with open(path, newline="") as f:
        cells = [r for r in csv.DictReader(f) if r["table"] == table and r["dataset"] == dataset]
    if not cells:
        raise ValueError(f"{path}: no table {table!r} on {dataset!r}")
    rows = list(dict.fromkeys(r["row"] for r in cells))
    metrics = list(dict.fromkeys(r["metric"] for r in cells))
    body = []
    for row in rows:
        mine = {r["metric"]: r for r in cells if r["row"] == row}
        n = max(int(r["n"]) for r in mine.values())
        if n == 0:
            continue
        text = [cell_text(Cell(mean=_float(mine[m]["mean"]), ci95=_float(mine[m]["ci95"]), n=int(mine[m]["n"])),
                          n, " ± ", " (n = {})") for m in metrics]
        body.append([row, str(n), *text])
    lines = [markdown_table(["row", "n", *[column(m).label for m in metrics]], body), ""]
    lines.append(f"*From [reports/{study}.md](reports/{study}.md), table `{table}`, {dataset}; "
                 f"`python -m demon_lab.report {study}` writes the report, `python -m demon_lab.report --docs` "
                 "this table.*")
    return "\n".join(lines) + "\n"


def _float(text: str) -> float:
    """A number of a report's CSV; NaN where the cell is empty (a value that is not defined)."""
    return float(text) if text.strip() else math.nan


def _relink(text: str, page: Path, root: Path) -> str:
    """The source line's link, relative to ``page``."""
    prefix = "../" * len(page.resolve().parent.relative_to(root.resolve()).parts)
    return text.replace("](reports/", f"]({prefix}reports/")


def write_blocks(page: Path, root: Path) -> int:
    """Rewrite every block of ``page`` from its report; returns how many blocks it holds."""
    text = page.read_text()
    found = 0

    def fill(m: re.Match) -> str:
        nonlocal found
        found += 1
        body = _relink(render(root / "reports", m.group(2), m.group(3), m.group(4)), page, root)
        return m.group(1) + body + m.group(6)

    new = BLOCK.sub(fill, text)
    if new != text:
        page.write_text(new)
    return found


def stale_blocks(pages: Iterable[Path], root: Path) -> list[str]:
    """The blocks of ``pages`` whose table differs from what their report says now."""
    stale = []
    for page in pages:
        for m in BLOCK.finditer(page.read_text()):
            wanted = _relink(render(root / "reports", m.group(2), m.group(3), m.group(4)), page, root)
            if m.group(5) != wanted:
                stale.append(f"{page.relative_to(root)}: {m.group(2)} {m.group(3)} {m.group(4)}")
    return stale


def pages(root: Path) -> list[Path]:
    """The pages whose blocks ``--docs`` writes: README.md and docs/*.md."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]
