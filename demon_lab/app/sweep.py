"""A sweep (``python -m demon_lab -m``) on Hydra's own basic sweeper, through Hydra's public APIs.

Hydra's basic sweeper expands the sweep (``hydra.sweeper.params``, then the command line's
overrides, a key given in both taking the command line's value) and launches its jobs batch by
batch, with any launcher. demon_lab adds three things, in a Hydra callback
(:class:`demon_lab.app.callbacks.MultirunTracking`) and in the job:

- **every job is checked before the first launch.** Hydra calls the callback's ``on_multirun_start``
  before the sweeper starts; it expands the sweep as the basic sweeper will (:func:`expand`), composes
  each job with Hydra's config loader as its launcher will (``load_sweep_config``), and validates it
  (:func:`check_job`). A bad key, type or value in any job is one line on stderr and exit status 2,
  with no job started and no MLflow run created.
- **a failed job does not stop the sweep.** The basic sweeper stops at the first job that raises,
  so in a sweep a job never does: it ends its run FAILED, prints one line, leaves ``error.txt`` in
  its folder and returns (:func:`demon_lab.app.job.main_task`).
- **the sweep's verdict.** Each job leaves a record of its outcome (:func:`write_record`, called by
  the callback's ``on_job_end`` in the job's own process, which with the joblib and SLURM launchers is
  another one, so a file is what reaches the sweep) in its sweep's own folder of records
  (:func:`records_dir`: under the sweep's folder, named by the sweep's id, one file per job number);
  the sweep's end reads them (:func:`read_records`), prints their table, lists the failed jobs and
  exits non-zero if any failed.
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException
from omegaconf import DictConfig, OmegaConf, open_dict, read_write
from omegaconf.errors import OmegaConfBaseException

RECORDS = ".records"
"""The folder under a sweep's folder that holds its jobs' outcomes, one folder per sweep id."""
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
    settings = validate(job, here=launcher not in REMOTE_LAUNCHERS)
    if multirun and launcher != "slurm_ddp" and world_size(settings) > 1 and not processes_launched_outside():
        # Lightning's launcher starts each extra process by re-running the command line: under -m
        # that would re-run the whole sweep
        raise ConfigError(f"trainer.devices x trainer.num_nodes = {world_size(settings)} in a sweep with "
                          f"hydra/launcher={launcher}: use hydra/launcher=slurm_ddp (or torchrun), "
                          f"or one device per job")


def expand(params: Mapping[str, Any] | None, arguments: Iterable[str], config_loader: Any = None) -> list[list[str]]:
    """The overrides of each job of a sweep, in launch order, as Hydra's basic sweeper expands
    ``hydra.sweeper.params`` (``params``) followed by the command line's overrides (``arguments``,
    ``hydra.overrides.task``): each key's values in the order given, a key given twice taking its
    last value in its first place, the jobs the product of the keys' values. Hydra's own parser reads
    the overrides (``config_loader`` expands a config group's glob sweep)."""
    lines = [f"{k}={v}" for k, v in (params or {}).items()] + list(arguments)
    values: dict[str, list[str]] = {}
    for override in OverridesParser.create(config_loader=config_loader).parse_overrides(lines):
        key = override.get_key_element()
        if not override.is_sweep_override():
            values[key] = [f"{key}={override.get_value_element_as_str()}"]
        elif override.is_discrete_sweep():
            values[key] = [f"{key}={v}" for v in override.sweep_string_iterator()]
        else:
            raise HydraException(f"{key}: a sweep of a range or interval needs a sweeper that samples; the basic "
                                 f"sweeper takes choices (a,b,c) and range(...)")
    return [list(job) for job in itertools.product(*values.values())]


def check_sweep(primary: DictConfig, config_loader: Any) -> str | None:
    """None if every job of the sweep whose primary config is ``primary`` composes and validates, else
    the line that says why. ``config_loader``: Hydra's (``GlobalHydra.instance().config_loader()``)."""
    from demon_lab.pipeline.config import ConfigError

    launcher = primary.hydra.runtime.choices.get("hydra/launcher") or "basic"
    try:
        for overrides in expand(primary.hydra.sweeper.get("params"), primary.hydra.overrides.task, config_loader):
            check_job(config_loader.load_sweep_config(primary, list(overrides)), launcher, multirun=True)
    except ConfigError as e:
        return str(e)
    except (HydraException, OmegaConfBaseException) as e:
        return one_line(e)
    except Exception as e:  # (a weights file that cannot be read, a cached stage that cannot be listed)
        from demon_lab.app.job import known_errors

        line = str(e).strip().splitlines()[0] if str(e).strip() else ""
        return line if isinstance(e, known_errors()) else f"{type(e).__name__}: {line}"
    return None


def records_dir(sweep_dir: str | Path, sweep: str) -> Path:
    """Where the jobs of sweep ``sweep`` (its id) leave their outcomes: under the sweep's folder
    (``hydra.sweep.dir`` of its primary config, made absolute), a folder of its own. The jobs' own
    folders may be shared (a sweep over a key its folder names leave out, such as ``threads``) or lie
    elsewhere (a sweep over ``experiment``), so the records do not go there."""
    return Path(sweep_dir).resolve() / RECORDS / sweep


def write_record(job_return: Any, directory: Path) -> None:
    """A sweep job's outcome as ``directory/job-NUM.json`` (:func:`records_dir`): its place in the
    sweep, its folder, its overrides, its status and run id (the task's return,
    :func:`demon_lab.app.job.main_task`; ``FAILED`` where Hydra ended it so) and the pass its row shows
    (``baseline`` for a method scored without passes). Written whole (a file renamed into place), and
    by the job's first process alone where it trains on several (DDP: the others only train)."""
    from hydra.core.utils import JobStatus

    from demon_lab.core.execution import global_rank, world_size
    from demon_lab.pipeline.methods import method

    cfg = job_return.cfg
    if cfg is not None and world_size(cfg) > 1 and global_rank(cfg) != 0:
        return
    returned = job_return._return_value if isinstance(job_return._return_value, dict) else {}
    failed = job_return.status == JobStatus.FAILED
    chain = cfg is None or method(cfg.method).scores_passes  # (a classical method's summary has no passes)
    hydra = job_return.hydra_cfg.hydra
    num = int(hydra.job.num)
    record = {"num": num, "folder": str(hydra.runtime.output_dir), "overrides": list(job_return.overrides or []),
              "status": "FAILED" if failed else returned.get("status") or "-", "run_id": returned.get("run_id"),
              "pass": ("-" if cfg is None else cfg.iterations) if chain else "baseline"}
    directory.mkdir(parents=True, exist_ok=True)
    part = directory / f".job-{num}.json.{os.getpid()}"
    part.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(part, directory / f"job-{num}.json")


def read_records(directory: Path) -> list[dict[str, Any]]:
    """The records in ``directory`` (:func:`write_record`), in launch order."""
    found = []
    for path in directory.glob("job-*.json"):
        try:
            found.append(json.loads(path.read_text()))
        except (OSError, ValueError):  # (a record cannot be torn: it is renamed into place whole)
            continue
    return sorted(found, key=lambda r: r["num"])


