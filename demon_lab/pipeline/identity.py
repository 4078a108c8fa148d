"""What makes two runs, stages, sweeps or rendered data sets the same: their keys, in one place.

Every key is a short hash of a JSON description plus :func:`versions` (the training code's and the
scene generator's), so a change that alters results makes older entries stale instead of reusing
them:

- run key (:func:`run_key`): a job's resolved configuration without the keys that do not change
  what it computes (:data:`NON_SEMANTIC`; where its scenes are cached: :func:`without_render_cache`);
  a FINISHED run with the same key is skipped.
- stage key (:func:`stage_key`): what determines one training stage's weights (its description,
  :func:`describe_stage`, chained through the keys of its upstream stages), with the CPU threads it
  trains with (:func:`cpu_threads`); a net of one's own by its class, arguments and source
  (:func:`plugin_identity`).
- sweep key (:func:`sweep_key`): a multirun's experiment and its result-changing overrides; the
  same sweep re-issued continues its MLflow parent run.

One rule keeps the keys of older configs as they were when an option is added: the option declares
its neutral value in :data:`NEUTRAL` (the value under which a job computes what it computed before
the option existed), and every key leaves an option at its neutral value out
(:func:`leave_out_neutral`). A stage option that the shipped schedule does not write needs no entry:
a stage key hashes the stage's own config node, where an option left unset is absent.

A rendered synthetic data set's cache folder has a key of its own, from the generator
(:func:`demon_lab.data.synthetic.render_key`), so that the data layer needs nothing above it.

:data:`NON_SEMANTIC` also decides the job's output folder: ``hydra.job.config.override_dirname
.exclude_keys`` in ``conf/config.yaml`` is the job's overrides that it holds
(``${non_semantic_overrides:}``, :mod:`demon_lab.pipeline.config`).
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from demon_lab.core.execution import normalize_precision, resolve_accelerator
from demon_lab.core.losses import OPTIONAL_WEIGHTS

CODE_VERSION = 2
"""Bump when the training code changes what a stage produces."""

EXECUTION_KEYS = ("channels_last", "compile")
"""Keys of ``model`` that say how the nets run, not what they are (so in :data:`NON_SEMANTIC`)."""

NEUTRAL: dict[str, Any] = {
    "model.compat": None, "model.weights": None, "model.correlation": None,
    "model.flow1_prior": None, "model.dm1_prior": None, "model.flow2_prior": None, "model.dm2_prior": None,
    "precision": "32-true", "eval.ceiling": False, "model.motion_fit": None, "loss.fit_residual": 0.0,
    "loss.flow_match": 0.0, "loss.fit_weight": 0.0, "model.flow_refine": None, "schedule.order": None,
    "model.fit_weights": "learned", "model.fit_starts": 0,
    "model.nets": {"flow1": None, "dm1": None, "flow2": None, "dm2": None, "refine": None},
    **{f"model.nets.{slot}": None for slot in ("flow1", "dm1", "flow2", "dm2", "refine")},
}
"""The options added after keys were first written, each with its neutral value (precision by its
normalised name). A new option that every config writes (a key of ``conf/model/demon.yaml``, a
top-level key) adds its line here; nothing else in the keys changes."""

NON_SEMANTIC = ("tracking", "force", "hydra", "cache_dir", "eval.visualize", "eval.point_clouds", "row",
                "data.num_workers", "threads", "trainer.reuse_frozen", "trainer.profile",
                *(f"model.{k}" for k in EXECUTION_KEYS))
"""Config keys (and whole subtrees) that do not change what a job computes: where it logs and
caches, how many loader workers it uses, the nets' memory layout and compilation and whether a
stage reads its frozen nets' outputs from a memo (they change floating-point rounding at most),
what it draws, which report row it is. ``threads`` is here as a setting (its folder name, the sweep
key); the count the nets compute with enters the stage and run keys as :func:`cpu_threads`."""


NEUTRAL_THREADS = 2
"""The CPU thread count that keys leave out: the count of the 2-core machine that every key before
the thread count entered them was measured on (the GOLDEN keys keep their values)."""


def cpu_threads(job) -> dict[str, int]:
    """``{"threads": n}`` for a job whose nets compute on the CPU, with n the threads they compute with
    (``threads``, else torch's count at this moment: the library's default, or the share a parallel
    launcher gave the job), and ``{}`` where n is :data:`NEUTRAL_THREADS` or the nets run on an
    accelerator. A CPU net splits its reductions across the threads, so its rounding and, after a
    stage's steps, its weights depend on n (reports/timing/threads_stage_weights.txt: the profile's
    dm1 after 10 steps differs by 1e-3), so the stage and run keys hold it; ``threads`` itself stays in
    :data:`NON_SEMANTIC` (the output folder, the sweep key)."""
    if resolve_accelerator(job.trainer.accelerator) != "cpu":
        return {}
    if job.threads is not None:
        n = int(job.threads)
    else:
        import torch

        n = torch.get_num_threads()
    return {} if n == NEUTRAL_THREADS else {"threads": n}


def without_render_cache(data: Any) -> Any:
    """A plain data config (or a source list, or a source) with every ``cache_dir`` written as null.

    Where a job's scenes are cached (``data.cache_dir`` or a source's own; ``false``: not at all) does
    not change what it computes (rendering is deterministic), so :func:`is_semantic` says so; the keys
    still hold these entries, as null, their default, so that the keys written before this rule hold."""
    if isinstance(data, dict):
        return {k: None if k == "cache_dir" else without_render_cache(v) for k, v in data.items()}
    if isinstance(data, list):
        return [without_render_cache(v) for v in data]
    return data


def code_version() -> int | str:
    """:data:`CODE_VERSION`, where the code that decides what a stage produces is the code it names;
    else ``"<version>+<digest>"`` (:func:`demon_lab.resources.versioned`): no stage trained by other
    code is ever reused."""
    from demon_lab.resources import versioned

    return versioned(CODE_VERSION, "stage")


def versions() -> dict[str, int | str]:
    """What every key includes besides its description: the training code's version and the
    synthetic scene generator's (new scenes make old stages, runs and sweeps stale), each with the
    digest of its code where that code is not the code the version names (:func:`code_version`,
    :func:`demon_lab.data.synthetic.generator_version`)."""
    from demon_lab.data.synthetic import generator_version

    return {"code_version": code_version(), "generator_version": generator_version()}


def digest(payload: Any, algorithm: str = "sha256", sort_keys: bool = True) -> str:
    """The first 16 hex digits of the hash of ``payload`` as JSON (non-JSON values as ``str``)."""
    blob = json.dumps(payload, sort_keys=sort_keys, default=str)
    return hashlib.new(algorithm, blob.encode()).hexdigest()[:16]


def is_semantic(key: str) -> bool:
    """Whether a dotted config key (or an override's key: ``+a.b``, ``group/option``) changes
    results, i.e. lies outside every :data:`NON_SEMANTIC` subtree."""
    key = key.lstrip("+~").split("=", 1)[0].replace("/", ".")
    if key.startswith("data.") and key.endswith(".cache_dir"):
        return False  # where scenes are cached (without_render_cache): data.cache_dir, data.train.0.cache_dir
    return not any(key == k or key.startswith(k + ".") for k in NON_SEMANTIC)


def portable(value: Any) -> Any:
    """``value`` with the paths of files that ship inside the package written as ``bundled:NAME``:
    where the package is installed does not change what a job computes. A bundled file is one under
    this install's data folder (:data:`demon_lab.resources.DATA`) or under another install's, as a run
    of another environment logged it (``.../demon_lab/data/real/NAME``). The keys and the reports'
    config digests (:func:`demon_lab.reporting.provenance.config_digest`) follow this rule."""
    from demon_lab.resources import DATA

    if isinstance(value, dict):
        return {k: portable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [portable(v) for v in value]
    if isinstance(value, str):
        if value.startswith(str(DATA) + "/"):
            return "bundled:" + value[len(str(DATA)) + 1:]
        inside = "/" + "/".join(DATA.parts[-3:]) + "/"  # /demon_lab/data/real/
        if inside in value and value.startswith("/"):
            return "bundled:" + value.split(inside, 1)[1]
    return value


def leave_out_neutral(plain: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``plain`` (a config or a part of one, as plain containers, at the dotted ``prefix``) without the
    :data:`NEUTRAL` options that hold their neutral value, at any depth; precision compared by its
    normalised name."""
    out = {}
    for key, value in plain.items():
        dotted = prefix + key
        if dotted in NEUTRAL and (normalize_precision(value) if dotted == "precision" else value) == NEUTRAL[dotted]:
            continue
        out[key] = leave_out_neutral(value, dotted + ".") if isinstance(value, dict) else value
    return out


def model_identity(model: dict[str, Any]) -> dict[str, Any]:
    """A plain ``model`` config as keys hold it: its neutral options left out (:func:`leave_out_neutral`),
    without :data:`EXECUTION_KEYS` (which never change a key), a correlation front with its
    :data:`demon_lab.nets.blocks.CORRELATION_VERSION` (from 2 on), each net of one's own by its class,
    arguments and source digest (:func:`plugin_identity`: an edit of its module trains it again), and
    ``weights`` named by the file's content (``sha256:...``), not its path: a
    moved file keeps its keys, a changed one gets new ones."""
    model = {k: v for k, v in leave_out_neutral(model, "model.").items() if k not in EXECUTION_KEYS}
    if model.get("nets"):
        model["nets"] = {slot: plugin_identity(node) for slot, node in model["nets"].items()}
    if model.get("correlation") is not None:  # how the front computes (its rounding): the version since 1
        from demon_lab.nets.blocks import CORRELATION_VERSION

        if CORRELATION_VERSION > 1:
            model["correlation_version"] = CORRELATION_VERSION
    if not model.get("weights"):
        return model
    return {**model, "weights": describe(model["weights"])}


def plugin_identity(node: Mapping[str, Any]) -> dict[str, Any]:
    """A slot's plug-in as keys hold it: its class, its arguments and the digest of its source."""
    from demon_lab.nets.slots import plugin_class, source_digest

    args = {k: v for k, v in node.items() if k != "_target_"}
    return {"class": str(node["_target_"]), "args": args, "source": source_digest(plugin_class(node["_target_"]))}


def describe_stage(job, name: str, upstream: dict[str, str]) -> dict[str, Any]:
    """Everything that determines the result of stage ``name`` of the job's schedule (what its key
    hashes: :func:`stage_key`), ``upstream`` the keys of the stages before it. ``job``: the job's
    settings (:class:`demon_lab.pipeline.settings.JobSettings`); the stage's own config, the model's,
    the loss weights and the data are hashed as the config writes them (``job.config``)."""
    config = copy.deepcopy(dict(job.config))
    schedule, data = config["schedule"], config["data"]
    spec = job.stages[name]
    return {
        "stage": name,
        "stage_config": schedule["stages"][name],
        "optimisation": {k: schedule[k] for k in ("lr_schedule", "weight_decay", "grad_clip")},
        "batch_size": spec.batch_size or data["batch_size"],
        "model": {**_stage_model(model_identity(config["model"]), name, list(job.schedule.stages)),
                  "size": list(data["size"])},  # weights by content
        # Only the weights this stage's loss reads: ablations that change another stage's terms
        # (no_normals for the flow stages, say, or no_sig for a flow stage without sig terms)
        # share this stage.
        # (an optional weight, OPTIONAL_WEIGHTS, where the preset does not write it: its default, left out as neutral)
        "loss": leave_out_neutral({k: float(config["loss"].get(k, OPTIONAL_WEIGHTS.get(k)))
                                   for k in spec.weight_keys()}, "loss."),
        "train_data": without_render_cache(data["train"]),  # not where its scenes are cached
        # the held-apart sets that choose the kept nets (keep_best; left out where the stage keeps its last)
        **({"keep_best_on": without_render_cache(data["val"])} if spec.keep_best else {}),
        "seed": config["seed"],
        "upstream": dict(upstream),
        # the nets' precision where the stage trains (a stage of 0 steps keeps its nets as they are)
        **leave_out_neutral({"precision": normalize_precision(config["precision"])} if int(spec.steps) > 0 else {}),
        # the CPU threads it trains with (their rounding parts the weights), but for the neutral 2
        **(cpu_threads(job) if int(spec.steps) > 0 else {}),
    }


MODEL_OPTION_FROM = {"dm1_prior": "dm1", "flow2_prior": "flow2", "dm2_prior": "dm2", "motion_fit": "dm1",
                     "fit_weights": ("flow1r", "dm1"), "fit_starts": "dm1", "flow_refine": "flow1r"}
"""Model options that change only the nets from a stage on (of a tuple's stages, the one the chain runs
first): the stages before it leave them out of their keys (so flow1 is shared between chains with and
without ``dm1_prior``, flow1 and dm1 between chains with and without ``flow2_prior``, flow1, dm1 and
flow2 between chains with and without ``dm2_prior``, and flow1 between chains with and without
``motion_fit`` or ``flow_refine`` (whose net the stage ``flow1r`` trains first;
``fit_weights=confidence`` gives that net its confidence head, so the option keys ``flow1r`` on where
the chain has that stage, ``dm1`` on where it has not)."""


def _stage_model(model: dict[str, Any], name: str, names: list[str]) -> dict[str, Any]:
    """``model`` as stage ``name`` keys it: without the options, and the nets of one's own, of the
    slots that a later stage trains first (a net of one's own in ``dm1`` shares ``flow1``)."""
    def later(stage: str) -> bool:
        return stage in names and names.index(name) < names.index(stage)

    def first(option: str) -> str:
        stages = MODEL_OPTION_FROM[option]
        return stages if isinstance(stages, str) else min((s for s in stages if s in names), key=names.index,
                                                          default=stages[-1])

    out = {k: v for k, v in model.items() if not (k in MODEL_OPTION_FROM and later(first(k)))}
    if "nets" in out:
        nets = {slot: v for slot, v in out["nets"].items() if not later(slot)}
        out = {k: v for k, v in out.items() if k != "nets"} | ({"nets": nets} if nets else {})
    return out


def semantic_config(job) -> dict[str, Any]:
    """The resolved config as plain containers, without the :data:`NON_SEMANTIC` keys, with
    bundled files named rather than located (:func:`portable`)."""
    plain = copy.deepcopy(dict(job.config))
    for dotted in NON_SEMANTIC:
        node = plain
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.get(p, {})
        if isinstance(node, dict):
            node.pop(leaf, None)
    if isinstance(plain.get("model"), dict):
        plain["model"] = model_identity(plain["model"])
    if isinstance(plain.get("data"), dict):
        plain["data"] = without_render_cache(plain["data"])
    plain["precision"] = normalize_precision(plain["precision"])
    from demon_lab.pipeline.methods import method

    if not method(plain.get("method", "demon")).runs_chain:
        del plain["precision"]  # the methods that run no net compute the same in any precision
    else:
        plain.update(cpu_threads(job))  # nor with any thread count
    return portable(leave_out_neutral(plain))


def run_key(job) -> str:
    """A job's identity (``job``: its settings): its semantic config and :func:`versions`."""
    return digest({"config": semantic_config(job), **versions()})


def stage_key(description: Mapping[str, Any]) -> str:
    """A training stage's identity: its description (:func:`describe_stage`) and :func:`versions`."""
    return digest({**versions(), **portable(dict(description))})


def sweep_key(experiment: str, overrides: Iterable[str]) -> str:
    """A multirun's identity: its experiment, the command-line overrides that change results
    (so the same sweep re-issued with another thread count, store or launcher continues its parent
    run) and :func:`versions` (a version change starts a new parent)."""
    changing = sorted(_normal_override(o) for o in overrides if is_semantic(o))
    return digest({"experiment": str(experiment), "overrides": changing, **versions()}, sort_keys=False)


def _normal_override(override: str) -> str:
    """``precision=bf16`` and ``precision=bf16-mixed`` are one override (one name, one key)."""
    key, sep, value = override.partition("=")
    if sep and key.lstrip("+~") == "precision":
        try:
            return f"{key}={normalize_precision(value)}"
        except ValueError:
            return override
    return override


_hashes: dict[tuple[str, int, int], str] = {}


def content_hash(path: str | Path) -> str:
    """The sha256 of a file's bytes (cached per path, size and modification time)."""
    path = Path(path)
    stat = path.stat()
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _hashes:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 22), b""):
                h.update(chunk)
        _hashes[key] = h.hexdigest()
    return _hashes[key]


def describe(path: str | Path) -> str:
    """``sha256:<hex>`` of a weights file: how keys name it."""
    return "sha256:" + content_hash(os.fspath(path))
