"""The sweeper of ``python -m demon_lab -m``: Hydra's basic sweeper, without its second composition
of each job, and going on past a failed job.

The jobs and their batches are the basic sweeper's: :meth:`Sweeper.batches` is its expansion
(``BasicSweeper.split_arguments``) of ``hydra.sweeper.params`` followed by the command line's
overrides, a key given in both taking the command line's value. The check that ``python -m
demon_lab`` runs before Hydra starts (``demon_lab.__main__.check``) expands a sweep with the same
method and composes each job as the launcher will (``ConfigLoader.load_sweep_config``), then
validates it. So this sweeper does not compose each batch again before launching it, as the basic
sweeper does (``validate_batch_is_legal``): a job is composed twice in all, by the check and by its
launcher.

A job that fails ends ``JobStatus.FAILED`` (:func:`demon_lab.app.job.main_task` raises
:class:`~demon_lab.app.job.JobFailed` after printing its line and writing ``error.txt``). The basic
sweeper would raise that error and stop the sweep; this one launches the next batch. After each
batch it hands the batch's JobReturns to every Hydra callback that defines
``on_jobs_returned(config, job_returns)``, in the sweep's own process: a callback's ``on_job_end``
runs in the job's process, which with the joblib and SLURM launchers is another one.
:class:`demon_lab.app.callbacks.MultirunTracking` counts the failed jobs that way.

Hydra instantiates sweepers only from the ``hydra_plugins`` namespace: the class that
``conf/hydra/sweeper/demon_lab.yaml`` names is ``hydra_plugins.demon_lab_sweeper.DemonLabSweeper``,
this class under that name.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.utils import JobReturn
from omegaconf import OmegaConf

RETURNS_HOOK = "on_jobs_returned"
"""The callback method that receives each batch's JobReturns in the sweep's process."""


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
        """BasicSweeper.sweep without its composition of each batch before the launch and without
        raising a failed job's error: every batch is launched, and its returns handed over."""
        assert self.config is not None and self.launcher is not None and self.hydra_context is not None
        self.overrides = self.batches(self.params, arguments, self.hydra_context.config_loader, self.max_batch_size)
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
            for callback in self.hydra_context.callbacks.callbacks:
                hook = getattr(callback, RETURNS_HOOK, None)
                if hook is not None:
                    hook(config=self.config, job_returns=results)
        return returns
