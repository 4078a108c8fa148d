"""A stage as the job trains it: its kind's loss, nets and scores, the options handed to it, its
curriculum, restarts, keep_best, and a killed stage resumed from its checkpoint."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from demon_lab.__main__ import CONF
from tests.jobs import client, compose_config, settings, smoke_overrides


def test_each_stage_kind_carries_its_loss_nets_oracles_and_scores_and_the_rate_schedules_are_implemented():
    from demon_lab.core.losses import OPTIONAL_WEIGHTS, WEIGHT_KEYS
    from demon_lab.nets.chain import ORACLES
    from demon_lab.pipeline.kinds import STAGE_SPECS, StageSpec
    from demon_lab.pipeline.schema import LR_SCHEDULES
    from demon_lab.pipeline.stages.base import learning_rate

    nets = {"flow1", "dm1", "flow2", "dm2", "refine_net"}
    for kind, spec in STAGE_SPECS.items():  # each kind is one class: its own loss, nets, weights, oracles
        assert issubclass(spec, StageSpec) and spec.loss is not StageSpec.loss, kind
        stage = spec(name=kind, steps=10, lr=1e-3)
        assert set(stage.trained_nets()) <= nets and set(stage.weight_keys()) <= {*WEIGHT_KEYS, *OPTIONAL_WEIGHTS}, kind
        assert set(spec.oracles) - {None} <= set(ORACLES), kind
    flow2 = STAGE_SPECS["flow"](name="flow2", steps=1, lr=1.0, net="flow2", sig_start=1.0)
    assert flow2.trained_nets() == ("flow2",) and flow2.validation_passes() == 1
    assert flow2.weight_keys() == ("flow", "flow_conf")  # its sig terms never start: not read, not in its key
    assert STAGE_SPECS["iterative"](name="iterative", steps=1, lr=1.0).trained_nets() == ("flow2", "dm2")
    assert STAGE_SPECS["refine"](name="refine", steps=1, lr=1.0, iterations=2).validation_passes() == 2
    for schedule in LR_SCHEDULES:  # each is implemented: the base rate at step 0, decayed by mid-stage
        assert learning_rate(0, 1000, 1e-3, schedule) == 1e-3
        assert 0 < learning_rate(500, 1000, 1e-3, schedule) < learning_rate(399, 1000, 1e-3, schedule) <= 1e-3
    with pytest.raises(ValueError, match=r"schedule\.lr_schedule: expected one of"):
        learning_rate(500, 1000, 1e-3, "cosine")


def test_the_stages_train_the_chain_with_all_four_priors_and_under_the_depth_motion_oracle(tmp_path):
    """Every stage kind trains and evaluates with the four priors (flow2's correction of the previous
    flow in the flow2, dm2, iterative and refine stages), and flow2 trains with its prior under the
    depth-motion oracle, where it reads ground-truth depth and motion and corrects the bootstrap flow."""
    from demon_lab.app.job import run

    priors = ["model.flow1_prior=dis", "model.dm1_prior=ransac", "model.flow2_prior=previous",
              "model.dm2_prior=previous"]
    threads = torch.get_num_threads()
    try:
        chain = run(compose_config(smoke_overrides(tmp_path, "threads=1", *priors)))
        oracle = run(compose_config(smoke_overrides(tmp_path, "threads=1", "+experiment=gt_depth_motion_oracle",
                                                    "model.flow2_prior=previous")))
    finally:
        torch.set_num_threads(threads)
    assert chain["status"] == oracle["status"] == "finished"
    for name in ("synthetic_sun3d", "middlebury"):
        assert all(math.isfinite(chain["summary"][name][f"it{k}/epe"]) for k in range(4))
        assert math.isfinite(oracle["summary"][name]["it1/epe"])


def test_train_stage_hands_the_probe_options_to_their_stages(tmp_path, monkeypatch):
    """A flow stage gets level5_fade, a depth-motion stage gt_flow_warmup, from the stage's config;
    a stage without them gets DeMoN's values (its kind's defaults)."""
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Built(Exception):
        pass

    given = {}

    def capture(chain, spec, **kwargs):
        given[spec.kind] = spec
        raise Built

    monkeypatch.setattr(training, "StageModule", capture)
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}", "+schedule.stages.flow1.level5_fade=0.75",
                                 "+schedule.stages.dm1.gt_flow_warmup=0.4"])
        plain = compose("config", ["scale=smoke", f"cache_dir={tmp_path}"])
    for config, expect in ((cfg, (0.75, 0.4)), (plain, (1 / 3, 0.0))):  # (DeMoN's: a third, none)
        chain = build_chain(settings(config))
        for stage in stage_dirs(settings(config))[:2]:  # flow1, dm1
            with pytest.raises(Built):
                training.train_stage(settings(config), chain, stage, logger=None, progress=False)
        assert (given["flow"].level5_fade, given["depth_motion"].gt_flow_warmup) == expect


def test_train_stage_draws_its_samples_with_the_stage_curriculum(tmp_path, monkeypatch):
    """easy_first of a stage reaches its sampler, with each source ordered by flow_order; a stage
    without it draws with the plain sampler."""
    from demon_lab.data.mixture import flow_order
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Built(Exception):
        pass

    samplers = []

    def fit(trainer, module, train_dataloaders, ckpt_path=None):
        samplers.append(train_dataloaders.sampler)
        raise Built

    monkeypatch.setattr(training.L.Trainer, "fit", fit)
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}",
                                 "+schedule.stages.flow1.easy_first=[0.25,0.5]"])
    chain = build_chain(settings(cfg))
    for stage in stage_dirs(settings(cfg))[:2]:  # flow1 with the curriculum, dm1 without
        with pytest.raises(Built):
            training.train_stage(settings(cfg), chain, stage, logger=None, progress=False)
    easy, plain = samplers
    assert easy.easy_first == (0.25, 0.5) and plain.easy_first is None
    datasets = training.build_datamodule(settings(cfg), 2, 4).train_sources
    assert [list(o) for o in easy.order] == [list(flow_order(d)) for _, d in datasets]


def test_a_flow1_stage_starts_on_fresh_2d_layers_and_trains_on_them(tmp_path, monkeypatch):
    """layers_first of flow1 reaches its sampler as the lead of a 2-D layers source of the job's size
    and seed (weight 0: none after the lead); a flow1 step on a batch of layers has a finite loss that
    the flow net's every parameter gets a gradient from."""
    from demon_lab.data.datasets import LayersDataset
    from demon_lab.pipeline.kinds import FlowStage
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.base import StageModule
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Built(Exception):
        pass

    loaders = []

    def fit(trainer, module, train_dataloaders, ckpt_path=None):
        loaders.append(train_dataloaders)
        raise Built

    monkeypatch.setattr(training.L.Trainer, "fit", fit)
    with initialize_config_dir(CONF, version_base="1.3"):
        cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path}", "seed=3",
                                 "+schedule.stages.flow1.layers_first=0.5"])
    chain = build_chain(settings(cfg))
    for stage in stage_dirs(settings(cfg))[:2]:  # flow1 with the layers, dm1 without
        with pytest.raises(Built):
            training.train_stage(settings(cfg), chain, stage, logger=None, progress=False)
    layered, plain = (loader.sampler for loader in loaders)
    sources = loaders[0].dataset.datasets
    assert isinstance(sources[-1], LayersDataset) and sources[-1].size == tuple(cfg.data.size)
    assert sources[-1].seed == 3 and layered.lead_source == len(sources) - 1 and layered.p[-1] == 0
    steps, batch = int(cfg.schedule.stages.flow1.steps), int(cfg.data.batch_size)
    assert layered.lead_keys == round(0.5 * steps) * batch and plain.lead_keys == 0
    assert not any(isinstance(d, LayersDataset) for d in loaders[1].dataset.datasets)
    module = StageModule(chain, FlowStage(name="flow1", steps=10, lr=1e-4), weights=dict(cfg.loss))
    pairs = torch.utils.data.default_collate([sources[-1][i] for i in range(2)])
    from demon_lab.core import losses

    loss, terms = module.stage_loss(pairs, losses.ground_truth(pairs))
    assert torch.isfinite(loss) and terms["flow2"] > 0
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in chain.flow1.parameters())


def test_restarts_screen_starts_of_flow1_and_the_stage_continues_from_the_best(tmp_path):
    """restarts=[1, 1] is the plain stage, to the last bit (start 0 is the chain's own initialisation and
    the stage continues from its checkpoint as a resumed stage does); restarts=[3, 1] trains three starts
    for one step, logs each one's held-apart EPE, continues from the lowest and keeps only its checkpoint."""
    from demon_lab.pipeline.stages import training
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    class Recorder:
        def __init__(self):
            self.logged = []

        def log_metrics(self, metrics, step=None):
            self.logged.append((dict(metrics), step))

    def trained(*extra, logger=None):
        with initialize_config_dir(CONF, version_base="1.3"):
            cfg = compose("config", ["scale=smoke", f"cache_dir={tmp_path / str(len(list(tmp_path.iterdir())))}",
                                     "schedule.stages.flow1.steps=3", *extra])
        torch.manual_seed(0)
        chain = build_chain(settings(cfg))
        stage = stage_dirs(settings(cfg))[0]
        training.train_stage(settings(cfg), chain, stage, logger=None, progress=False) if logger is None else \
            _train_with(training, cfg, chain, stage, logger)
        return chain.flow1.state_dict(), stage

    plain, _ = trained()
    one, _ = trained("+schedule.stages.flow1.restarts=[1,1]")
    assert all(torch.equal(plain[k], one[k]) for k in plain)
    recorder = Recorder()
    three, stage = trained("+schedule.stages.flow1.restarts=[3,1]", logger=recorder)
    scores = [m["restart/val_epe"] for m, _ in recorder.logged if "restart/val_epe" in m]
    chosen = [m["restart/chosen"] for m, _ in recorder.logged if "restart/chosen" in m]
    assert len(scores) == 3 and len(set(scores)) == 3 and chosen == [float(np.argmin(scores))]
    assert [p.name for p in stage.path.glob("restart*.ckpt")] == [f"restart{int(chosen[0])}.ckpt"]
    assert any(not torch.equal(plain[k], three[k]) for k in plain) == (chosen[0] != 0)


def _train_with(training, cfg, chain, stage, logger):
    """train_stage with a logger that records the metrics logged outside Lightning's own logging."""
    original = training.L.Trainer.__init__

    def without_logger(self, *args, **kwargs):  # the stage's own curves need an MLflow run: not here
        kwargs["logger"] = False
        original(self, *args, **kwargs)

    import unittest.mock

    with unittest.mock.patch.object(training.L.Trainer, "__init__", without_logger):
        training.train_stage(settings(cfg), chain, stage, logger=logger, progress=False)


@pytest.mark.slow
def test_killed_training_stage_resumes_from_its_checkpoint(tmp_path):
    """A real job is killed (SIGKILL) mid-stage; the same command resumes from the stage's last
    checkpoint instead of starting over."""
    args = smoke_overrides(tmp_path, "scale.steps.flow1=100", "schedule.until=flow1", "iterations=0",
                           "scale.checkpoint_every=5",
                           "eval.max_samples=1")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "demon_lab", *args], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoints = []
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        checkpoints = list((tmp_path / "cache" / "stages").glob("flow1-*/last.ckpt"))
        if checkpoints and any((p.parent / "weights.pt").exists() for p in checkpoints):
            break
        if checkpoints:
            time.sleep(1.0)  # let a few more steps pass
            break
        time.sleep(0.2)
    assert checkpoints, "no checkpoint was written before the deadline"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    import torch

    step_at_kill = torch.load(checkpoints[0], map_location="cpu", weights_only=False)["global_step"]
    assert 0 < step_at_kill < 100
    from demon_lab.app.job import run

    result = run(compose_config(args))
    assert result["status"] == "finished"
    assert (checkpoints[0].parent / "weights.pt").is_file()
    # the stage resumed from the checkpoint (at the kill step or a later one written just before
    # the kill) and ran only the remaining steps
    figures = result["figures"]["flow1"]
    assert step_at_kill <= figures["resumed_from_step"] < 100
    assert torch.load(checkpoints[0], map_location="cpu", weights_only=False)["global_step"] == 100
    c = client(tmp_path)
    statuses = [r.info.status for r in c.search_runs([c.get_experiment_by_name("default").experiment_id])]
    assert "FINISHED" in statuses


def test_keep_best_keeps_the_nets_of_the_lowest_held_apart_score_across_a_resume(tmp_path):
    """KeepBest scores every 2 steps and at the last: scripted translation scores 40, 30, 35 at steps
    2, 4, 6 keep step 4's nets; a stage resumed after step 4 (a new callback over the same file) keeps
    them against a worse score at step 6 and takes a better one at step 8; the restored nets are those
    of the best step, bit for bit, and only the stage's own nets are written."""
    from types import SimpleNamespace

    from demon_lab.pipeline.stages.validation import KeepBest

    scripted = {2: 40.0, 4: 30.0, 6: 35.0, 8: 20.0}

    class Scorer:
        last_seconds = 1.5  # what each step's scoring took (the option's cost counts it)

        def evaluate(self, trainer, module):
            score = scripted[trainer.global_step]
            return {"val/a/tran_deg": score, "val/b/tran_deg": score, "val/a/epe": -1.0}

    chain = SimpleNamespace(dm1=torch.nn.Linear(2, 2), flow1=torch.nn.Linear(2, 2))
    module = SimpleNamespace(chain=chain)
    states = {}

    def steps(keep, first, last, max_steps):
        for step in range(first, last + 1):
            with torch.no_grad():
                chain.dm1.weight.fill_(float(step))
            states[step] = {k: v.clone() for k, v in chain.dm1.state_dict().items()}
            keep.on_train_batch_end(SimpleNamespace(global_step=step, max_steps=max_steps), module, None, None, 0)

    path = tmp_path / "best.pt"
    keep = KeepBest(Scorer(), "tran_deg", 2, path, ["dm1"])
    steps(keep, 1, 4, max_steps=8)
    resumed = KeepBest(Scorer(), "tran_deg", 2, path, ["dm1"])
    assert (resumed.best_step, resumed.best) == (4, 30.0)
    steps(resumed, 5, 6, max_steps=8)
    assert resumed.best_step == 4
    figures = resumed.restore(chain)
    assert figures["keep_best_step"] == 4 and figures["keep_best_tran_deg"] == 30.0
    assert torch.equal(chain.dm1.weight, states[4]["weight"])
    assert set(torch.load(path, weights_only=True)["nets"]) == {"dm1"}
    steps(resumed, 7, 8, max_steps=8)
    assert resumed.restore(chain)["keep_best_step"] == 8 and torch.equal(chain.dm1.weight, states[8]["weight"])
    assert figures["keep_best_seconds"] >= 1.5  # step 6 scored in this process (steps 2 and 4 before the resume)
