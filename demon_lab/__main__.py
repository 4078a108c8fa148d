"""``python -m demon_lab [overrides]``: check every job, then let Hydra run them (:mod:`demon_lab.app.job`).

Before Hydra starts, :func:`check` composes each job of the command as Hydra will (a ``-m`` sweep
expanded by the sweep's own sweeper, :mod:`demon_lab.app.sweeper`, each job composed by Hydra's
config loader as its launcher composes it) and validates it, so a bad key, type or value in any job
is one line and a non-zero exit, with no MLflow run created and no job started. Hydra then composes
each job once more, to run it, and nothing else composes it: the sweeper leaves out the basic
sweeper's own composition of each batch before its launch, and the job does not compose. (Before it
runs anything, Hydra also composes the command's primary config in sweep mode to read ``hydra.mode``
from it; for a single run that is its job's config.)
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from demon_lab import resources
from demon_lab.pipeline.config import register_resolvers

CONF = str(resources.CONF)
register_resolvers()  # conf/ interpolates demon_lab's resolvers (${bundled:}, ${non_semantic_overrides:}, ...)
CONFIG_NAME = "config"

REMOTE_LAUNCHERS = ("slurm", "slurm_ddp")
"""Launchers whose jobs run on other machines: their device-dependent checks run in the job."""


def _arguments(args: list[str]) -> argparse.Namespace:
    """The command line as Hydra's own parser reads it (overrides, -m, the flags that run no job),
    flags among the overrides included, so that a bad job is named whatever the order."""
    from hydra._internal.utils import get_args_parser

    return get_args_parser().parse_intermixed_args(args)


def _runs_jobs(parsed: argparse.Namespace) -> bool:
    """False for the flags that print something instead of running jobs (--help, --cfg, --info, ...)."""
    return not (parsed.help or parsed.hydra_help or parsed.cfg or parsed.info is not None or parsed.shell_completion
                or parsed.experimental_rerun is not None)


def _primary(parsed: argparse.Namespace) -> tuple[Any, Any]:
    """Hydra's config loader and the command's primary config, composed as Hydra composes it (a
    sweep's without its swept values); inside an initialized Hydra."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    loader = GlobalHydra.instance().config_loader()
    mode = RunMode.MULTIRUN if parsed.multirun else RunMode.RUN
    overrides = [*parsed.overrides, f"hydra.mode={mode.name}"]  # what hydra.main adds
    return loader, loader.load_configuration(parsed.config_name or CONFIG_NAME, overrides, mode)


def _job_overrides(loader: Any, primary: Any) -> list[list[str]]:
    """The overrides of each job of a sweep, as its sweeper expands them (``hydra.sweeper.params``,
    then the command line)."""
    from demon_lab.app.sweeper import Sweeper

    batches = Sweeper.batches(primary.hydra.sweeper.get("params"), primary.hydra.overrides.task, loader)
    return [job for batch in batches for job in batch]


def sweep_jobs(args: list[str]) -> list[list[str]]:
    """The overrides of each job that ``python -m demon_lab ARGS`` runs: with ``-m``, every job of
    the sweep (the one an experiment declares included), as the sweep's sweeper expands it; without,
    the one job's overrides."""
    from hydra import initialize_config_dir

    parsed = _arguments(args)
    with initialize_config_dir(CONF, version_base="1.3"):
        loader, primary = _primary(parsed)
        return _job_overrides(loader, primary) if parsed.multirun else [list(primary.hydra.overrides.task)]


def _two_lines(e: Exception) -> str:
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return " ".join(lines[:2]) if lines else type(e).__name__


def check(args: list[str]) -> str | None:
    """None if every job of ``python -m demon_lab ARGS`` composes and validates, else the error line.
    Each job is composed once here, by Hydra's config loader, as its launcher will compose it."""
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import open_dict, read_write
    from omegaconf.errors import OmegaConfBaseException

    from demon_lab.core.execution import processes_launched_outside, world_size
    from demon_lab.pipeline.config import ConfigError, drop_missing_sources
    from demon_lab.pipeline.validate import validate

    parsed = _arguments(args)
    multirun = bool(parsed.multirun)
    with initialize_config_dir(CONF, version_base="1.3"):
        try:
            loader, primary = _primary(parsed)
            jobs = _job_overrides(loader, primary) if multirun else [None]
        except (HydraException, OmegaConfBaseException) as e:
            # a sweep's primary config, or its expansion; a single run's primary config is its job's
            return str(e).splitlines()[0] if multirun else _two_lines(e)
        launcher = primary.hydra.runtime.choices.get("hydra/launcher") or "basic"
        for overrides in jobs:
            try:
                cfg = primary if overrides is None else loader.load_sweep_config(primary, overrides)
                with read_write(cfg), open_dict(cfg):
                    del cfg["hydra"]  # the job's config, as the task receives it
                drop_missing_sources(cfg, cfg.train)
                validate(cfg, here=launcher not in REMOTE_LAUNCHERS)
                if multirun and launcher != "slurm_ddp" and world_size(cfg) > 1 and not processes_launched_outside():
                    # Lightning's launcher starts each extra process by re-running the command line:
                    # under -m that would re-run the whole sweep
                    raise ConfigError(f"trainer.devices x trainer.num_nodes = {world_size(cfg)} in a sweep with "
                                      f"hydra/launcher={launcher}: use hydra/launcher=slurm_ddp (or torchrun), "
                                      f"or one device per job")
            except ConfigError as e:
                return str(e)
            except (HydraException, OmegaConfBaseException) as e:
                return _two_lines(e)
    return None


def _register_sweeper() -> None:
    """Hydra finds plugins by scanning the ``hydra_plugins`` namespace, which an editable install
    hides from it: register the sweeper of ``conf/hydra/sweeper/demon_lab.yaml`` by hand."""
    from hydra.core.plugins import Plugins

    try:
        from hydra_plugins.demon_lab_sweeper import DemonLabSweeper
    except ImportError as e:
        print(f"error: demon_lab's Hydra sweeper is not installed ({e}): install demon_lab again "
              "(pip install -e . in a checkout, or its wheel)", file=sys.stderr)
        sys.exit(2)
    Plugins.instance().register(DemonLabSweeper)


def main() -> None:
    args = sys.argv[1:]
    if _runs_jobs(_arguments(args)):
        error = check(args)
        if error:
            print(f"error: {error}", file=sys.stderr)
            sys.exit(2)
    _register_sweeper()
    import hydra

    from demon_lab.app.job import main_task

    hydra.main(version_base="1.3", config_path=CONF, config_name="config")(main_task)()


if __name__ == "__main__":
    main()
