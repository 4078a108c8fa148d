"""A configuration is checked before any work: bad ones are refused with one line (and exit status 2),
the documented ones and every experiment's sweep compose and validate, and checking imports no training."""

from __future__ import annotations

import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from demon_lab import resources
from demon_lab.__main__ import check
from tests.jobs import cli, compose_config, smoke_overrides


def test_a_data_config_without_held_apart_sets_validates(tmp_path):
    """``data.val`` null or left empty: no held-apart curves (a stage with keep_best refuses it)."""
    from demon_lab.pipeline.validate import validate

    assert validate(compose_config(smoke_overrides(tmp_path, "data.val=null"))).data.val == ()


@pytest.mark.parametrize("args, message", [
    (["iterations=-1"], "iterations: expected an integer >= 0"),
    (["threads=0"], "threads: expected an integer >= 1"),
    (["model.width=0"], "model.width: expected a positive number"),
    (["data.size=[100,128]"], "data.size: expected [H, W] with sides positive multiples of 32"),
    (["model.variant=v3"], "model.variant: expected one of v1, v2"),
    (["oracle=perfect"], "oracle: expected one of null, flow, depth_motion"),
    (["no_such_key=1"], "Could not override 'no_such_key'"),
    (["iterations=three"], "iterations: expected an integer"),
    (["loss=no_such_preset"], "Could not find 'loss/no_such_preset'"),
    (["schedule.stages.dm1.oracle=depth_motion"], "schedule.stages.dm1.oracle: expected one of null, flow"),
    (["-m", "iterations=0,1,-2"], "iterations: expected an integer >= 0, got -2"),
    (["schedule.until=dm1"], "iterations: expected 0 when schedule.until=dm1"),
    (["schedule.stages.flow1.sig_start=1.5"],
     "schedule.stages.flow1.sig_start: expected a fraction of the stage in [0, 1] (1: never)"),
    (["schedule.stages.flow1.warmup_steps=-5"], "schedule.stages.flow1.warmup_steps: expected an integer >= 0"),
    (["+schedule.stages.flow1.level5_fade=0"], "schedule.stages.flow1.level5_fade: expected a positive number"),
    (["+schedule.stages.dm1.level5_fade=1"], "schedule.stages.dm1.level5_fade: only flow stages have level-5 terms"),
    (["+schedule.stages.dm1.gt_flow_warmup=1.5"],
     "schedule.stages.dm1.gt_flow_warmup: expected a fraction of the stage in [0, 1]"),
    (["+schedule.stages.flow1.gt_flow_warmup=0.5"], "schedule.stages.flow1.gt_flow_warmup: only depth-motion"),
    (["+schedule.stages.flow1.easy_first=[0,0.5]"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["+schedule.stages.flow1.easy_first=0.5"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["+schedule.stages.flow1.easy_first=[1.5,0.5]"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["+schedule.stages.flow1.easy_first=[0.25,0]"], "schedule.stages.flow1.easy_first: expected [start, until]"),
    (["model.correlation=[2,8]"], "model.correlation: expected [max_displacement, stride], positive integers"),
    (["model.correlation=[4,1]", "model.compat=demon_original"],
     "model.correlation: compat=demon_original reproduces DeMoN's released graph, which has no correlation front"),
    (["model.flow1_prior=flownet"], "model.flow1_prior: expected one of null, dis, dis_x2, got 'flownet'"),
    (["model.dm1_prior=lmeds"], "model.dm1_prior: expected one of null, ransac, ransac_prior, got 'lmeds'"),
    (["model.dm1_prior=ransac_prior"], "model.dm1_prior: ransac_prior reads flow1's classical prior flow; set "
                                       "model.flow1_prior (dis or dis_x2)"),
    (["model.dm2_prior=ransac"], "model.dm2_prior: expected one of null, previous, got 'ransac'"),
    (["model.flow2_prior=dis"], "model.flow2_prior: expected one of null, previous, got 'dis'"),
    (["model.flow2_prior=previous", "model.compat=demon_original"],
     "model.flow2_prior: compat=demon_original reproduces DeMoN's released graph, whose nets have no priors"),
    (["model.dm2_prior=previous", "model.compat=demon_original"],
     "model.dm2_prior: compat=demon_original reproduces DeMoN's released graph, whose nets have no priors"),
    (["model.flow1_prior=dis", "model.compat=demon_original"],
     "model.flow1_prior: compat=demon_original reproduces DeMoN's released graph, whose nets have no priors"),
    (["+schedule.stages.dm1.layers_first=0.5"], "schedule.stages.dm1.layers_first: only the bootstrap flow net's"),
    (["+schedule.stages.flow1.layers_first=0"], "schedule.stages.flow1.layers_first: expected a fraction of the stage"),
    (["+schedule.stages.flow1.restarts=[3,0]"], "schedule.stages.flow1.restarts: expected [starts, steps]"),
    (["+schedule.stages.dm1.sig_start=0.5"],
     "schedule.stages.dm1.sig_start: not an option of a depth_motion stage (its options: kind, steps, lr, "
     "warmup_steps, batch_size, oracle, easy_first, fresh_scenes, keep_best, net, gt_flow_warmup, joint)"),
    (["+schedule.stages.flow1.fresh_scenes=2"],
     "schedule.stages.flow1.fresh_scenes: expected new scenes per training draw in [0, 1], got 2"),
    (["+schedule.stages.dm1.fresh_scenes=0.1", "+schedule.stages.dm1.easy_first=[0.5,0.5]"],
     "schedule.stages.dm1.fresh_scenes: the easy_first order is of a fixed set of scenes; leave easy_first unset"),
    (["+schedule.stages.flow1.keep_best=-1"], "schedule.stages.flow1.keep_best: expected an integer >= 0, got -1"),
    (["+schedule.stages.flow1.keep_best=10", "data.val=[]"],
     "schedule.stages.flow1.keep_best: scores the held-apart sets, and data.val has none"),
    (["+schedule.stages.refine.queue_size=4"], "schedule.stages.refine.queue_size: not an option of a refine stage"),
    (["trainer.reuse_frozen=sometimes"], "trainer.reuse_frozen: expected true or false, got 'sometimes'"),
    (["data.train=null"], "data.train: expected at least one training source"),
    (["schedule.stages.iterative.queue_size=-3"], "schedule.stages.iterative.queue_size: expected an integer >= 0"),
    (["baseline.size=[16,16]"], "baseline.size: expected native or [H, W] with sides >= 32 pixels"),
    (["baseline.size=full"], "baseline.size: expected native or [H, W] with sides >= 32 pixels, got full"),
    (["data.real_pair=/does/not/exist"], "data.test[3].path (data.real_pair): /does/not/exist: no such file"),
    (["data=pair_folder", "data.path=/no/pairs"], "data.test[0].path (data.path): /no/pairs: no such file"),
    (["data=tum", "data.root=/no/tum"], "data.test[0].root (data.root): /no/tum: no such file or directory"),
])
def test_bad_configuration_is_one_line_before_any_work(args, message, tmp_path, monkeypatch, capsys):
    """In the process: ``python -m demon_lab``'s own entry point, its exit status and its stderr (the
    process itself, for two of these cases: the next test)."""
    import logging

    from demon_lab.__main__ import main

    monkeypatch.chdir(tmp_path)
    # Hydra sets the root logger's handlers up for the job, on the stream this test captures: the
    # tests after this one get the handlers back
    monkeypatch.setattr(logging.root, "handlers", list(logging.root.handlers))
    flags = [a for a in args if a.startswith("-")]  # Hydra reads its flags before the overrides
    monkeypatch.setattr(sys, "argv", ["demon_lab", *flags, *smoke_overrides(tmp_path),
                                      *[a for a in args if a not in flags]])
    with pytest.raises(SystemExit) as exited:
        main()
    captured = capsys.readouterr()
    assert exited.value.code == 2, captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], captured.err
    assert not captured.out
    assert not (tmp_path / "mlflow.db").exists()  # nothing was recorded


@pytest.mark.parametrize("args, message", [
    (["model.width=0"], "model.width: expected a positive number"),
    (["-m", "iterations=0,1,-2"], "iterations: expected an integer >= 0, got -2"),
])
def test_a_bad_configuration_exits_the_process_with_status_2_and_one_line(args, message, tmp_path):
    flags = [a for a in args if a.startswith("-")]  # Hydra reads its flags before the overrides
    result = cli(*flags, *smoke_overrides(tmp_path), *[a for a in args if a not in flags], cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not result.stdout
    assert not (tmp_path / "mlflow.db").exists()  # nothing was recorded


@pytest.mark.parametrize("overrides", [
    ["scale=cpu"], ["scale=paper"], ["scale=smoke", "model.variant=v2"], ["loss=supplementary"],
    ["loss=no_sig"], ["loss=no_normals"], ["loss=no_confidence"], ["loss=depth_sig_1000"],
    ["schedule=supplementary"], ["data=synthetic_scenes11"], ["data=middlebury"],
    ["-m", "iterations=0,1,2,3,4,5"], ["-m", "loss=supplementary,released_code,no_sig"],
])
def test_documented_configurations_compose_and_validate(overrides):
    assert check(overrides) is None


EXPERIMENTS = sorted(p.stem for p in (resources.CONF / "experiment").glob("*.yaml") if p.stem != "released_model")
"""The experiments that run on demon_lab's own data (released_model needs DeMoN's files and weights:
tests/test_released.py)."""


SWEPT = [e for e in EXPERIMENTS if e not in ("cpu_recipe", "cpu_design", "cpu_motion", "cpu_prior", "cpu_departures",
                                             "learned_design", "learned_rerun", "baseline_thresholds", "ceiling")]
"""The experiments that declare a sweep (the probes of cpu_recipe, cpu_design, cpu_motion, cpu_prior,
cpu_departures, learned_design, learned_rerun, baseline_thresholds and ceiling are single jobs, the commands of their
study specs in ablations/, which tests/test_report.py composes)."""


@pytest.mark.parametrize("experiment", SWEPT)
@pytest.mark.parametrize("scale", ["smoke", pytest.param("cpu", marks=pytest.mark.slow),
                                   pytest.param("paper", marks=pytest.mark.slow)])
def test_every_experiment_sweep_composes_and_validates(experiment, scale):
    """Each job of an experiment's declared sweep (hydra.sweeper.params) composes and validates."""
    from demon_lab.__main__ import sweep_jobs

    args = ["-m", f"+experiment={experiment}", f"scale={scale}"]
    jobs = sweep_jobs(args)
    assert len(jobs) >= 3 and {o.split("=")[0] for job in jobs for o in job} >= {"seed"}
    assert check(args) is None


@pytest.mark.slow
def test_checking_a_configuration_imports_neither_lightning_nor_mlflow():
    """``python -m demon_lab``'s check of every experiment (what runs before any work) in a fresh
    process: composing and validating a config needs neither the training nor the tracking library."""
    code = ("import sys\n"
            "from demon_lab.__main__ import check\n"
            f"swept = {SWEPT!r}\n"
            f"for e in {EXPERIMENTS!r}:\n"
            "    assert check(['-m', f'+experiment={e}'] if e in swept else [f'+experiment={e}']) is None\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'lightning', 'pytorch_lightning', 'mlflow'}))\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]", result.stdout


def test_experiments_exist_for_every_study():
    assert set(EXPERIMENTS) >= {"gt_flow_oracle", "gt_depth_motion_oracle", "iterations", "loss_weights", "baselines"}


def test_times_resolver_takes_integers_only():
    from omegaconf.errors import InterpolationResolutionError

    import demon_lab.pipeline.config  # noqa: F401  (registers the resolver)

    assert OmegaConf.create({"n": 3, "m": "${times:${n},4}"}).m == 12
    with pytest.raises(InterpolationResolutionError, match="times: expected two integers"):
        _ = OmegaConf.create({"n": "3; rm -rf", "m": "${times:${n},4}"}).m
