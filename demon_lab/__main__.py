"""``python -m demon_lab [overrides]``: compose, validate, run each job (:mod:`demon_lab.app.job`).

The configuration of every job (each combination of a ``-m`` sweep) is composed and validated
before Hydra starts, so a bad key, type or value is one line and a non-zero exit, with no MLflow
run created.
"""

from __future__ import annotations

import itertools
import sys

from demon_lab import resources

CONF = str(resources.CONF)
MAX_CHECKED_JOBS = 256


def _job_overrides(args: list[str]) -> list[list[str]]:
    """The overrides of each job: sweeps (a=1,2) expanded, Hydra's own options left out. With
    ``-m``, the sweeps an experiment declares in ``hydra.sweeper.params`` are expanded too (the
    command line wins for a key it also sets), as Hydra's basic sweeper does."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    plain = [a for a in args if not a.startswith("-") and not a.lstrip("+~").startswith(("hydra.", "hydra/"))]
    parser = OverridesParser.create()
    parsed = parser.parse_overrides(plain)
    if any(a in ("-m", "--multirun") for a in args):
        from hydra import compose

        fixed = [o.input_line for o in parsed if not o.is_sweep_override()]
        params = compose("config", overrides=fixed, return_hydra_config=True).hydra.sweeper.get("params") or {}
        given = {o.get_key_element().lstrip("+~") for o in parsed}
        extra = [f"{k}={v}" for k, v in params.items() if k.lstrip("+~") not in given]
        parsed += parser.parse_overrides(extra)
    choices = []
    for o in parsed:
        if o.is_sweep_override():
            choices.append([f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()])
        else:
            choices.append([o.input_line])
    jobs = [list(c) for c in itertools.product(*choices)] if choices else [[]]
    return jobs[:MAX_CHECKED_JOBS]


REMOTE_LAUNCHERS = ("slurm", "slurm_ddp")
"""Launchers whose jobs run on other machines: their device-dependent checks run in the job."""


def check(args: list[str]) -> str | None:
    """None if every job's config composes and validates, else the error line."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from demon_lab.core.execution import processes_launched_outside, world_size
    from demon_lab.pipeline.config import ConfigError, drop_missing_sources
    from demon_lab.pipeline.validate import validate

    with initialize_config_dir(CONF, version_base="1.3"):
        try:
            jobs = _job_overrides(args)
        except (HydraException, OmegaConfBaseException) as e:
            return str(e).splitlines()[0]
        multirun = any(a in ("-m", "--multirun") for a in args)
        launcher = next((a.split("=", 1)[1] for a in args if a.lstrip("+").startswith("hydra/launcher=")), "basic")
        for overrides in jobs:
            try:
                cfg = compose("config", overrides=overrides)
                drop_missing_sources(cfg)
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
                lines = [line.strip() for line in str(e).splitlines() if line.strip()]
                return " ".join(lines[:2]) if lines else type(e).__name__
    return None


def main() -> None:
    args = sys.argv[1:]
    if not any(a in ("--help", "-h", "--hydra-help", "--info", "--cfg", "-c", "--shell-completion") or
               a.startswith(("--cfg", "--info", "-c")) for a in args):
        error = check(args)
        if error:
            print(f"error: {error}", file=sys.stderr)
            sys.exit(2)
    import hydra

    from demon_lab.app.job import main_task

    hydra.main(version_base="1.3", config_path=CONF, config_name="config")(main_task)()


if __name__ == "__main__":
    main()
