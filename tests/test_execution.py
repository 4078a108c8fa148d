"""Precision, memory layout and compilation (demon_lab.core.execution): the float32 islands inside
autocast, the keys, the one-line refusals, and the smoke pipeline in bf16-mixed with channels-last
(into MLflow, within a stated tolerance of float32) and with compiled nets."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from conftest import random_scene

from demon_lab.core import execution, loss_maps, losses, warping
from demon_lab.core import geometry as geo
from demon_lab.nets.chain import DeMoN, depth_motion_net_inputs, flow_net_inputs, ground_truth_inputs
from demon_lab.pipeline.config import ConfigError
from demon_lab.pipeline.identity import run_key
from demon_lab.pipeline.stages.schedule import stage_dirs
from demon_lab.pipeline.validate import validate
from tests.jobs import DEMON_DESIGN, client, compose_config, settings, smoke_overrides


def test_precision_names_are_lightnings():
    for value, name in [(32, "32-true"), ("32", "32-true"), ("32-true", "32-true"), ("bf16", "bf16-mixed"),
                        ("bf16-mixed", "bf16-mixed"), ("16-mixed", "16-mixed"), (16, "16-mixed")]:
        assert execution.normalize_precision(value) == name
    for bad in ("64", "fp16", True, None, "bf16-true"):
        with pytest.raises(ValueError, match="precision: expected one of 32, bf16-mixed, 16-mixed"):
            execution.normalize_precision(bad)
    assert execution.autocast_dtype(32) is None and execution.autocast_dtype("bf16-mixed") is torch.bfloat16


def _scene_inputs():
    inv, motion, K = random_scene(2, 64, 64, dtype=torch.float32, seed=7)
    flow = geo.flow_from_depth_motion(inv, motion, K)
    image = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(7))
    pred = 1 / (1.5 + 4 * torch.rand(2, 1, 64, 64, generator=torch.Generator().manual_seed(8)))
    return inv, motion, K, flow, image, pred


def _loss_targets(inv, m, K):
    return losses.ground_truth({"inv_depth": inv, "motion": m, "intrinsics": K})


W = {k: 1.0 for k in losses.WEIGHT_KEYS}
ISLANDS = {
    "flow_from_depth_motion": lambda inv, m, K, f, im, p: geo.flow_from_depth_motion(inv, m, K),
    "depth_from_flow_motion": lambda inv, m, K, f, im, p: geo.depth_from_flow_motion(f, m, K),
    "normals_from_depth": lambda inv, m, K, f, im, p: geo.normals_from_depth(inv, K),
    "angle_axis_to_matrix": lambda inv, m, K, f, im, p: geo.angle_axis_to_matrix(m[:, :3]),
    "matrix_to_angle_axis": lambda inv, m, K, f, im, p: geo.matrix_to_angle_axis(geo.angle_axis_to_matrix(m[:, :3])),
    "matrix_to_quaternion": lambda inv, m, K, f, im, p: geo.matrix_to_quaternion(geo.angle_axis_to_matrix(m[:, :3])),
    "reproject": lambda inv, m, K, f, im, p: geo.reproject(inv, m, K),
    "triangulation_angle": lambda inv, m, K, f, im, p: geo.triangulation_angle(inv, m, K),
    "visibility_mask": lambda inv, m, K, f, im, p: geo.visibility_mask(inv, m, K),
    "warp_image": lambda inv, m, K, f, im, p: warping.warp_image(im, torch.nan_to_num(f)),
    "warp2d": lambda inv, m, K, f, im, p: warping.warp2d(im, torch.nan_to_num(f)),
    "scale_invariant_gradients": lambda inv, m, K, f, im, p: loss_maps.scale_invariant_gradients(p),
    "median_downsample": lambda inv, m, K, f, im, p: loss_maps.median_downsample(p),
    "inverse_depth_pyramid": lambda inv, m, K, f, im, p: loss_maps.inverse_depth_pyramid(p, levels=3),
    "sig_loss": lambda inv, m, K, f, im, p: losses.sig_loss(p, inv),
    # (the predictions: slices and flips of the inputs, exact in any precision; the targets from the
    # float32 batch, as training computes them)
    "flow_loss": lambda inv, m, K, f, im, p: losses.flow_loss(
        torch.cat([f.flip(1), im[:, :2]], 1)[:, :, ::32, ::32], torch.cat([f.flip(1), im[:, :2]], 1)[:, :, ::4, ::4],
        _loss_targets(inv.float(), m.float(), K.float()), W, ramp=1.0, level5=0.5),
    "depth_motion_loss": lambda inv, m, K, f, im, p: losses.depth_motion_loss(
        p[:, :, ::4, ::4], im[:, :, ::4, ::4], m.flip(1), _loss_targets(inv.float(), m.float(), K.float()), W,
        ramp=1.0),
    "refine_loss": lambda inv, m, K, f, im, p: losses.refine_loss(p, _loss_targets(inv.float(), m.float(), K.float()),
                                                                  W, ramp=1.0),
    "ground_truth_inputs": lambda inv, m, K, f, im, p: ground_truth_inputs({"inv_depth": inv, "motion": m}, K),
    "flow_net_inputs": lambda inv, m, K, f, im, p: flow_net_inputs(im, p, geo.normals_from_depth(p, K), m, K),
    "depth_motion_net_inputs": lambda inv, m, K, f, im, p: depth_motion_net_inputs(im, torch.nan_to_num(f),
                                                                                  torch.ones_like(f), m, K),
}


def _tensors(x) -> list[torch.Tensor]:
    """Every tensor in a result (a tensor, a tuple or list, a dict, a dataclass)."""
    if isinstance(x, torch.Tensor):
        return [x]
    if dataclasses.is_dataclass(x):
        return _tensors([getattr(x, f.name) for f in dataclasses.fields(x)])
    if isinstance(x, dict):
        return _tensors(list(x.values()))
    return [t for v in x for t in _tensors(v)]


@pytest.mark.parametrize("name", sorted(ISLANDS))
def test_a_float32_island_computes_the_float32_result_inside_autocast(name):
    """Half-precision inputs under bf16 autocast give exactly the float32 computation on those inputs
    (rounded to bf16 and cast back); outside autocast the function is called as it is."""
    fn = ISLANDS[name]
    inputs = _scene_inputs()
    half = [x.bfloat16() for x in inputs]
    expected = _tensors(fn(*[x.float() for x in half]))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = _tensors(fn(*half))
    assert len(got) == len(expected) > 0
    for g, e in zip(got, expected):
        assert g.dtype == (torch.float32 if e.is_floating_point() else e.dtype)
        torch.testing.assert_close(g, e, rtol=0, atol=0, equal_nan=True)


def test_an_island_casts_half_inputs_outside_autocast_too():
    """An island called from another (where autocast is already off) still computes in float32."""
    *_, pred = _scene_inputs()
    half = pred.bfloat16()
    got = loss_maps.scale_invariant_gradients(half)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, loss_maps.scale_invariant_gradients(half.float()), rtol=0, atol=0, equal_nan=True)
    assert loss_maps.scale_invariant_gradients.__wrapped__(half).dtype == torch.bfloat16  # without the island


def test_every_geometry_layer_and_loss_is_an_island():
    """A new public geometry function or loss gets the float32 island too (or a reason here)."""
    import inspect

    not_islands = {"valid_depth": "a comparison: exact in any precision",
                   "check_map": "a shape check", "normalised_grid": "pixel centres, made in the input's own dtype"}
    loss_names = ("sig_loss", "flow_loss", "depth_motion_loss", "refine_loss", "pointwise_l2", "vector_loss",
                  "confidence_target")
    for module, names in ((geo, None), (warping, None), (loss_maps, None), (losses, loss_names)):
        for name, fn in inspect.getmembers(module, inspect.isfunction):
            if fn.__module__ != module.__name__ or name.startswith("_") or name in not_islands:
                continue
            if names is None or name in names:
                assert getattr(fn, "float32_island", False), f"{module.__name__}.{name} is not a float32 island"
    assert all(getattr(f, "float32_island", False) for f in (ground_truth_inputs, flow_net_inputs,
                                                            depth_motion_net_inputs))


def test_without_the_island_autocast_changes_the_geometry():
    """The check above is not vacuous: the same projection with the island taken away runs its
    rotation of the rays (an einsum) in bf16 under autocast."""
    inv, motion, K, *_ = _scene_inputs()
    expected = geo.flow_from_depth_motion(inv, motion, K)
    bare = geo.flow_from_depth_motion.__wrapped__
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = bare(inv, motion, K)
    assert not torch.equal(torch.nan_to_num(got.float()), torch.nan_to_num(expected))


def test_the_nets_return_float32_under_autocast_and_the_losses_too():
    torch.manual_seed(0)
    chain = DeMoN("v1", 0.125, (64, 64)).eval()
    images = torch.rand(2, 3, 64, 64) - 0.5
    K = torch.tensor([geo.DEMON_INTRINSICS] * 2)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = chain(images, images.flip(-1), K, iterations=1)
        conv = chain.flow1.conv1.y.conv(torch.cat([images, images], 1))
        inv, motion, K2 = random_scene(2, 64, 64, dtype=torch.float32)
        gt = losses.ground_truth({"inv_depth": inv, "motion": motion, "intrinsics": K2})
        p = out.passes[0]
        total, terms = losses.depth_motion_loss(p.inv_depth.bfloat16(), p.normals.bfloat16(), p.motion.bfloat16(),
                                                gt, {k: 1.0 for k in losses.WEIGHT_KEYS}, ramp=1.0)
    assert conv.dtype == torch.bfloat16  # the nets do compute in bf16
    for p in out.passes:
        assert {getattr(p, f).dtype for f in p.__dataclass_fields__} == {torch.float32}
    assert out.refined.dtype == torch.float32
    assert total.dtype == torch.float32 and {t.dtype for t in terms.values()} == {torch.float32}


def _keys(cfg) -> tuple[str, list[str]]:
    return run_key(settings(cfg)), [s.key for s in stage_dirs(settings(cfg))]


def test_precision_keys_stages_and_runs_only_off_its_default_and_layout_or_compile_none(tmp_path):
    """Precision is left out of the keys at its neutral value, whatever its spelling (the keys every run
    and stage had before the option existed: GOLDEN pins them), and the memory layout and compilation
    never enter a key."""
    from demon_lab.pipeline.identity import NEUTRAL, leave_out_neutral

    base = compose_config(smoke_overrides(tmp_path))
    for spelling in ("32", "32-true"):
        assert _keys(compose_config(smoke_overrides(tmp_path, f"precision={spelling}"))) == _keys(base)
    assert NEUTRAL["precision"] == "32-true"
    assert leave_out_neutral({"precision": 32, "model": {"compat": None, "width": 1.0}, "seed": None}) == \
        {"model": {"width": 1.0}, "seed": None}  # only the declared options, at their neutral values
    bf16 = _keys(compose_config(smoke_overrides(tmp_path, "precision=bf16-mixed")))
    assert bf16[0] != _keys(base)[0] and all(a != b for a, b in zip(bf16[1], _keys(base)[1]))
    assert _keys(compose_config(smoke_overrides(tmp_path, "precision=bf16"))) == bf16  # one name, one key
    layout = compose_config(smoke_overrides(tmp_path, "model.channels_last=true", "model.compile=true"))
    assert _keys(layout) == _keys(base)


@pytest.mark.parametrize(("overrides", "message"), [
    (["precision=fp16"], "precision: expected one of 32, bf16-mixed, 16-mixed, got 'fp16'"),
    (["precision=16-mixed", "trainer.accelerator=cpu"], "precision=16-mixed needs a CUDA device"),
    (["model.channels_last=yes"], "model.channels_last: expected true or false, got 'yes'"),
    (["model.compile=1"], "model.compile: expected true or false, got 1"),
])
def test_execution_options_are_refused_in_one_line(overrides, message, tmp_path):
    with pytest.raises(ConfigError) as e:
        validate(compose_config(smoke_overrides(tmp_path, *overrides)))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_a_baseline_job_ignores_the_chains_precision(tmp_path):
    """The precision that a chain's job refuses on a CPU is no concern of a classical method's job."""
    overrides = ("precision=16-mixed", "trainer.accelerator=cpu")
    with pytest.raises(ConfigError, match="precision=16-mixed needs a CUDA device"):
        validate(compose_config(smoke_overrides(tmp_path, "method=demon", *overrides)))
    assert validate(compose_config(smoke_overrides(tmp_path, "method=base_ff", *overrides))).precision == "16-mixed"


def _job(tmp, *extra):
    from demon_lab.app.job import run

    threads = torch.get_num_threads()
    try:
        return run(compose_config(smoke_overrides(tmp, "threads=1", "schedule.until=dm1", "iterations=0", *extra)))
    finally:
        torch.set_num_threads(threads)


@pytest.mark.slow
def test_bf16_mixed_with_channels_last_runs_the_smoke_pipeline_into_mlflow_within_tolerance(tmp_path):
    """The same smoke job (flow1 and dm1, the bootstrap pass evaluated) in float32 and in bf16-mixed
    with channels-last, from the same seed. Tolerances: the first step's loss (same weights, same
    batch: the forward pass's rounding only) within 2 %; after training, flow EPE within 2 %, L1 of
    the inverse depth and the rotation error within 5 % of float32 on every test set (measured: 0.02 %;
    0.14 %, 1.57 % and 0.73 %; ``-s`` prints them). The translation direction and sc-inv of this
    barely trained chain are ill-conditioned (a translation of norm ~1e-3; an almost constant depth):
    checked finite only."""
    fp32 = _job(tmp_path / "fp32")
    mixed = _job(tmp_path / "bf16", "precision=bf16-mixed", "model.channels_last=true")
    assert fp32["status"] == mixed["status"] == "finished"
    mlflow = client(tmp_path / "bf16")
    run = mlflow.get_run(mixed["run_id"])
    assert run.info.status == "FINISHED"
    assert run.data.params["precision"] == "bf16-mixed" and run.data.params["model.channels_last"] == "True"
    metrics = {k: v for k, v in run.data.metrics.items() if k.startswith("test/")}
    assert metrics and all(math.isfinite(v) for v in metrics.values())

    def first_loss(tmp, result):
        c = client(tmp)
        children = c.search_runs([c.get_run(result["run_id"]).info.experiment_id],
                                 f"tags.mlflow.parentRunId = '{result['run_id']}' and tags.`demon_lab.stage` = 'flow1'")
        history = c.get_metric_history(children[0].info.run_id, "train/loss")
        assert all(math.isfinite(m.value) for m in history)
        return min(history, key=lambda m: m.step).value

    loss_mixed, loss_fp32 = first_loss(tmp_path / "bf16", mixed), first_loss(tmp_path / "fp32", fp32)
    assert loss_mixed != loss_fp32  # the job did train in bf16 (same weights, same batch: only the rounding differs)
    assert loss_mixed == pytest.approx(loss_fp32, rel=0.02)
    worst = {k: max(abs(mixed["summary"][n][k] / s[k] - 1) for n, s in fp32["summary"].items())
             for k in ("epe", "l1_inv", "rot_deg")}
    print(f"bf16-mixed against float32: first step's loss {abs(loss_mixed / loss_fp32 - 1):.2%}; over the test "
          "sets at most " + ", ".join(f"{k} {v:.2%}" for k, v in worst.items()))  # (pytest -s shows it)
    for name, summary in fp32["summary"].items():
        got = mixed["summary"][name]
        assert got["epe"] == pytest.approx(summary["epe"], rel=0.02), name
        assert got["l1_inv"] == pytest.approx(summary["l1_inv"], rel=0.05), name
        assert got["rot_deg"] == pytest.approx(summary["rot_deg"], rel=0.05, abs=0.01), name
        assert math.isfinite(got["tran_deg"]) and math.isfinite(got["sc_inv"]), name


@pytest.mark.slow
def test_compile_trains_a_smoke_stage_or_is_refused_in_one_line(tmp_path):
    from demon_lab.pipeline.stages.training import prepare_chain

    cfg = compose_config(smoke_overrides(tmp_path, "model.compile=true", "schedule.until=flow1", "iterations=0",
                                         "trainer.accelerator=cpu"))
    problem = execution.compile_problem("cpu")
    if problem is not None:
        with pytest.raises(ConfigError, match=r"model\.compile=true") as e:
            validate(cfg)
        assert "\n" not in str(e.value)
        pytest.skip(f"refused as it should be here: {problem}")
    validate(cfg)
    from torch._dynamo.utils import counters

    counters.clear()
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        chain, stages, figures = prepare_chain(settings(cfg), progress=False)
    finally:
        torch.set_num_threads(threads)
    assert counters["stats"]["unique_graphs"] >= 1  # the nets did run compiled
    assert all(getattr(getattr(chain, n), "_compiled_call_impl", None) is not None
               for n in ("flow1", "dm1", "flow2", "dm2", "refine_net"))
    assert [s.name for s in stages] == ["flow1"] and stages[0].done()
    assert figures["flow1"]["steps_per_second"] > 0 and all(math.isfinite(v) for v in figures["flow1"].values())
    # the stage's weights load into an uncompiled chain under the same keys
    plain = DeMoN("v1", float(cfg.model.width), tuple(cfg.data.size))
    plain.flow1.load_state_dict(stages[0].load()["flow1"])
    for (k, a), (k2, b) in zip(plain.flow1.state_dict().items(), chain.flow1.state_dict().items()):
        assert k == k2 and torch.equal(a, b)


def test_evaluation_runs_the_nets_in_the_precision_asked_for():
    from demon_lab.data.datasets import SyntheticDataset
    from demon_lab.pipeline.evaluate import evaluate_dataset

    torch.manual_seed(3)
    chain = DeMoN("v1", 0.125, (64, 64)).eval()
    dataset = SyntheticDataset("synthetic_sun3d", "test", length=2, size=(64, 64))
    fp32, _ = evaluate_dataset(chain, dataset, iterations=0, batch_size=2)
    again, _ = evaluate_dataset(chain, dataset, iterations=0, batch_size=2, precision="32")
    bf16, _ = evaluate_dataset(chain, dataset, iterations=0, batch_size=2, precision="bf16-mixed",
                               channels_last=True)
    assert [r["epe"] for r in again] == [r["epe"] for r in fp32]
    assert [r["epe"] for r in bf16] != [r["epe"] for r in fp32]  # the nets did run in bf16
    for a, b in zip(fp32, bf16):
        assert b["epe"] == pytest.approx(a["epe"], rel=0.02) and b["l1_inv"] == pytest.approx(a["l1_inv"], rel=0.05)


def test_the_evaluation_device_follows_the_training_accelerator(tmp_path, caplog):
    cfg = compose_config(smoke_overrides(tmp_path, "trainer.accelerator=cpu"))
    assert execution.evaluation_device(cfg) == torch.device("cpu")
    here = "cuda" if torch.cuda.is_available() else ("mps" if execution._mps_available() else "cpu")
    assert execution.resolve_accelerator("auto") == here
    assert execution.resolve_accelerator("cuda") == "cuda" and execution.resolve_accelerator("cpu") == "cpu"
    if not torch.cuda.is_available():
        cfg = compose_config(smoke_overrides(tmp_path, "trainer.accelerator=cuda"))
        with caplog.at_level("INFO", logger="demon_lab.core.execution"):
            assert execution.evaluation_device(cfg) == torch.device("cpu")
        assert "no cuda device here, evaluating on the CPU" in caplog.text


GOLDEN = {  # the keys these configurations had before precision, channels-last and compile existed
    DEMON_DESIGN: ("2907aa5b1f5f6ccc", ["3dd138c21ef927e2", "1fca1025f3da4572", "54995bd435165a57",
                                        "ad9248f256cc5ae1", "0f277acf9143285f", "11d045c2fab422bf"]),
    # the cpu profile with its four priors (CHANGELOG: every key of the cpu scale's chain changed with them)
    (): ("b3e49a491ddd875d", ["4fece5ce0aac4f5e", "e8cfb0b0d6d805c0", "5819b46d56b48364", "2c873cbbbd55e7f2",
                              "e6262b4cde5c75c0", "862513d583e42a48"]),
    ("scale=paper",): ("b01069ad9b5a53e9", ["2dc7c6d575068f58", "eab06ec47ffda056", "fcff31279bd656ec",
                                            "bce9080cff5cd55a", "ad5b1a5caad91d32", "a301ba0f14d4e8c8"]),
}


@pytest.mark.parametrize("overrides", list(GOLDEN))
def test_float32_jobs_keep_the_keys_they_had(overrides):
    # on 2 threads (identity.NEUTRAL_THREADS: the count these keys were measured with), whatever this process has
    cfg = compose_config(["cache_dir=/x", "tracking.uri=sqlite:////x/m.db", "threads=2", *overrides])
    assert _keys(cfg) == (GOLDEN[overrides][0], GOLDEN[overrides][1])
    layout = compose_config(["cache_dir=/x", "tracking.uri=sqlite:////x/m.db", "threads=2", *overrides,
                             "precision=32-true", "model.channels_last=true", "model.compile=true"])
    assert _keys(layout) == _keys(cfg)


def test_precision_keys_only_what_runs_a_net(tmp_path):
    from demon_lab.pipeline.identity import sweep_key

    base = smoke_overrides(tmp_path, "method=base_ff")
    assert run_key(settings(compose_config(base))) == run_key(settings(compose_config([*base, "precision=bf16-mixed"])))
    frozen = smoke_overrides(tmp_path, "scale.steps.flow1=0")
    plain, bf16 = (stage_dirs(settings(compose_config(frozen + extra))) for extra in ([], ["precision=bf16-mixed"]))
    assert plain[0].key == bf16[0].key and plain[1].key != bf16[1].key  # flow1 trains nothing in bf16
    assert sweep_key("e", ["precision=bf16"]) == sweep_key("e", ["precision=bf16-mixed"]) \
        != sweep_key("e", ["precision=32"])


def test_the_cpu_thread_count_keys_what_a_cpu_job_trains(tmp_path):
    """The nets' weights depend on the CPU threads they train with: the keys hold the count, but for the
    neutral 2; a stage of 0 steps, a method without nets, an accelerator and the sweep leave it out."""
    from demon_lab.pipeline.identity import cpu_threads, sweep_key

    frozen = smoke_overrides(tmp_path, "scale.steps.flow1=0", "trainer.accelerator=cpu")
    one, two, four = (compose_config([*frozen, f"threads={n}"]) for n in (1, 2, 4))
    assert [cpu_threads(settings(c)) for c in (one, two, four)] == [{"threads": 1}, {}, {"threads": 4}]
    keys = [_keys(c) for c in (one, two, four)]
    assert len({k[0] for k in keys}) == 3 and len({k[1][1] for k in keys}) == 3
    assert keys[0][1][0] == keys[1][1][0] == keys[2][1][0]  # flow1 trains nothing: the same stage
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # threads=null: the count the job computes with now
        assert _keys(compose_config(frozen)) == keys[0]
    finally:
        torch.set_num_threads(threads)
    base = smoke_overrides(tmp_path, "method=base_ff", "trainer.accelerator=cpu")
    one, two = (settings(compose_config([*base, f"threads={n}"])) for n in (1, 2))
    assert run_key(one) == run_key(two)
    assert cpu_threads(settings(compose_config([*frozen, "threads=1", "trainer.accelerator=cuda"]))) == {}
    assert sweep_key("e", ["threads=1"]) == sweep_key("e", [])


def test_a_cluster_launch_leaves_the_device_checks_to_the_job(tmp_path):
    from demon_lab.__main__ import check

    args = smoke_overrides(tmp_path, "precision=16-mixed", "trainer.accelerator=cpu")
    assert "precision=16-mixed needs a CUDA device" in check(args)
    assert check(["-m", *args, "hydra/launcher=slurm"]) is None  # checked by the job, where it runs
    with pytest.raises(ConfigError, match="needs a CUDA device"):
        validate(compose_config(args))


@pytest.mark.parametrize("env, devices, rank", [
    ({}, 1, 0),
    ({"TORCHELASTIC_RUN_ID": "job", "RANK": "3", "LOCAL_RANK": "1", "GROUP_RANK": "1"}, 2, 3),  # torchrun
    ({"SLURM_NTASKS": "4", "SLURM_NTASKS_PER_NODE": "2", "SLURM_PROCID": "2", "SLURM_JOB_NAME": "train"}, 2, 2),  # srun
    ({"LOCAL_RANK": "1", "NODE_RANK": "1"}, 4, 5),  # a process Lightning's launcher started: node x devices + local
    # an interactive SLURM shell is not a SLURM launch (Lightning's rule): the local launcher's rank
    ({"SLURM_NTASKS": "1", "SLURM_PROCID": "0", "SLURM_JOB_NAME": "bash", "LOCAL_RANK": "1"}, 2, 1),
])
def test_the_rank_is_the_one_lightnings_cluster_environments_give(env, devices, rank, monkeypatch):
    from types import SimpleNamespace

    for var in ("TORCHELASTIC_RUN_ID", "RANK", "LOCAL_RANK", "GROUP_RANK", "NODE_RANK", "SLURM_NTASKS", "SLURM_PROCID",
                "SLURM_NTASKS_PER_NODE",
                "SLURM_JOB_NAME"):
        monkeypatch.delenv(var, raising=False)
    for var, value in env.items():
        monkeypatch.setenv(var, value)
    cfg = SimpleNamespace(trainer=SimpleNamespace(devices=devices, num_nodes=2))
    assert execution.global_rank(cfg) == rank
