"""``python -m demon_lab [-m] [overrides]``: Hydra runs the job (:mod:`demon_lab.app.job`) or the sweep.

Every job is checked before it does any work, and a bad key, type or value is one line on stderr and
exit status 2, with no MLflow run created:

* a sweep's jobs before the sweeper launches any (:mod:`demon_lab.app.sweep`: the Hydra callback's
  ``on_multirun_start`` composes and validates every job);
* a single job by the job itself (:func:`demon_lab.app.job.run` validates before it opens its run);
* what Hydra itself cannot compose (an unknown key, a missing config) by this entry point: Hydra
  raises it (``HYDRA_FULL_ERROR=1``, Hydra's documented switch) and it is printed as one line here.

:func:`check` runs the same checks on a command without running it (what the tests and the report
command use).
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Sequence

from demon_lab import resources
from demon_lab.pipeline.config import register_resolvers

CONF = str(resources.CONF)
register_resolvers()  # conf/ interpolates demon_lab's resolvers (${bundled:}, ${non_semantic_overrides:}, ...)
CONFIG_NAME = "config"


def _split(args: Sequence[str]) -> tuple[bool, list[str]]:
    """``ARGS`` of :func:`check` or :func:`sweep_jobs`: whether it is a sweep (``-m``), and its overrides."""
    overrides = [a for a in args if a not in ("-m", "--multirun")]
    flags = [a for a in overrides if a.startswith("-")]
    if flags:
        raise ValueError(f"only overrides and -m, got {flags}")
    return len(overrides) < len(args), overrides


def _primary(loader, overrides: list[str], multirun: bool):
    """The command's primary config, composed by Hydra's config loader as ``python -m demon_lab`` composes it."""
    from hydra.types import RunMode

    mode = RunMode.MULTIRUN if multirun else RunMode.RUN
    return loader.load_configuration(CONFIG_NAME, [*overrides, f"hydra.mode={mode.name}"], mode)


def check(args: Sequence[str]) -> str | None:
    """None if every job of ``python -m demon_lab ARGS`` composes and validates, else the line that
    says why. ``ARGS``: overrides, with ``-m`` (``--multirun``) for a sweep; each job is composed by
    Hydra's config loader as its launcher will compose it."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from demon_lab.app.sweep import check_job, check_sweep, one_line
    from demon_lab.pipeline.config import ConfigError

    multirun, overrides = _split(args)
    with initialize_config_dir(CONF, version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()
        try:
            primary = _primary(loader, overrides, multirun)
            if multirun:
                return check_sweep(primary, loader)
            check_job(primary, primary.hydra.runtime.choices.get("hydra/launcher") or "basic", multirun=False)
        except ConfigError as e:
            return str(e)
        except (HydraException, OmegaConfBaseException) as e:
            return str(e).splitlines()[0] if multirun else one_line(e)
    return None


def sweep_jobs(args: Sequence[str]) -> list[list[str]]:
    """The overrides of each job that ``python -m demon_lab -m ARGS`` runs, as its sweeper expands
    them (``hydra.sweeper.params``, then the command line: :func:`demon_lab.app.sweep.expand`)."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from demon_lab.app.sweep import expand

    _, overrides = _split(args)
    with initialize_config_dir(CONF, version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()
        primary = _primary(loader, overrides, multirun=True)
        return expand(primary.hydra.sweeper.get("params"), primary.hydra.overrides.task, loader)


def main() -> None:
    import hydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from demon_lab.app.job import main_task
    from demon_lab.app.sweep import one_line

    started = []

    @functools.wraps(main_task)  # Hydra names the job after the task's module: demon_lab.app.job
    def task(cfg):
        started.append(True)
        return main_task(cfg)

    before = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises what it cannot compose: one line below
    try:
        hydra.main(version_base="1.3", config_path=CONF, config_name=CONFIG_NAME)(task)()
    except (HydraException, OmegaConfBaseException) as e:
        if started:  # the job's own error, not the command's: main_task has said what it is
            raise
        print(f"error: {one_line(e)}", file=sys.stderr)
        sys.exit(2)
    finally:
        if before is None:
            del os.environ["HYDRA_FULL_ERROR"]
        else:
            os.environ["HYDRA_FULL_ERROR"] = before


if __name__ == "__main__":
    main()
