"""Study specs (``ablations/NAME.yaml``): reading one, with its ``extends`` and ``design`` applied,
and finding the study that reports an experiment. The format is described in
:mod:`demon_lab.reporting.report` and docs/running.md."""

from __future__ import annotations

import csv
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from demon_lab.resources import STUDIES

FIGURES = ("iterations", "pixel_histograms", "motion_distributions", "qualitative", "time_to_accuracy")


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
    unknown = dropped - {row["label"] for table in spec.get("tables", []) for row in table["rows"]}
    if unknown:
        raise ReportError(f"{_shown(name, directory)}: drop_rows: {sorted(unknown)} are rows of no table of {base}")
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
    names = [table["name"] for table in spec["tables"]]
    curves = spec.get("curves", names[:1])
    if not isinstance(curves, list) or not curves or not set(curves) <= set(names):
        raise ReportError(f"{_shown(name, directory)}: curves: expected a list of the spec's table names "
                          f"({', '.join(names)}), got {curves!r}")
    spec["name"] = name
    return spec


def paper_numbers(path: Path = STUDIES / "paper_numbers.csv") -> list[dict[str, str]]:
    # Kept as text rows (csv): pandas would turn the table numbers ("2") and empty cells into numbers
    # and NaN, and paper_cells compares and reads them as the CSV spells them.
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
