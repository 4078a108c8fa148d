"""Every documented sweep composes with every launcher (nothing is submitted), output folders are
deterministic, and site settings (local/slurm.yaml on hydra.searchpath) reach the SLURM launchers."""

from __future__ import annotations

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


def test_sweeps_run_on_hydras_own_basic_sweeper_and_demon_lab_expands_them_as_it_does():
    """conf/config.yaml keeps Hydra's basic sweeper (no plugin of demon_lab's); an experiment's declared
    sweep reaches it; and the jobs demon_lab checks before the first launch (``sweep.expand``) are the
    jobs the basic sweeper launches, in its order: choices, ranges, a config group's glob, a key given
    in both hydra.sweeper.params and on the command line (the command line's value, in the first place)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper  # (Hydra's own, to compare with)
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from demon_lab.app.sweep import expand

    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", overrides=["+experiment=iterations"], return_hydra_config=True)
        assert cfg.hydra.sweeper._target_ == "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
        assert dict(cfg.hydra.sweeper.params) == {"iterations": "0,1,2,3,4,5", "seed": "0,1,2"}
        loader = GlobalHydra.instance().config_loader()
        cases = [({"iterations": "0,1,2,3,4,5", "seed": "0,1,2"}, ["seed=4", "threads=1"]),
                 ({"seed": "range(0,3)"}, ["method=base_ff,base_sift", "+experiment=iterations"]),
                 (None, ["scale=glob(sm*)", "seed=0,1"]),
                 ({"seed": "0,1"}, [])]
        for params, arguments in cases:
            lines = [f"{k}={v}" for k, v in (params or {}).items()] + arguments
            hydras = BasicSweeper.split_arguments(OverridesParser.create(loader).parse_overrides(lines), None)[0]
            assert expand(params, arguments, loader) == hydras, (params, arguments)
    assert expand({"iterations": "0,1", "seed": "0,1,2"}, ["seed=4"])[0] == ["iterations=0", "seed=4"]


def _multirun_config(tmp_path, *overrides: str):
    """A smoke sweep's primary config as Hydra composes it for ``-m`` (call inside initialize_config_dir)."""
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    loader = GlobalHydra.instance().config_loader()
    return loader.load_configuration("config", ["scale=smoke", f"hydra.sweep.dir={tmp_path / 'sweep'}",
                                                f"tracking.uri=sqlite:///{tmp_path}/mlflow.db",
                                                "hydra.mode=MULTIRUN", *overrides], RunMode.MULTIRUN)


def test_a_sweep_with_one_bad_job_launches_none_and_says_which_in_one_line(tmp_path, capsys):
    """Before the sweeper starts (Hydra's ``on_multirun_start``), the callback composes every job of the
    sweep as its launcher will and validates it: one bad job is one line and exit status 2, with no
    store, no parent run and no job folder; a good sweep passes and opens its parent run."""
    from demon_lab.app.callbacks import MultirunTracking

    with initialize_config_dir(CONF, version_base="1.3"):
        callback = MultirunTracking()
        with pytest.raises(SystemExit) as exited:
            callback.on_multirun_start(_multirun_config(tmp_path, "seed=0,1", "iterations=0,-2"))
        assert exited.value.code == 2
        assert capsys.readouterr().err.strip() == "error: iterations: expected an integer >= 0, got -2"
        assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "sweep").exists()
        callback.on_multirun_start(_multirun_config(tmp_path, "seed=0,1", "iterations=0"))
    assert callback.parent is not None and callback.records.parent == (tmp_path / 'sweep' / '.records').resolve()


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


def test_any_error_of_the_check_stops_the_sweep_in_one_line(tmp_path, monkeypatch, capsys):
    """Hydra turns an exception of a callback into a warning, so the check says every error itself:
    one that is not a config error (a weights file that cannot be read) is one line and exit status 2
    too, not a sweep launched unchecked."""
    from demon_lab.app.callbacks import MultirunTracking
    from demon_lab.pipeline import validate

    def unreadable(cfg, here=True):
        raise PermissionError("[Errno 13] Permission denied: 'weights.pt'")

    monkeypatch.setattr(validate, "validate", unreadable)
    with initialize_config_dir(CONF, version_base="1.3"), pytest.raises(SystemExit) as exited:
        MultirunTracking().on_multirun_start(_multirun_config(tmp_path, "seed=0,1"))
    assert exited.value.code == 2
    assert capsys.readouterr().err.strip() == "error: PermissionError: [Errno 13] Permission denied: 'weights.pt'"
    assert not (tmp_path / "mlflow.db").exists()
