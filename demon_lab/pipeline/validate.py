"""Configuration checks before any work: a wrong type or an out-of-range value, or a file the job
would read that is not there, is one line naming the key and what is allowed (raised as
:class:`demon_lab.pipeline.config.ConfigError`).

Written out rather than as Hydra structured configs: those check a value's type, but not its range
(a positive step count, an odd window), rules across keys (``iterations > 0`` needs the iterative
stages; a batch must split over the DDP processes) or the existence of files, and their errors
span several lines with the config's full key path and object type. What the checked config holds
is typed in :mod:`demon_lab.pipeline.schema`, which the code reads it through.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from demon_lab.baselines.methods import METHODS as BASELINES
from demon_lab.core.losses import check_weights
from demon_lab.nets.chain import ORACLES
from demon_lab.pipeline.config import ConfigError, expect_choice, expect_int, expect_positive
from demon_lab.pipeline.schema import PRIOR_KEYS, STAGE_KIND_NAMES, ModelSpec, stage_spec
from demon_lab.pipeline.stages.schedule import LR_SCHEDULES

PATH_KEYS = ("path", "root")
"""Arguments of the datasets (``demon_lab.data.datasets``) that name a file or folder to read."""


def _source_key(node: DictConfig, key: str, where: str) -> str:
    """``where`` and, when the value comes from another key by interpolation, that key too (the
    one a user sets): ``data.test[3].path (data.path)``."""
    raw = node._get_node(key)._value()
    if isinstance(raw, str) and raw.startswith("${") and raw.endswith("}") and ":" not in raw:
        return f"{where} ({raw[2:-1]})"
    return where


CHAIN_METHODS = ("demon", "base_mat_f")
"""The methods that run the DeMoN chain (``base_mat_f`` reads its flow): they train what the stage
cache lacks."""


def _trains(cfg: DictConfig) -> bool:
    """Whether the job will train a stage (and so read its training data)."""
    if not (cfg.train and cfg.method in CHAIN_METHODS):
        return False
    from demon_lab.pipeline.stages.schedule import stage_dirs

    return not all(stage.done() for stage in stage_dirs(cfg))


def check_paths(cfg: DictConfig) -> None:
    """Every file or folder the job reads exists: its test sets, and its training sets when it
    trains a stage the cache lacks. Checked before any rendering, training or tracking."""
    sources = [(f"data.test[{i}]", entry) for i, entry in enumerate(cfg.data.test)]
    if _trains(cfg):
        sources += [(f"data.train[{i}].dataset", entry.dataset) for i, entry in enumerate(cfg.data.train)]
    for where, node in sources:
        for key in PATH_KEYS:
            if key in node and node[key] is not None and not Path(str(node[key])).exists():
                raise ConfigError(f"{_source_key(node, key, f'{where}.{key}')}: {node[key]}: no such file or "
                                  f"directory")


def _model_files(cfg: DictConfig) -> None:
    """``model.compat`` and ``model.weights``: the file exists and fits the chain the config builds."""
    from demon_lab.nets.chain import COMPATS

    model = ModelSpec.of(cfg.model)
    expect_choice("model.compat", model.compat, COMPATS)
    if model.compat == "demon_original" and model.variant != "v1":
        raise ConfigError("model.compat: demon_original reproduces DeMoN's released v1 graph; it needs "
                          f"model.variant=v1, got {model.variant}")
    if model.correlation is not None:
        from demon_lab.nets.blocks import check_correlation

        try:
            check_correlation(model.correlation)
        except ValueError as e:
            raise ConfigError(f"model.{e}") from None
        if model.compat == "demon_original":
            raise ConfigError("model.correlation: compat=demon_original reproduces DeMoN's released graph, which has "
                              "no correlation front; leave model.correlation null")
    from demon_lab.nets.prior import CHOICES

    for key in PRIOR_KEYS:
        expect_choice(f"model.{key}", getattr(model, key), CHOICES[key])
    if model.dm1_prior == "ransac_prior" and model.flow1_prior is None:
        raise ConfigError("model.dm1_prior: ransac_prior reads flow1's classical prior flow; set model.flow1_prior "
                          "(dis or dis_x2)")
    for key in PRIOR_KEYS:
        if getattr(model, key) is not None and model.compat == "demon_original":
            raise ConfigError(f"model.{key}: compat=demon_original reproduces DeMoN's released graph, whose "
                              f"nets have no priors; leave model.{key} null")
    weights = model.weights
    if not weights:
        return
    if cfg.method not in CHAIN_METHODS:
        raise ConfigError(f"model.weights: method={cfg.method} runs no DeMoN chain; leave model.weights unset")
    if not Path(str(weights)).is_file():
        raise ConfigError(f"model.weights: {weights}: no such file")
    from demon_lab.pipeline.weights import check_fits

    why = check_fits(weights, model.variant, model.width, tuple(cfg.data.size), model.correlation, **model.priors())
    if why:
        raise ConfigError(f"model.weights: {why}")
    if not cfg.train:  # evaluated as they are: the passes run must not fall back on untrained nets
        from demon_lab.pipeline.weights import read_nets

        needed = ["flow1", "dm1"] + (["flow2", "dm2"] if int(cfg.iterations) > 0 else [])
        lacking = [n for n in needed if n not in read_nets(weights, mmap=True)]
        if lacking:
            raise ConfigError(f"model.weights: {weights} has no {', '.join(lacking)}, which train=false with "
                              f"iterations={cfg.iterations} evaluates (the refinement net is optional)")


def _kept_nets(cfg: DictConfig, stage: str, before: list[str]) -> None:
    """A stage of 0 steps trains nothing: its nets stay as they are at that point of the schedule,
    so each must come from an earlier stage that trains it or from ``model.weights``."""
    from demon_lab.pipeline.weights import read_nets

    earlier = {n for s in before if cfg.schedule.stages[s].steps > 0 for n in stage_spec(cfg, s).trained_nets()}
    held = set(read_nets(cfg.model.weights, mmap=True)) if cfg.model.weights else set()
    lacking = [n for n in stage_spec(cfg, stage).trained_nets() if n not in earlier | held]
    if lacking:
        source = f"{cfg.model.weights} has no" if cfg.model.weights else "model.weights is not set for"
        raise ConfigError(f"schedule.stages.{stage}.steps: 0 trains nothing and keeps the stage's nets as they "
                          f"are, but no earlier stage trains {', '.join(lacking)} and {source} "
                          f"{', '.join(lacking)}")


TRACKING_SCHEMES = ("sqlite", "http", "https", "postgresql", "mysql", "mssql", "file", "databricks")
METHODS = ("demon", *BASELINES)


def _baseline(cfg: DictConfig) -> None:
    """``baseline``: its rules are :class:`demon_lab.baselines.methods.BaselineConfig`'s (one line)."""
    from demon_lab.baselines.methods import BaselineConfig

    try:
        BaselineConfig(**OmegaConf.to_container(cfg.baseline, resolve=True), seed=cfg.seed)
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e).splitlines()[0]) from None


def _execution(cfg: DictConfig, here: bool = True) -> None:
    """``precision``, ``model.channels_last`` and ``model.compile``: known values, and, when the job
    runs ``here``, ones this platform can run on the device the job trains on (one line where it
    cannot; a job a cluster launcher sends elsewhere is checked there, by the job itself)."""
    from demon_lab.core import execution

    try:
        execution.normalize_precision(cfg.precision)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    for key in ("channels_last", "compile"):
        if not isinstance(cfg.model[key], bool):
            raise ConfigError(f"model.{key}: expected true or false, got {cfg.model[key]!r}")
    if cfg.method not in CHAIN_METHODS or not here:
        return
    device = execution.resolve_accelerator(cfg.trainer.accelerator)
    problem = execution.precision_problem(cfg.precision, device)
    if problem is None and cfg.model.compile:
        problem = execution.compile_problem(device)
    if problem is not None:
        raise ConfigError(problem)


SYNTHETIC_SOURCE = "demon_lab.data.datasets.SyntheticDataset"
"""The training source whose scenes ``fresh_scenes`` renders (a generator makes new ones)."""


def validate(cfg: DictConfig, here: bool = True) -> None:
    """Check every key the job reads (one ConfigError line). ``here=False``: the job will run on
    another machine (a cluster launcher), so what depends on this machine's devices is left to the
    job's own check there."""
    try:
        OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    except Exception as e:
        raise ConfigError(str(e).splitlines()[0]) from None
    expect_int("iterations", cfg.iterations, 0)
    expect_int("seed", cfg.seed, 0)
    if cfg.threads is not None:
        expect_int("threads", cfg.threads, 1)
    expect_choice("oracle", cfg.oracle, ORACLES)
    expect_choice("method", cfg.method, METHODS)
    if cfg.method != "demon" and cfg.oracle is not None:
        raise ConfigError(f"oracle: expected null with method={cfg.method} (oracles feed the DeMoN chain), "
                          f"got {cfg.oracle!r}")
    _baseline(cfg)
    expect_choice("force", cfg.force, (True, False))
    expect_choice("train", cfg.train, (True, False))
    expect_choice("model.variant", cfg.model.variant, ("v1", "v2"))
    expect_positive("model.width", cfg.model.width)
    size = list(cfg.data.size)
    if len(size) != 2 or any(isinstance(s, bool) or not isinstance(s, int) or s < 32 or s % 32 for s in size):
        raise ConfigError(f"data.size: expected [H, W] with sides positive multiples of 32, got {size}")
    expect_int("data.batch_size", cfg.data.batch_size, 1)
    expect_int("data.num_workers", cfg.data.num_workers, 0)
    _model_files(cfg)
    if not cfg.data.train:
        raise ConfigError("data.train: expected at least one training source")
    expect_choice("schedule.lr_schedule", cfg.schedule.lr_schedule, LR_SCHEDULES)
    expect_positive("schedule.weight_decay", cfg.schedule.weight_decay, allow_zero=True)
    expect_positive("schedule.grad_clip", cfg.schedule.grad_clip)
    stages = list(cfg.schedule.stages)
    expect_choice("schedule.until", cfg.schedule.until, tuple(stages))
    trained = stages[: stages.index(cfg.schedule.until) + 1]
    flow_oracle_study = cfg.oracle == "depth_motion" and "flow2" in trained  # scores flow2 only (EPE)
    if cfg.iterations > 0 and cfg.train and not {"flow2", "dm2"} <= set(trained) and not flow_oracle_study:
        raise ConfigError(f"iterations: expected 0 when schedule.until={cfg.schedule.until} "
                          f"(the iterative nets flow2 and dm2 are not trained), got {cfg.iterations}")
    for name in stages:
        expect_choice(f"schedule.stages.{name}.kind", cfg.schedule.stages[name].kind, STAGE_KIND_NAMES)
        spec = stage_spec(cfg, name)  # the rules of its kind's own options (the spec's check)
        if spec.steps == 0 and name in trained:
            _kept_nets(cfg, name, trained[: trained.index(name)])
        if spec.fresh_scenes and not any(entry.dataset.get("_target_") == SYNTHETIC_SOURCE for entry in cfg.data.train):
            raise ConfigError(f"schedule.stages.{name}.fresh_scenes: renders synthetic scenes, and data.train has "
                              f"no {SYNTHETIC_SOURCE} source")
        if spec.keep_best and not cfg.data.get("val"):
            raise ConfigError(f"schedule.stages.{name}.keep_best: scores the held-apart sets, and data.val "
                              f"has none; set data.val or keep_best=0")
        if getattr(spec, "restarts", None) is not None and cfg.trainer.devices * cfg.trainer.num_nodes > 1:
            raise ConfigError(f"schedule.stages.{name}.restarts: screening restarts runs in one process; "
                              f"train with trainer.devices=1 trainer.num_nodes=1")
    try:
        check_weights(OmegaConf.to_container(cfg.loss, resolve=True))
    except ValueError as e:
        raise ConfigError(str(e)) from None
    if cfg.eval.max_samples is not None:
        expect_int("eval.max_samples", cfg.eval.max_samples, 1)
    expect_int("eval.batch_size", cfg.eval.batch_size, 1)
    expect_choice("trainer.accelerator", cfg.trainer.accelerator, ("auto", "cpu", "gpu", "cuda", "mps"))
    expect_int("trainer.devices", cfg.trainer.devices, 1)
    expect_int("trainer.num_nodes", cfg.trainer.num_nodes, 1)
    if not isinstance(cfg.trainer.reuse_frozen, bool):
        raise ConfigError(f"trainer.reuse_frozen: expected true or false, got {cfg.trainer.reuse_frozen!r}")
    _execution(cfg, here)
    world = cfg.trainer.devices * cfg.trainer.num_nodes
    for name in stages:
        batch = cfg.schedule.stages[name].get("batch_size") or cfg.data.batch_size
        if batch % world:
            raise ConfigError(f"trainer.devices: the batch of stage {name} ({batch}) must split evenly over "
                              f"trainer.devices x trainer.num_nodes = {world} processes")
    if not isinstance(cfg.tracking.uri, str) or not cfg.tracking.uri:
        raise ConfigError(f"tracking.uri: expected a URI such as sqlite:///mlflow.db, got {cfg.tracking.uri!r}")
    scheme = cfg.tracking.uri.split("://", 1)[0].split("+", 1)[0] if "://" in cfg.tracking.uri else ""
    if scheme not in TRACKING_SCHEMES:
        raise ConfigError(f"tracking.uri: expected a URI with one of the schemes {', '.join(TRACKING_SCHEMES)} "
                          f"(e.g. sqlite:///mlflow.db, http://127.0.0.1:5000), got {cfg.tracking.uri!r}")
    check_paths(cfg)
