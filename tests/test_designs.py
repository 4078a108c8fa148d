"""The shipped designs and their options: the cpu profile's departures, DeMoN's design, the learned design,
the probe options; what each keys, and the stages that train them."""

from __future__ import annotations

import math

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from demon_lab import resources
from demon_lab.__main__ import CONF
from demon_lab.pipeline.identity import run_key
from tests.conftest import shared_renders
from tests.jobs import DEMON_DESIGN, FOUR_PRIORS_OFF, client, compose_config, settings, smoke_overrides


@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_longer_oracle_study_trains_dm1_four_times_the_profile_and_shares_flow1(scale):
    import demon_lab.pipeline.config  # noqa: F401  (registers the ${times:} resolver, as the app does)
    from demon_lab.pipeline.stages.schedule import stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        base = compose("config", [f"scale={scale}", "+experiment=gt_flow_oracle", "oracle=flow"])
        long = compose("config", [f"scale={scale}", "+experiment=gt_flow_oracle_long", "oracle=flow"])
    assert long.experiment == "gt_flow_oracle_long" and long.schedule.stages.dm1.oracle == "flow"
    assert long.schedule.stages.dm1.steps == 4 * base.scale.steps.dm1 == 4 * base.schedule.stages.dm1.steps
    (flow1, dm1), (flow1_long, dm1_long) = stage_dirs(settings(base)), stage_dirs(settings(long))
    assert flow1.key == flow1_long.key and dm1.key != dm1_long.key


@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_the_probe_options_are_absent_from_every_profile_and_key_only_their_stage_and_later(scale):
    """level5_fade, gt_flow_warmup, easy_first and layers_first exist for probes (ablations/cpu_recipe.yaml,
    ablations/cpu_design.yaml): no profile sets them,
    so no key holds them; set, they key their own stage and, through the upstream keys, the later ones."""
    from demon_lab.pipeline.stages.schedule import stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        plain = compose("config", [f"scale={scale}"])
        fade = compose("config", [f"scale={scale}", "+schedule.stages.flow1.level5_fade=1.0"])
        warm = compose("config", [f"scale={scale}", "+schedule.stages.dm1.gt_flow_warmup=0.5"])
        easy = compose("config", [f"scale={scale}", "+schedule.stages.flow1.easy_first=[0.25,0.5]"])
        layers = compose("config", [f"scale={scale}", "+schedule.stages.flow1.layers_first=0.3"])
    for spec in plain.schedule.stages.values():
        assert not {"level5_fade", "gt_flow_warmup", "easy_first", "layers_first"} & set(spec)
    keys = {name: [d.key for d in stage_dirs(settings(cfg))]
            for name, cfg in (("plain", plain), ("fade", fade), ("warm", warm), ("easy", easy), ("layers", layers))}
    for option in ("fade", "easy", "layers"):
        assert all(a != b for a, b in zip(keys["plain"], keys[option], strict=True))
    assert keys["warm"][0] == keys["plain"][0] and all(a != b for a, b in zip(keys["plain"][1:], keys["warm"][1:],
                                                                             strict=True))


@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_design_demon_is_demons_design_at_every_scale_with_the_keys_of_the_four_priors_off(scale):
    """design=demon composes DeMoN's design: at the smoke and paper scales the scale's own config, at the cpu
    scale the profile with its four priors off, each with the stage and run keys of those configs."""
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.stages.schedule import stage_dirs
    from demon_lab.pipeline.tracking import flatten
    from demon_lab.reporting.provenance import DEMON, departures, design_name

    with initialize_config_dir(CONF, version_base="1.3"):
        named = compose("config", [f"scale={scale}", "design=demon"])
        spelled = compose("config", [f"scale={scale}", *FOUR_PRIORS_OFF])
        own = compose("config", [f"scale={scale}"])
    assert run_key(settings(named)) == run_key(settings(spelled))
    assert [d.key for d in stage_dirs(settings(named))] == [d.key for d in stage_dirs(settings(spelled))]
    assert design_name(departures(flatten(OmegaConf.to_container(named, resolve=True)))) == DEMON
    assert (run_key(settings(named)) == run_key(settings(own))) == (scale != "cpu")


@pytest.mark.parametrize("option, key, built", [
    ("model.correlation=[8,2]", "correlation",
     lambda chain: chain.flow1.correlation == (8, 2) and chain.flow2.correlation == (8, 2)),
    ("model.flow1_prior=dis", "flow1_prior", lambda chain: chain.flow1.prior == "dis" and chain.flow2.prior is None),
], ids=["correlation", "flow1_prior"])
@pytest.mark.parametrize("scale", ["smoke", "cpu", "paper"])
def test_a_flow_net_option_keys_every_stage_and_the_run_and_is_absent_by_default(option, key, built, scale):
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.identity import semantic_config
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        plain = compose("config", [f"scale={scale}", *DEMON_DESIGN])
        changed = compose("config", [f"scale={scale}", *DEMON_DESIGN, option])
    assert plain.model[key] is None and key not in semantic_config(settings(plain))["model"]
    assert all(a.key != b.key for a, b in zip(stage_dirs(settings(plain)), stage_dirs(settings(changed)), strict=True))
    assert run_key(settings(plain)) != run_key(settings(changed))
    if scale != "paper":  # (the paper-scale chain is 46 M parameters: the smaller ones show the same)
        assert built(build_chain(settings(changed))) and not built(build_chain(settings(plain)))


@pytest.mark.parametrize(("option", "first"), [("dm1_prior=ransac", "dm1"), ("flow2_prior=previous", "flow2"),
                                               ("dm2_prior=previous", "dm2")])
def test_a_motion_prior_keys_the_stages_from_its_net_on_and_shares_those_before(option, first):
    import demon_lab.pipeline.config  # noqa: F401  (registers the resolvers, as the app does)
    from demon_lab.pipeline.stages.schedule import build_chain, stage_dirs

    key, value = option.split("=")
    with initialize_config_dir(CONF, version_base="1.3"):
        plain = compose("config", ["scale=cpu", *DEMON_DESIGN])
        prior = compose("config", ["scale=cpu", *DEMON_DESIGN, f"model.{option}"])
    assert plain.model[key] is None and run_key(settings(plain)) != run_key(settings(prior))
    a, b = stage_dirs(settings(plain)), stage_dirs(settings(prior))
    names = [d.name for d in a]
    assert names == [d.name for d in b] and first in names
    cut = names.index(first)
    assert all(x.key == y.key for x, y in zip(a[:cut], b[:cut], strict=True))
    assert all(x.key != y.key for x, y in zip(a[cut:], b[cut:], strict=True))
    assert getattr(build_chain(settings(prior)), key) == value and getattr(build_chain(settings(plain)), key) is None


def test_only_the_cpu_profile_departs_and_the_departures_study_turns_each_departure_off():
    """The cpu profile takes the four priors (dis_x2, ransac_prior, previous, previous) and the memo;
    smoke and paper keep DeMoN's design. Each row of the cpu_departures study at the cpu scale turns
    off exactly the prior its name says (without flow1's prior, dm1 reads RANSAC of flow1's own flow),
    row demon all four, and row profile is the cpu profile itself."""
    from demon_lab.pipeline.schema import PRIOR_KEYS
    from demon_lab.pipeline.stages.schedule import build_chain

    spec = yaml.safe_load((resources.STUDIES / "cpu_departures.yaml").read_text())
    four = {"flow1_prior": "dis_x2", "dm1_prior": "ransac_prior", "flow2_prior": "previous", "dm2_prior": "previous"}
    assert set(PRIOR_KEYS) == set(four)
    with initialize_config_dir(CONF, version_base="1.3"):
        for scale in ("smoke", "paper"):
            cfg = compose("config", [f"scale={scale}"])
            assert all(cfg.model[k] is None for k in four) and cfg.trainer.reuse_frozen is False
        cpu = compose("config", ["scale=cpu"])
        assert {k: cpu.model[k] for k in four} == four and cpu.trainer.reuse_frozen is True
        rows = {}
        for run in spec["runs"]:
            cfg = compose("config", ["scale=cpu", *(o for o in run if not o.startswith("seed="))])
            rows[cfg.row] = {k: cfg.model[k] for k in four}
            assert cfg.train is (cfg.row != "untrained")
    assert rows["profile"] == rows["untrained"] == four and rows["demon"] == dict.fromkeys(four)
    assert rows["no_flow1_prior"] == {**four, "flow1_prior": None, "dm1_prior": "ransac"}
    for key in ("dm1_prior", "flow2_prior", "dm2_prior"):
        assert rows[f"no_{key}"] == {**four, key: None}
    with initialize_config_dir(CONF, version_base="1.3"):
        chain = build_chain(settings(compose("config", ["scale=cpu", *spec["runs"][0]])))
    assert (chain.flow1_prior, chain.dm1_prior, chain.flow2_prior, chain.dm2_prior) == tuple(four.values())


def test_a_stage_key_holds_only_the_loss_weights_that_stage_reads():
    """The loss-weight study's presets share every stage whose loss they leave unchanged:
    no_normals and depth_sig_1000 change depth-motion weights only, so they share supplementary's
    flow1 and train their own dm1; no_confidence changes the flow weights, so its flow1 (and,
    through the upstream key, its dm1) is its own. no_sig changes the flow sig weights, which the
    cpu scale's flow1 never reads (sig_start 1), so there it shares supplementary's flow1 too; at
    the paper scale (sig terms from step 0) it does not."""
    from demon_lab.pipeline.stages.schedule import stage_dirs

    keys = {}
    with initialize_config_dir(CONF, version_base="1.3"):
        for loss in ("supplementary", "no_normals", "depth_sig_1000", "no_confidence", "no_sig"):
            cfg = compose("config", ["scale=cpu", "+experiment=loss_weights", f"loss={loss}"])
            keys[loss] = [d.key for d in stage_dirs(settings(cfg))]
    flow1 = {loss: k[0] for loss, k in keys.items()}
    dm1 = {loss: k[1] for loss, k in keys.items()}
    assert flow1["no_normals"] == flow1["depth_sig_1000"] == flow1["supplementary"] != flow1["no_confidence"]
    assert flow1["no_sig"] == flow1["supplementary"]
    assert len(set(dm1.values())) == 5
    with initialize_config_dir(CONF, version_base="1.3"):
        paper = {loss: stage_dirs(settings(compose("config", ["scale=paper", "+experiment=loss_weights",
                                                              f"loss={loss}"])))[0].key
                 for loss in ("supplementary", "no_sig")}
    assert paper["no_sig"] != paper["supplementary"]


LEARNED_CHOICES = {  # the study's row -> what it turns off, as the row's overrides set it
    "no_correlation": {"model.correlation": None},
    "no_layers_first": {"schedule.stages.flow1.layers_first": None},
    "no_fresh_scenes": {"schedule.stages.flow1.fresh_scenes": 0, "schedule.stages.dm1.fresh_scenes": 0},
    "no_gt_flow_warmup": {"schedule.stages.dm1.gt_flow_warmup": 0},
    "no_keep_best": {f"schedule.stages.{s}.keep_best": 0 for s in ("flow1", "dm1", "iterative")},
    "profile_steps": {"scale.steps.flow1": 5000, "scale.steps.dm1": 2500,  # (and the stages that read them)
                      "schedule.stages.flow1.steps": 5000, "schedule.stages.dm1.steps": 2500},
    "no_previous": {"model.flow2_prior": None, "model.dm2_prior": None},
    "untrained": {"train": False},
}


def _leaves(node, prefix=""):
    if isinstance(node, dict):
        return {k: v for key, value in node.items() for k, v in _leaves(value, f"{prefix}{key}.").items()}
    return {prefix[:-1]: node}


def test_the_learned_design_has_no_classical_prior_and_its_study_turns_each_choice_off_alone():
    """design=learned: no DIS flow, no RANSAC motion, its choices set; the profile and DeMoN's design
    set none of its new options; each row of ablations/learned_design.yaml differs from row learned in
    exactly the keys its name turns off (and its row tag), and every row composes the design."""
    from demon_lab.pipeline.identity import semantic_config

    spec = yaml.safe_load((resources.STUDIES / "learned_design.yaml").read_text())
    with initialize_config_dir(CONF, version_base="1.3"):
        learned = compose("config", ["design=learned"])
        others = [compose("config", []), compose("config", ["+experiment=cpu_departures", *DEMON_DESIGN])]
        rows = {}
        for run in spec["runs"]:
            assert "seed=0,1,2" in run  # every row at 3 seeds (a sweep: composed here at seed 0)
            cfg = compose("config", [o for o in run if not o.startswith("seed=")])
            rows[cfg.row] = _leaves(OmegaConf.to_container(cfg, resolve=True))
    assert (learned.model.flow1_prior, learned.model.dm1_prior) == (None, None)
    assert learned.model.correlation == [8, 2] and learned.model.flow2_prior == "previous"
    stages = learned.schedule.stages
    assert stages.flow1.fresh_scenes > 0 and stages.dm1.fresh_scenes > 0 and stages.dm1.gt_flow_warmup > 0
    assert stages.flow1.keep_best > 0 and stages.dm1.keep_best > 0 and stages.flow1.layers_first > 0
    for cfg in others:
        for stage in cfg.schedule.stages.values():
            assert not {"fresh_scenes", "keep_best"} & set(stage)
    assert set(rows) == {"learned", *LEARNED_CHOICES}
    semantic = _leaves(semantic_config(settings(learned)))
    base = {k: v for k, v in rows["learned"].items() if k in semantic}
    for row, turned_off in LEARNED_CHOICES.items():
        changed = {k: v for k, v in rows[row].items() if k in semantic and base.get(k) != v}
        assert changed == turned_off, row


@pytest.mark.parametrize("option", ["schedule.stages.flow1.fresh_scenes=0.1", "schedule.stages.flow1.keep_best=100",
                                    "schedule.stages.dm1.fresh_scenes=0.1", "schedule.stages.dm1.keep_best=100"])
def test_fresh_scenes_and_keep_best_key_their_stage_and_the_later_ones_only(option):
    """Set on a stage, either option keys that stage and (through the upstream keys) the later ones;
    the earlier stages keep their keys. keep_best also keys the held-apart sets that choose."""
    from demon_lab.pipeline.stages.schedule import stage_dirs

    with initialize_config_dir(CONF, version_base="1.3"):
        plain = [d.key for d in stage_dirs(settings(compose("config", ["scale=cpu"])))]
        changed = [d.key for d in stage_dirs(settings(compose("config", ["scale=cpu", f"+{option}"])))]
        other_val = [d.key for d in stage_dirs(settings(compose("config", ["scale=cpu", f"+{option}",
                                                                  "data.val=${data.test}"])))]
    first = 0 if ".flow1." in option else 1
    assert changed[:first] == plain[:first]
    assert all(a != b for a, b in zip(plain[first:], changed[first:], strict=True))
    assert (other_val == changed) == ("fresh_scenes" in option)


def _stage_runs(c, run_id: str) -> dict:
    """The stage runs of a job's run, by stage name."""
    stages = c.search_runs([c.get_experiment_by_name("default").experiment_id],
                           filter_string=f"tags.`mlflow.parentRunId` = '{run_id}'")
    return {r.data.tags["demon_lab.stage"]: r for r in stages}


@pytest.mark.slow
def test_the_learned_design_trains_every_stage_keeping_its_best_nets_on_fresh_scenes(tmp_path):
    """design=learned end to end at the smoke scale (its own data loader worker): every stage run
    FINISHED, the stages with keep_best log which step they kept, and the fresh scenes that flow1
    and dm1 drew were rendered into the cache beyond the set's own scenes."""
    from demon_lab.app.job import run

    steps = [f"scale.steps.{s}={n}" for s, n in (("flow1", 8), ("dm1", 8), ("flow2", 2), ("dm2", 2), ("iterative", 2),
                                                 ("refine", 2))]
    cache = tmp_path / "scenes"
    overrides = [o for o in smoke_overrides(tmp_path) if not o.startswith("data.cache_dir=")]
    cfg = compose_config([*overrides, "design=learned", *steps, f"data.cache_dir={cache}", "threads=1",
                                         "schedule.stages.flow1.fresh_scenes=0.5", "schedule.stages.flow1.keep_best=4",
                                         "schedule.stages.dm1.keep_best=4", "schedule.stages.iterative.keep_best=1"])
    result = run(cfg)
    assert result["status"] == "finished"
    c = client(tmp_path)
    by_stage = _stage_runs(c, result["run_id"])
    assert len(by_stage) == 6 and all(r.info.status == "FINISHED" for r in by_stage.values())
    figures = c.get_run(result["run_id"]).data.metrics
    for stage, metric in (("flow1", "epe"), ("dm1", "tran_deg"), ("iterative", "tran_deg")):
        assert figures[f"stage/{stage}/keep_best_step"] in ({4.0, 8.0} if stage != "iterative" else {1.0, 2.0})
        assert f"stage/{stage}/keep_best_{metric}" in figures and figures[f"stage/{stage}/keep_best_seconds"] >= 0
    assert "stage/refine/keep_best_step" not in figures
    assert result["figures"]["flow1"]["keep_best_step"] == figures["stage/flow1/keep_best_step"]
    rendered = {(p.parent.name, int(p.stem)) for p in cache.glob("synthetic/synthetic_*-*/[0-9]*.pt")}
    from demon_lab.data.datasets import SPLIT_SEEDS

    # training scenes past the sets' own
    fresh = [(name, i) for name, i in rendered if cfg.data.train_length <= i < SPLIT_SEEDS["val"]]
    # rendered ahead of the stage that first draws them
    ahead = figures["stage/flow1/fresh_scenes_rendered"] + figures.get("stage/dm1/fresh_scenes_rendered", 0)
    assert len(fresh) == ahead
    assert len(fresh) > 0


def test_the_profiles_priors_alone_are_scored_beside_the_chain_and_change_none_of_its_rows(tmp_path, monkeypatch):
    """With both bootstrap priors, the evaluation scores the priors alone (no net) as pass 'priors':
    the untrained chain's pass 0 reads the same motion (dm1's correction starts at none), so their
    motion errors agree; the chain's own rows are those of an evaluation without the priors row, digit
    for digit; a chain without the priors has no such row, nor does an oracle's."""
    from demon_lab.data.datasets import SyntheticDataset
    from demon_lab.nets.chain import DeMoN
    from demon_lab.pipeline.evaluate import evaluate_dataset, summarize
    from demon_lab.pipeline.stages.schedule import build_chain

    cfg = compose_config(smoke_overrides(tmp_path, "model.flow1_prior=dis_x2", "model.dm1_prior=ransac_prior"))
    chain = build_chain(settings(cfg)).eval()
    dataset = SyntheticDataset("synthetic_sun3d", split="test", length=3, size=(64, 64), cache_dir=shared_renders())
    rows, _ = evaluate_dataset(chain, dataset, iterations=1)
    priors = [r for r in rows if r["it"] == "priors"]
    first = [r for r in rows if r["it"] == 0]
    assert len(priors) == 3 and [r["id"] for r in priors] == [r["id"] for r in first]
    for p, c in zip(priors, first, strict=True):
        assert p["rot_deg"] == pytest.approx(c["rot_deg"], abs=1e-3) and p["tran_deg"] == pytest.approx(c["tran_deg"],
                                                                                                          abs=1e-3)
        assert math.isfinite(p["epe"]) and math.isfinite(p["sc_inv"])
    summary = summarize(rows, 1)
    assert summary["priors/tran_deg"] == pytest.approx(sum(r["tran_deg"] for r in priors) / 3)
    monkeypatch.setattr(DeMoN, "priors_alone", lambda self, pair, intrinsics: None)
    without, _ = evaluate_dataset(chain, dataset, iterations=1)
    assert without == [r for r in rows if r["it"] != "priors"]
    monkeypatch.undo()
    assert not [r for r in evaluate_dataset(chain, dataset, iterations=0, oracle="flow")[0] if r["it"] == "priors"]
    plain = build_chain(settings(compose_config(smoke_overrides(tmp_path)))).eval()
    assert not [r for r in evaluate_dataset(plain, dataset, iterations=0)[0] if r["it"] == "priors"]


def test_a_profiled_stage_logs_its_loops_largest_parts_and_keeps_its_keys():
    """trainer.profile=true: the SimpleProfiler's actions become figures named as metrics, the largest first,
    with the time outside the batches and the loader; the option is in no key."""
    from demon_lab.pipeline import identity
    from demon_lab.pipeline.stages.training import LOOP_PARTS, loop_parts

    durations = {"run_training_epoch": [9.0], "run_training_batch": [0.5] * 10,
                 "[_TrainingEpochLoop].train_dataloader_next": [0.1] * 10,
                 "[Callback]KeepBest.on_train_batch_end": [0.0] * 9 + [1.5],
                 **{f"[LightningModule]FlowStage.hook{i}": [0.01 * i] for i in range(12)}}
    figures = loop_parts(durations, seconds=8.0)
    assert list(figures)[:3] == ["profile/run_training_batch_seconds",
                                 "profile/callback.KeepBest.on_train_batch_end_seconds",
                                 "profile/trainingepochloop.train_dataloader_next_seconds"]
    assert len(figures) == LOOP_PARTS + 1 and "profile/run_training_epoch_seconds" not in figures
    assert figures["profile/outside_seconds"] == pytest.approx(8.0 - 5.0 - 1.0)
    assert not identity.is_semantic("trainer.profile")
    assert identity.run_key(settings(compose_config(["scale=smoke", "trainer.profile=true"]))) == \
        identity.run_key(settings(compose_config(["scale=smoke"])))


@pytest.mark.slow
def test_the_fit_design_trains_every_stage_with_its_flow_refinement_motion_fit_and_geometric_residual(tmp_path):
    """design=fit end to end at the smoke scale: every stage run FINISHED, flow1r (between flow1 and dm1)
    trains the flow refinement on its sequence loss (and its confidence head), dm1, dm2 and the iterative
    stage log the fitted motion's geometric residual among their loss terms (dm1 and dm2 also their
    weights' classification, loss.fit_weight), and the passes' motions are scored."""
    from demon_lab.app.job import run

    steps = [f"scale.steps.{s}={n}" for s, n in (("flow1", 4), ("flow1r", 4), ("dm1", 4), ("flow2", 2), ("dm2", 2),
                                                 ("iterative", 2), ("refine", 2))]
    cfg = compose_config([*smoke_overrides(tmp_path), "design=fit", *steps, "threads=1", "iterations=1",
                          "schedule.stages.flow1r.keep_best=2", "schedule.stages.flow1r.fresh_scenes=0",
                          "schedule.stages.flow1.keep_best=0", "schedule.stages.dm1.keep_best=0",
                          "schedule.stages.iterative.keep_best=0", "schedule.stages.flow1.fresh_scenes=0",
                          "schedule.stages.dm1.fresh_scenes=0"])
    result = run(cfg)
    assert result["status"] == "finished"
    c = client(tmp_path)
    by_stage = _stage_runs(c, result["run_id"])
    assert len(by_stage) == 7 and all(r.info.status == "FINISHED" for r in by_stage.values())
    assert [k for k in by_stage["flow1r"].data.metrics if k.endswith("flow2_refined")]
    assert [k for k in by_stage["flow1r"].data.metrics if k.endswith("flow_precise")]  # its confidence head
    for stage in ("dm1", "dm2", "iterative"):
        terms = [k for k in by_stage[stage].data.metrics if k.endswith("fit_residual")]
        assert terms and all(math.isfinite(by_stage[stage].data.metrics[k]) for k in terms), (stage, terms)
    for stage in ("dm1", "dm2"):  # the weights classified against the precise vectors (loss.fit_weight)
        terms = [k for k in by_stage[stage].data.metrics if k.endswith("fit_weight")]
        assert terms and all(math.isfinite(by_stage[stage].data.metrics[k]) for k in terms), (stage, terms)
    assert not [k for k in by_stage["flow1"].data.metrics if k.endswith("fit_residual")]
    metrics = c.get_run(result["run_id"]).data.metrics
    assert all(math.isfinite(metrics[f"test/synthetic_sun3d/it{i}/tran_deg"]) for i in (0, 1))
