"""The sweeper of ``python -m demon_lab -m``: Hydra's basic sweeper that checks every job before it
launches any, and goes on past a failed job.

The jobs and their batches are the basic sweeper's: :meth:`Sweeper.batches` is its expansion
(``BasicSweeper.split_arguments``) of ``hydra.sweeper.params`` followed by the command line's
overrides, a key given in both taking the command line's value. Before the first launch the sweeper
composes each job as its launcher will (``ConfigLoader.load_sweep_config``, as the basic sweeper's
``validate_batch_is_legal`` does) and validates it (:func:`check_job`): a bad key, type or value in
any job is one line on stderr and exit status 2, with no job started and no MLflow run created.
Then it hands the sweep to every Hydra callback that defines ``on_sweep_checked(config)``
(:class:`demon_lab.app.callbacks.MultirunTracking` opens the sweep's parent run there) and launches
the batches. Each job is composed twice in all: by this check and by its launcher.

A job that fails ends ``JobStatus.FAILED`` (:func:`demon_lab.app.job.main_task` raises
:class:`~demon_lab.app.job.JobFailed` after printing its line and writing ``error.txt``). The basic
sweeper would raise that error and stop the sweep; this one launches the next batch. After each
batch it hands the batch's JobReturns to every Hydra callback that defines
``on_jobs_returned(config, job_returns)``, in the sweep's own process: a callback's ``on_job_end``
runs in the job's process, which with the joblib and SLURM launchers is another one.

Hydra instantiates sweepers only from the ``hydra_plugins`` namespace, which it scans for plugins:
the class that ``conf/hydra/sweeper/demon_lab.yaml`` names is
``hydra_plugins.demon_lab_sweeper.DemonLabSweeper``, this class under that name.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf, open_dict, read_write
from omegaconf.errors import OmegaConfBaseException

RETURNS_HOOK = "on_jobs_returned"
"""The callback method that receives each batch's JobReturns in the sweep's process."""
CHECKED_HOOK = "on_sweep_checked"
"""The callback method called once every job of the sweep is checked, before the first launch."""
REMOTE_LAUNCHERS = ("slurm", "slurm_ddp")
"""Launchers whose jobs run on other machines: their device-dependent checks run in the job."""


def one_line(e: BaseException) -> str:
    """A Hydra or OmegaConf error as one line: its first two lines (what failed, and how to fix it)."""
    lines = [line.strip() for line in str(e).splitlines() if line.strip()]
    return " ".join(lines[:2]) if lines else type(e).__name__


def check_job(cfg: DictConfig, launcher: str, multirun: bool) -> None:
    """Validate one composed job (its ``hydra`` node included) as its launcher will run it; raises
    :class:`~demon_lab.pipeline.config.ConfigError` with the line to print."""
    from demon_lab.core.execution import processes_launched_outside, world_size
    from demon_lab.pipeline.config import ConfigError, drop_missing_sources
    from demon_lab.pipeline.validate import validate

    job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])  # the config the task receives
    with read_write(job), open_dict(job):
        drop_missing_sources(job, job.train)
    validate(job, here=launcher not in REMOTE_LAUNCHERS)
    if multirun and launcher != "slurm_ddp" and world_size(job) > 1 and not processes_launched_outside():
        # Lightning's launcher starts each extra process by re-running the command line: under -m
        # that would re-run the whole sweep
        raise ConfigError(f"trainer.devices x trainer.num_nodes = {world_size(job)} in a sweep with "
                          f"hydra/launcher={launcher}: use hydra/launcher=slurm_ddp (or torchrun), "
                          f"or one device per job")


def check_sweep(primary: DictConfig, config_loader: Any, batches: Sequence[Sequence[Sequence[str]]]) -> str | None:
    """None if every job of the sweep composes and validates, else the line that says why."""
    from demon_lab.pipeline.config import ConfigError

    launcher = primary.hydra.runtime.choices.get("hydra/launcher") or "basic"
    for batch in batches:
        for overrides in batch:
            try:
                check_job(config_loader.load_sweep_config(primary, list(overrides)), launcher, multirun=True)
            except ConfigError as e:
                return str(e)
            except (HydraException, OmegaConfBaseException) as e:
                return one_line(e)
    return None


class Sweeper(BasicSweeper):
    def __init__(self, max_batch_size: int | None = None, params: dict[str, str] | None = None) -> None:
        """BasicSweeper's state, set here rather than by its ``__init__``: Hydra's plugin scan re-imports
        the basic sweeper's module when it is already loaded, after which that ``__init__``'s
        ``super(BasicSweeper, self)`` names a different class than this one derives from."""
        self.overrides: list[list[list[str]]] | None = None
        self.batch_index = 0
        self.max_batch_size = max_batch_size
        self.params = params or {}
        self.hydra_context = None
        self.config = None
        self.launcher = None

    @staticmethod
    def batches(params: Any, arguments: Iterable[str], config_loader: Any = None,
                max_batch_size: int | None = None) -> list[list[list[str]]]:
        """The overrides of each job, in batches of ``max_batch_size`` (None: one batch), as the basic
        sweeper expands ``hydra.sweeper.params`` (``params``) and the command line's overrides
        (``arguments``, ``hydra.overrides.task``)."""
        lines = [f"{k}={v}" for k, v in (params or {}).items()] + list(arguments)
        overrides = OverridesParser.create(config_loader=config_loader).parse_overrides(lines)
        return BasicSweeper.split_arguments(overrides, max_batch_size)

    def sweep(self, arguments: list[str]) -> list[Sequence[JobReturn]]:
        """Check every job (one line and exit status 2 on the first bad one), then launch every batch
        and hand its returns over, whether its jobs failed or not."""
        assert self.config is not None and self.launcher is not None and self.hydra_context is not None
        self.overrides = self.batches(self.params, arguments, self.hydra_context.config_loader, self.max_batch_size)
        error = check_sweep(self.config, self.hydra_context.config_loader, self.overrides)
        if error:
            print(f"error: {error}", file=sys.stderr, flush=True)
            sys.exit(2)
        self._call(CHECKED_HOOK, config=self.config)
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        returns: list[Sequence[JobReturn]] = []
        first = 0
        while not self.is_done():
            batch = self.get_job_batch()
            results = self.launcher.launch(batch, initial_job_idx=first)
            first += len(batch)
            returns.append(results)
            self._call(RETURNS_HOOK, config=self.config, job_returns=results)
        return returns

    def _call(self, hook: str, **kwargs: Any) -> None:
        for callback in self.hydra_context.callbacks.callbacks:
            method = getattr(callback, hook, None)
            if method is not None:
                method(**kwargs)
