"""Every documented sweep composes with every launcher (nothing is submitted), output folders are
deterministic, and site settings (local/slurm.yaml on hydra.searchpath) reach the SLURM launchers."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from demon_lab.__main__ import CONF, _job_overrides
from tests.test_pipeline import SWEPT

LAUNCHERS = {
    "basic": "hydra._internal.core_plugins.basic_launcher.BasicLauncher",
    "joblib": "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
    "slurm": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
    "slurm_ddp": "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher",
}
SWEEPS = [[f"+experiment={e}"] for e in SWEPT] + [["iterations=0,1,2,3,4,5"]]


@pytest.mark.parametrize("launcher", [name if name == "basic" else pytest.param(name, marks=pytest.mark.slow)
                                      for name in LAUNCHERS])
@pytest.mark.parametrize("sweep", SWEEPS, ids=lambda s: s[0])
def test_every_job_of_every_documented_sweep_composes_with_every_launcher(launcher, sweep):
    with initialize_config_dir(CONF, version_base="1.3"):
        jobs = _job_overrides(["-m", *sweep, "scale=paper"])
        assert len(jobs) >= 3
        subdirs: set[str] = set()
        for job in jobs:
            extra = ["trainer.devices=4"] if launcher == "slurm_ddp" else []
            overrides = [*job, *extra, f"hydra/launcher={launcher}"]
            cfg = compose("config", overrides=overrides, return_hydra_config=True)
            assert cfg.hydra.launcher._target_ == LAUNCHERS[launcher]
            settings = OmegaConf.to_container(cfg.hydra.launcher, resolve=True)
            if launcher == "slurm":
                assert settings["gpus_per_node"] == 1 and settings["tasks_per_node"] == 1
                assert settings["max_num_timeout"] > 0  # a timed-out job is re-queued and resumes
            if launcher == "slurm_ddp":  # one task per GPU: Lightning finds its ranks, spawns nothing
                assert settings["tasks_per_node"] == settings["gpus_per_node"] == 4
            # output folders come from the experiment and the overrides, never from the clock
            raw = OmegaConf.to_container(cfg.hydra, resolve=False)
            assert "now:" not in str([raw["run"], raw["sweep"], raw["launcher"]])
            assert cfg.hydra.sweep.dir == f"multirun/{cfg.experiment}"
            subdirs.add(cfg.hydra.sweep.subdir)
            assert all(o.lstrip("+") in cfg.hydra.sweep.subdir for o in job if "=" in o)
        assert len(subdirs) == len(jobs)  # each job its own folder, the same on every re-issue


def test_site_settings_on_the_search_path_reach_the_slurm_launchers(tmp_path):
    (tmp_path / "local").mkdir()
    (tmp_path / "local" / "slurm.yaml").write_text("partition: site_gpu\naccount: lab42\n")
    for launcher in ("slurm", "slurm_ddp"):
        with initialize_config_dir(CONF, version_base="1.3"):
            cfg = compose("config", overrides=[f"hydra/launcher={launcher}", f"hydra.searchpath=[file://{tmp_path}]"],
                          return_hydra_config=True)
            assert cfg.hydra.launcher.partition == "site_gpu" and cfg.hydra.launcher.account == "lab42"
            plain = compose("config", overrides=[f"hydra/launcher={launcher}"], return_hydra_config=True)
            assert plain.hydra.launcher.partition is None  # without local/slurm.yaml: submitit's defaults


def test_output_folders_name_the_overrides_not_the_tracking_or_cache(tmp_path):
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", return_hydra_config=True)
    excluded = set(cfg.hydra.job.config.override_dirname.exclude_keys)
    assert {"tracking.uri", "cache_dir", "force"} <= excluded and "seed" not in excluded
