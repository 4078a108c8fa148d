"""Configuration checks before any work, one line naming the key and what is allowed (raised as
:class:`demon_lab.pipeline.config.ConfigError`).

Each key's type, range and the rules across keys are the typed settings'
(:class:`demon_lab.pipeline.settings.JobSettings`, which :func:`validate` reads first); what is
checked here is what no type can say: the files the job reads exist and fit the chain
(``model.weights``, the data sources), the nets a stage of 0 steps keeps come from somewhere, and
this machine's devices can run the precision and compilation asked for.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from demon_lab.pipeline.config import ConfigError
from demon_lab.pipeline.methods import method
from demon_lab.pipeline.settings import JobSettings

PATH_KEYS = ("path", "root")
"""Arguments of the datasets (``demon_lab.data.datasets``) that name a file or folder to read."""


def _source_key(node: DictConfig, key: str, where: str) -> str:
    """``where`` and, when the value comes from another key by interpolation, that key too (the
    one a user sets): ``data.test[3].path (data.path)``."""
    raw = node._get_node(key)._value()
    if isinstance(raw, str) and raw.startswith("${") and raw.endswith("}") and ":" not in raw:
        return f"{where} ({raw[2:-1]})"
    return where


def _trains(job: JobSettings) -> bool:
    """Whether the job will train a stage (and so read its training data)."""
    if not (job.train and method(job.method).runs_chain):
        return False
    from demon_lab.pipeline.stages.schedule import stage_dirs

    return not all(stage.done() for stage in stage_dirs(job))


def check_paths(job: JobSettings) -> None:
    """Every file or folder the job reads exists: its test sets, and its training sets when it
    trains a stage the cache lacks. Checked before any rendering, training or tracking."""
    sources = [(f"data.test[{i}]", entry) for i, entry in enumerate(job.data.test)]
    if _trains(job):
        sources += [(f"data.train[{i}].dataset", entry.dataset) for i, entry in enumerate(job.data.train)]
    for where, node in sources:
        for key in PATH_KEYS:
            if key in node and node[key] is not None and not Path(str(node[key])).exists():
                raise ConfigError(f"{_source_key(node, key, f'{where}.{key}')}: {node[key]}: no such file or "
                                  f"directory")


def _model_files(job: JobSettings) -> None:
    """``model.weights``: the file exists and fits the chain the config builds."""
    model = job.model
    weights = model.weights
    if not weights:
        return
    if not method(job.method).runs_chain:
        raise ConfigError(f"model.weights: method={job.method} runs no DeMoN chain; leave model.weights unset")
    if not Path(str(weights)).is_file():
        raise ConfigError(f"model.weights: {weights}: no such file")
    from demon_lab.pipeline.weights import check_fits

    why = check_fits(weights, model.variant, model.width, job.data.size, model.correlation, **model.net_options())
    if why:
        raise ConfigError(f"model.weights: {why}")
    if not job.train:  # evaluated as they are: the passes run must not fall back on untrained nets
        from demon_lab.pipeline.weights import read_nets

        needed = ["flow1", "dm1"] + (["flow2", "dm2"] if job.iterations > 0 else [])
        lacking = [n for n in needed if n not in read_nets(weights, mmap=True)]
        if lacking:
            raise ConfigError(f"model.weights: {weights} has no {', '.join(lacking)}, which train=false with "
                              f"iterations={job.iterations} evaluates (the refinement net is optional)")


def _kept_nets(job: JobSettings, stage: str, before: tuple[str, ...]) -> None:
    """A stage of 0 steps trains nothing: its nets stay as they are at that point of the schedule,
    so each must come from an earlier stage that trains it or from ``model.weights``."""
    from demon_lab.pipeline.weights import read_nets

    weights = job.model.weights
    earlier = {n for s in before if job.stages[s].steps > 0 for n in job.stages[s].trained_nets()}
    held = set(read_nets(weights, mmap=True)) if weights else set()
    lacking = [n for n in job.stages[stage].trained_nets() if n not in earlier | held]
    if lacking:
        source = f"{weights} has no" if weights else "model.weights is not set for"
        raise ConfigError(f"schedule.stages.{stage}.steps: 0 trains nothing and keeps the stage's nets as they "
                          f"are, but no earlier stage trains {', '.join(lacking)} and {source} "
                          f"{', '.join(lacking)}")


def _execution(job: JobSettings) -> None:
    """``precision`` and ``model.compile`` on the device the job trains on: one line where this
    platform cannot run them."""
    from demon_lab.core import execution

    if not method(job.method).runs_chain:
        return
    device = execution.resolve_accelerator(job.trainer.accelerator)
    problem = execution.precision_problem(job.precision, device)
    if problem is None and job.model.compile:
        problem = execution.compile_problem(device)
    if problem is not None:
        raise ConfigError(problem)


def validate(cfg: DictConfig, here: bool = True) -> JobSettings:
    """Check every key the job reads (one ConfigError line) and return the job's typed settings.
    ``here=False``: the job will run on another machine (a cluster launcher), so what depends on
    this machine's devices is left to the job's own check there."""
    try:
        OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    except Exception as e:
        raise ConfigError(str(e).splitlines()[0]) from None
    job = JobSettings.of(cfg)
    _model_files(job)
    trained = job.schedule.trained()
    for i, name in enumerate(trained):
        if job.stages[name].steps == 0:
            _kept_nets(job, name, trained[:i])
    if here:
        _execution(job)
    check_paths(job)
    return job
