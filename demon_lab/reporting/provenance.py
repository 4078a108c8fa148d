"""What a report's numbers come from: the design each row measures, its configuration's digest,
the code that ran it and the runs themselves.

A design is named by its departures from DeMoN's design: the model options that give a net a prior
or a correlation front, a net of one's own in a slot of the chain (``model.nets.SLOT``), and the
stage options that a stage of DeMoN's schedule leaves out (2-D
layers first, fresh scenes, keeping the best held-apart nets, ...), each where it is off its
default. The designs the project ships at the ``cpu`` scale (the profile with its classical priors,
``design=learned``) are composed from ``conf/`` and named when a run's departures are exactly
theirs; any other set is named by the nearest one and what differs from it.

A report row whose runs measure different designs is refused (:class:`DesignMixError`): its mean
would describe no design. Runs of other code or scene-generator versions never share a row either:
the report counts only this checkout's (:func:`demon_lab.reporting.selection.current_versions`).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Mapping, Sequence
from typing import Any

import pandas as pd

from demon_lab.pipeline.identity import digest, is_semantic, portable
from demon_lab.pipeline.methods import METHODS
from demon_lab.pipeline.schema import PRIOR_KEYS
from demon_lab.reporting.archive import IMPORTED_FROM
from demon_lab.reporting.tables import markdown_table

DEMON = "DeMoN's design"
DEPARTURE_MODEL_KEYS = tuple(f"model.{k}" for k in (*PRIOR_KEYS, "correlation", "motion_fit", "fit_weights",
                                                     "fit_starts", "flow_refine"))
"""The model options that depart from DeMoN's nets where set."""
DEPARTURE_LOSS_KEYS = ("loss.fit_residual", "loss.flow_match", "loss.fit_weight")
"""The loss weights that depart from DeMoN's losses where set (and not 0)."""
DEPARTURE_STAGE_OPTION = re.compile(
    r"schedule\.stages\.\w+\.(layers_first|restarts|easy_first|level5_fade|gt_flow_warmup|fresh_scenes|keep_best|joint)$")
"""The stage options a stage of DeMoN's schedule leaves out, which depart from it where set."""
OFF = ("None", "nan", "0", "0.0", "")
OFF_BY_KEY = {"model.fit_weights": "learned"}
"""A departure's own off value beside :data:`OFF` (the motion fit's weights are the nets' unless uniform)."""
NAMED = {"the cpu profile": ["scale=cpu"], "the learned design": ["scale=cpu", "design=learned"],
         "the fit design": ["scale=cpu", "design=fit"]}
"""The designs the project ships at the cpu scale, as the overrides that compose them."""
SHIPPED = {"profile": ("the cpu profile", DEMON), "learned": ("the learned design",), "fit": ("the fit design",)}
"""A study spec's ``design``, by short name, and the designs whose runs its rows count (its commands
compose it): ``profile`` is a scale's own design (``design`` unset): the cpu profile at the ``cpu``
scale, DeMoN's design at the ``smoke`` and ``paper`` scales; ``learned`` is ``design=learned``, ``fit``
``design=fit``."""
COMMIT_TAG = "tags.mlflow.source.git.commit"
CLASSICAL = "no net (a classical method)"


class DesignMixError(ValueError):
    """A report row whose runs measure more than one design (one line, naming the row and designs)."""


def departures(params: Mapping[str, Any]) -> dict[str, str]:
    """A run's departures from DeMoN's design: its params (dotted keys, string values) that
    :data:`DEPARTURE_MODEL_KEYS`, :data:`DEPARTURE_LOSS_KEYS` or :data:`DEPARTURE_STAGE_OPTION` name, and a
    net of its own (``model.nets.SLOT._target_`` and its arguments), where not off."""
    out = {}
    for key, value in params.items():
        departs = (key in DEPARTURE_MODEL_KEYS or key in DEPARTURE_LOSS_KEYS or DEPARTURE_STAGE_OPTION.match(key)
                   or key.startswith("model.nets."))
        if departs and str(value) not in OFF and str(value) != OFF_BY_KEY.get(key):
            out[key] = str(value)
    return dict(sorted(out.items()))


@functools.cache
def named_designs() -> dict[str, dict[str, str]]:
    """The departures of each design in :data:`NAMED`, composed from the package's configs; also
    inside a running Hydra app (a job that prints its study's rows), whose global state is set
    aside while they compose and put back after."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup
    from omegaconf import OmegaConf

    from demon_lab.pipeline.config import register_resolvers
    from demon_lab.pipeline.tracking import flatten
    from demon_lab.resources import CONF

    register_resolvers()
    designs = {}
    running = get_gh_backup()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(str(CONF), version_base="1.3"):
            for name, overrides in NAMED.items():
                cfg = compose("config", overrides)
                designs[name] = departures(flatten(OmegaConf.to_container(cfg, resolve=True)))
    finally:
        restore_gh_from_backup(running)
    return designs


def design_name(found: Mapping[str, str]) -> str:
    """``found`` departures as a name: DeMoN's design or a shipped one where they are exactly its,
    else the nearest of these with what differs (``name with k=v``, ``name without k``)."""
    candidates = {DEMON: {}, **named_designs()}
    for name, wanted in candidates.items():
        if dict(found) == wanted:
            return name

    def distance(wanted: Mapping[str, str]) -> int:
        return len(set(wanted.items()) ^ set(found.items()))

    name, wanted = min(candidates.items(), key=lambda item: distance(item[1]))
    changed = [f"{k}={v}" for k, v in found.items() if wanted.get(k) != v]
    dropped = [k for k in wanted if k not in found]
    return name + "".join([f" with {', '.join(changed)}" if changed else "",
                           f" without {', '.join(dropped)}" if dropped else ""])


def run_design(params: Mapping[str, str]) -> str:
    """The design a run measures (its logged params): :func:`design_name` of its departures, or
    :data:`CLASSICAL` for a classical method whose numbers no net enters."""
    runs_chain = params.get("method", "demon") not in METHODS or METHODS[params.get("method", "demon")].runs_chain
    return design_name(departures(params)) if runs_chain else CLASSICAL


def shipped(params: Mapping[str, str]) -> str | None:
    """The short name (:data:`SHIPPED`) of the shipped design a run or job measures, or None."""
    found = run_design(params)
    return next((short for short, names in SHIPPED.items() if found in names), None)


def config_design(cfg: Any) -> str | None:
    """The short name of the shipped design a composed config measures (its ``hydra`` node aside),
    or None: what picks a study's spec for a job or a sweep (``NAME_learned`` for the learned design)."""
    from omegaconf import OmegaConf

    from demon_lab.pipeline.tracking import flatten

    mine = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    return shipped(flatten(OmegaConf.to_container(mine, resolve=True)))


def run_params(run: pd.Series) -> dict[str, str]:
    """A run of ``mlflow.search_runs``'s frame: its params (dotted keys), as logged."""
    return {k.removeprefix("params."): v for k, v in run.items()
            if k.startswith("params.") and isinstance(v, str)}


def config_digest(params: Mapping[str, str]) -> str:
    """A digest of a run's composed configuration as it logged it, without its seed and the keys
    that change no result, bundled files named rather than located (the keys' rule:
    :func:`demon_lab.pipeline.identity.portable`): the runs of one row at different seeds, and from
    different installs of the package, share it."""
    return digest(portable({k: v for k, v in params.items() if k != "seed" and is_semantic(k)}))


def rows(spec: Mapping[str, Any], used: pd.DataFrame) -> list[dict[str, Any]]:
    """Per table row with counted runs: its design, config digest(s), seeds and run ids. A row whose
    runs measure two designs raises :class:`DesignMixError`."""
    out = []
    for table in spec["tables"]:
        for row in table["rows"]:
            runs = used[(used["table"] == table["name"]) & (used["row"] == row["label"])]
            if runs.empty:
                continue
            params = [run_params(r) for _, r in runs.iterrows()]
            designs = [run_design(p) for p in params]
            if len(set(designs)) > 1:
                seeds = {d: [str(s) for s, dd in zip(runs["seed"], designs, strict=True) if dd == d]
                         for d in dict.fromkeys(designs)}
                mixed = "; ".join(f"{d} (seed {', '.join(s)})" for d, s in seeds.items())
                raise DesignMixError(f"{spec['name']}: table {table['name']}, row {row['label']!r} has runs of "
                                     f"different designs, which one row cannot average: {mixed}")
            out.append({"table": table["name"], "row": row["label"], "design": designs[0],
                        "config": ", ".join(dict.fromkeys(config_digest(p) for p in params)),
                        "seeds": ", ".join(str(s) for s in runs["seed"]),
                        "runs": " ".join(first_ids(runs))})
    return out


def first_ids(runs: pd.DataFrame) -> list[str]:
    """The runs' ids as first tracked: an imported run's original id (``demon_lab.imported_from``,
    :mod:`demon_lab.reporting.archive`), so that a report redrawn from an archive names the same runs."""
    imported = runs.get(f"tags.{IMPORTED_FROM}")
    if imported is None:
        return list(runs["run_id"])
    return [i if isinstance(i, str) and i else r for i, r in zip(imported, runs["run_id"], strict=True)]


def commits(used: pd.DataFrame) -> str:
    """The code commits the counted runs were made with (as MLflow tagged them)."""
    installed = "not recorded (runs of an installed package, not a checkout)"
    if COMMIT_TAG not in used.columns:
        return installed
    found = used[COMMIT_TAG].dropna().unique()
    lacking = int(used[COMMIT_TAG].isna().sum())
    text = ", ".join(c[:12] for c in sorted(found)) or installed
    return text + (f"; {lacking} run(s) of an installed package, not a checkout" if lacking and len(found) else "")


def markdown(entries: Sequence[Mapping[str, Any]], used: pd.DataFrame, versions: str,
             archives: Sequence[str] = ()) -> str:
    """The report's provenance section (``archives``: the run archives beside the report that hold
    runs of its experiments, relative to it)."""
    where = ("the run archive(s) " + ", ".join(f"[{a}]({a})" for a in archives) + " beside this report "
             f"(`python -m demon_lab.report --import reports/{archives[0]}` adds one's runs to a store)"
             if archives else "the MLflow store the report read")
    lines = ["## Provenance\n\n",
             f"- designs: {'; '.join(dict.fromkeys(e['design'] for e in entries)) or '-'}\n",
             f"- code: commit {commits(used)}; {versions}\n",
             f"- runs: {where}; config: a digest of each row's composed configuration (the seed aside)\n\n",
             markdown_table(["table", "row", "design", "config", "seeds", "run ids"],
                            [[e["table"], e["row"], e["design"], e["config"], e["seeds"], e["runs"]]
                             for e in entries]) + "\n"]
    return "".join(lines)


def footer(entries: Sequence[Mapping[str, Any]], used: pd.DataFrame, versions: str) -> str:
    """One line for a figure: its designs, code and versions."""
    designs = "; ".join(dict.fromkeys(e["design"] for e in entries)) or "-"
    return f"{designs} | commit {commits(used)} | {versions}"


def stamp_figure(path, line: str) -> None:
    """Add ``line`` under a report figure, and to its PNG metadata (``Description``)."""
    from PIL import Image, ImageDraw, PngImagePlugin

    image = Image.open(path).convert("RGB")
    strip = 14 * (1 + len(line) * 6 // max(image.width, 1))
    stamped = Image.new("RGB", (image.width, image.height + strip), "white")
    stamped.paste(image, (0, 0))
    draw = ImageDraw.Draw(stamped)
    per_line = max(1, image.width // 6)
    for i in range(0, len(line), per_line):
        draw.text((4, image.height + 1 + 14 * (i // per_line)), line[i:i + per_line], fill="dimgray")
    info = PngImagePlugin.PngInfo()
    info.add_text("Description", line)
    stamped.save(path, pnginfo=info)
