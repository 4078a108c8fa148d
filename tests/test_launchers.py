"""Every documented sweep composes with every launcher (nothing is submitted), output folders are
deterministic, and site settings (local/slurm.yaml on hydra.searchpath) reach the SLURM launchers."""

from __future__ import annotations

import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from demon_lab.__main__ import CONF, sweep_jobs
from tests.test_config_checks import SWEPT

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
    jobs = sweep_jobs(["-m", *sweep, "scale=paper"])
    assert len(jobs) >= 3
    with initialize_config_dir(CONF, version_base="1.3"):
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


def test_sweeps_run_through_demon_labs_sweeper_which_hydra_finds_and_instantiates(tmp_path):
    """conf/config.yaml selects hydra/sweeper=demon_lab: an experiment's declared sweep still reaches it,
    and Hydra instantiates it from the hydra_plugins name it requires of a sweeper, found by Hydra's own
    plugin scan (nothing registers it), also from a folder that is not the checkout."""
    from types import SimpleNamespace

    from hydra.core.plugins import Plugins
    from hydra.types import HydraContext

    from demon_lab.app.sweeper import Sweeper

    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=iterations"], return_hydra_config=True)
    assert cfg.hydra.sweeper._target_ == "hydra_plugins.demon_lab_sweeper.DemonLabSweeper"
    assert dict(cfg.hydra.sweeper.params) == {"iterations": "0,1,2,3,4,5", "seed": "0,1,2"}
    context = HydraContext(config_loader=None, callbacks=SimpleNamespace(callbacks=[]))
    sweeper = Plugins.instance().instantiate_sweeper(config=cfg, hydra_context=context, task_function=print)
    assert isinstance(sweeper, Sweeper) and sweeper.params == cfg.hydra.sweeper.params
    scan = ("from hydra.core.plugins import Plugins; from hydra.plugins.sweeper import Sweeper; "
            "print(sorted(c.__module__ + '.' + c.__name__ for c in Plugins.instance().discover(Sweeper)))")
    found = subprocess.run([sys.executable, "-c", scan], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert "hydra_plugins.demon_lab_sweeper.DemonLabSweeper" in found.stdout, found.stderr[-2000:]


def _smoke_sweep(tmp_path, params):
    """A sweeper of ``params`` at the smoke scale, its config loader counting the jobs it composes, its
    launcher recording the batches (seed=1 fails), its callbacks recording what reached them."""
    from types import SimpleNamespace

    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.utils import JobReturn, JobStatus
    from hydra.types import RunMode

    from demon_lab.app.sweeper import Sweeper

    seen = {"composed": [], "launched": [], "checked": [], "handed": []}
    loader = GlobalHydra.instance().config_loader()

    class Counting:
        def load_sweep_config(self, primary, overrides):
            seen["composed"].append(list(overrides))
            return loader.load_sweep_config(primary, overrides)

        def __getattr__(self, name):
            return getattr(loader, name)

    class Launcher:
        def launch(self, job_overrides, initial_job_idx):
            seen["launched"].append([list(o) for o in job_overrides])
            return [JobReturn(overrides=list(o), status=JobStatus.FAILED if "seed=1" in o else JobStatus.COMPLETED)
                    for o in job_overrides]

    class Recorder:
        def on_sweep_checked(self, config):
            seen["checked"].append(len(seen["launched"]))

        def on_jobs_returned(self, config, job_returns):
            seen["handed"].append([(r.overrides[0], r.status) for r in job_returns])

    sweeper = Sweeper(max_batch_size=2, params=params)
    sweeper.config = loader.load_configuration("config", ["scale=smoke", f"hydra.sweep.dir={tmp_path / 'sweep'}",
                                                          "hydra.mode=MULTIRUN"], RunMode.MULTIRUN)
    sweeper.hydra_context = SimpleNamespace(config_loader=Counting(),
                                            callbacks=SimpleNamespace(callbacks=[Recorder(), object()]))
    sweeper.launcher = Launcher()
    return sweeper, seen


def test_the_sweeper_checks_every_job_then_launches_every_batch_past_a_failed_job(tmp_path):
    """The basic sweeper's jobs and batches (the command line wins over hydra.sweeper.params); every job
    composed once by the sweeper (as its launcher will compose it) and validated before the first
    launch, the callbacks told then (on_sweep_checked: the parent run opens there); a FAILED job does
    not stop the sweep; each batch's JobReturns reach the callbacks' on_jobs_returned in the sweep's
    process."""
    from hydra.core.utils import JobStatus

    with initialize_config_dir(CONF, version_base="1.3"):
        sweeper, seen = _smoke_sweep(tmp_path, {"seed": "0,1,2", "iterations": "5"})
        returns = sweeper.sweep(["iterations=0", "method=demon"])
    jobs = [["seed=0", "iterations=0", "method=demon"], ["seed=1", "iterations=0", "method=demon"],
            ["seed=2", "iterations=0", "method=demon"]]
    assert seen["composed"] == jobs
    assert seen["checked"] == [0]  # every job checked before the first launch
    assert seen["launched"] == [jobs[:2], jobs[2:]]
    assert seen["handed"] == [[("seed=0", JobStatus.COMPLETED), ("seed=1", JobStatus.FAILED)],
                              [("seed=2", JobStatus.COMPLETED)]]
    assert [len(batch) for batch in returns] == [2, 1]
    assert (tmp_path / "sweep" / "multirun.yaml").is_file()


def test_a_sweep_with_one_bad_job_launches_none_and_says_which_in_one_line(tmp_path, capsys):
    with initialize_config_dir(CONF, version_base="1.3"):
        sweeper, seen = _smoke_sweep(tmp_path, {"seed": "0,1", "iterations": "0,-2"})
        with pytest.raises(SystemExit) as exited:
            sweeper.sweep([])
    assert exited.value.code == 2
    assert seen["launched"] == [] and seen["checked"] == [] and not (tmp_path / "sweep").exists()
    assert capsys.readouterr().err.strip() == "error: iterations: expected an integer >= 0, got -2"


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
        cfg = compose("config", [f"tracking.uri=sqlite:///{tmp_path}/m.db", f"cache_dir={tmp_path}", "force=true",
                                 "seed=1"], return_hydra_config=True)
    excluded = set(cfg.hydra.job.config.override_dirname.exclude_keys)
    assert {"tracking.uri", "cache_dir", "force"} <= excluded and "seed" not in excluded
    assert cfg.hydra.job.override_dirname == "seed=1"
