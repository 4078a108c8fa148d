"""The losses and their schedules: each term by hand, the presets, the learning-rate schedules and warm-up,
and each stage kind's terms as they ramp, fade and start."""

from __future__ import annotations

import math

import pytest
import torch

from demon_lab import resources
from demon_lab.core import losses
from demon_lab.nets import DeMoN


def test_pointwise_l2_hand_computed():
    pred = torch.tensor([[[[3.0, 0.0]], [[4.0, 0.0]]]])  # (1, 2, 1, 2)
    gt = torch.tensor([[[[0.0, math.nan]], [[0.0, 0.0]]]])
    # pixel 0: sqrt(9 + 16 + eps); pixel 1: NaN GT -> d = 0 -> sqrt(eps), still counted
    expected = (math.sqrt(25 + 1e-5) + math.sqrt(1e-5)) / 2
    assert losses.pointwise_l2(pred, gt).item() == pytest.approx(expected)


def test_a_non_finite_prediction_is_not_hidden_by_the_ground_truth_mask():
    """Missing ground truth is masked; a diverged net's NaN/inf where there is ground truth makes
    the loss non-finite, so the stage stops with the step and terms instead of training on."""
    gt = torch.tensor([[[[0.0, math.nan]], [[0.0, 0.0]]]])
    for bad in (math.nan, math.inf):
        pred = torch.tensor([[[[bad, 0.0]], [[0.0, 0.0]]]], requires_grad=True)
        assert not torch.isfinite(losses.pointwise_l2(pred, gt))
    pred = torch.tensor([[[[0.0, math.nan]], [[0.0, 0.0]]]], requires_grad=True)  # NaN where gt is missing
    loss = losses.pointwise_l2(pred, gt)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()


def test_vector_loss_and_confidence_target():
    pred = torch.tensor([[1.0, -2.0, 0.0]])
    assert losses.vector_loss(pred, torch.zeros(1, 3)).item() == pytest.approx(
        math.sqrt(1 + 1e-5) + math.sqrt(4 + 1e-5) + math.sqrt(1e-5))
    conf = losses.confidence_target(torch.tensor([[0.1, 0.0]]), torch.tensor([[0.0, 0.0]]))
    torch.testing.assert_close(conf, torch.tensor([[math.exp(-1.0), 1.0]]))


def test_sig_loss_is_zero_for_a_scaled_copy_and_positive_otherwise():
    x = torch.rand(2, 1, 16, 16) + 0.5
    assert losses.sig_loss(3 * x, x, eps_pred=0, eps_gt=0).item() == pytest.approx(math.sqrt(1e-5), rel=1e-3)
    assert losses.sig_loss(x.flip(-1), x).item() > 0.05


def test_ramps():
    assert losses.ease_out_quad(0, 100) == 0 and losses.ease_out_quad(50, 100) == 0.75
    assert losses.ease_out_quad(200, 100) == 1 and losses.ease_out_quad(5, 0) == 1
    assert losses.ease_in_quad_down(0, 100) == 1 and losses.ease_in_quad_down(50, 100) == 0.75
    assert losses.ease_in_quad_down(100, 100) == 0
    # DeMoN's dm1 depth-sig ramp runs over twice the stage: it ends at 75 %
    assert losses.ease_out_quad(1_000_000, 2_000_000) == 0.75


_preset = losses.preset


def test_loss_presets():
    supp = losses.check_weights(_preset("supplementary"))
    assert (supp["flow"], supp["flow_conf"], supp["depth"], supp["normals"], supp["flow_sig"],
            supp["depth_sig"], supp["translation"], supp["rotation"]) == (1000, 1000, 300, 100, 1000, 1500, 15, 160)
    code = losses.check_weights(_preset("released_code"))
    assert (code["flow"], code["flow_conf"], code["flow_sig"], code["depth"], code["depth_sig"],
            code["normals"], code["translation"]) == (500, 25, 250, 150, 375, 25, 45)
    assert losses.check_weights(_preset("no_sig"))["depth_sig"] == 0
    assert losses.check_weights(_preset("no_normals"))["normals"] == 0
    assert losses.check_weights(_preset("no_confidence"))["flow_conf"] == 0
    assert losses.check_weights(_preset("depth_sig_1000"))["depth_sig"] == 1000
    with pytest.raises(ValueError, match="missing"):
        losses.check_weights({"flow": 1.0})


def test_every_term_is_reported_and_weighted():
    torch.manual_seed(4)
    H, W = 64, 64
    batch = {"inv_depth": torch.rand(2, 1, H, W) + 0.2, "motion": torch.tensor([[0, 0.1, 0, 1.0, 0, 0]] * 2),
             "intrinsics": torch.tensor([[0.9, 1.2, 0.5, 0.5]] * 2)}
    gt = losses.ground_truth(batch)
    assert gt["inv_depth2"].shape == (2, 1, 16, 16) and gt["flow5"].shape == (2, 2, 2, 2)
    weights = losses.check_weights(_preset("supplementary"))
    flow5, flow2 = torch.rand(2, 4, 2, 2), torch.rand(2, 4, 16, 16)
    total, terms = losses.flow_loss(flow5, flow2, gt, weights, ramp=0.5, level5=0.25)
    assert set(terms) == {"flow2", "conf2", "flow2_sig", "conf2_sig", "flow5", "conf5"}
    assert total.item() == pytest.approx(sum(t.item() for t in terms.values()))
    assert terms["flow5"].item() == pytest.approx(1000 * 0.25 * losses.pointwise_l2(flow5[:, :2], gt["flow5"]).item())
    _, no5 = losses.flow_loss(flow5, flow2, gt, weights, level5=0.0)
    assert "flow5" not in no5
    total, terms = losses.depth_motion_loss(torch.rand(2, 1, 16, 16), torch.rand(2, 3, 16, 16),
                                            torch.zeros(2, 6), gt, weights)
    assert set(terms) == {"depth2", "depth2_sig", "normal2", "rotation", "translation"}
    assert terms["translation"].item() == pytest.approx(15 * (1 + 2 * math.sqrt(1e-5) + 0), rel=1e-4)


def test_released_learning_rate_is_constant_for_a_third_then_decays_quadratically_to_1e6():
    from demon_lab.pipeline.stages.base import learning_rate

    lr = lambda step: learning_rate(step, 300, 1e-3, "released")  # noqa: E731
    assert lr(0) == lr(100) == 1e-3
    assert lr(200) == pytest.approx(1e-3 + (1e-6 - 1e-3) * 0.25)  # half-way through the decay
    assert lr(300) == pytest.approx(1e-6)


def test_supplementary_learning_rate_drops_20_percent_at_each_milestone():
    from demon_lab.pipeline.stages.base import learning_rate

    lr = [learning_rate(s, 100, 1.0, "supplementary") for s in (0, 39, 40, 60, 80, 99)]
    assert lr == pytest.approx([1.0, 1.0, 0.8, 0.64, 0.512, 0.512])
    with pytest.raises(ValueError, match=r"schedule\.lr_schedule"):
        learning_rate(0, 100, 1.0, "cosine")


def test_warmup_rises_linearly_to_the_schedule():
    from demon_lab.pipeline.stages.base import learning_rate

    assert learning_rate(0, 3000, 1e-3, "released", warmup_steps=100) == pytest.approx(1e-5)
    assert learning_rate(49, 3000, 1e-3, "released", warmup_steps=100) == pytest.approx(5e-4)
    assert learning_rate(99, 3000, 1e-3, "released", warmup_steps=100) == 1e-3
    assert learning_rate(2999, 3000, 1e-3, "released", warmup_steps=100) == learning_rate(2999, 3000, 1e-3, "released")


def _stage_batch() -> dict:
    """Two rendered 64x64 training pairs (not cached), batched, for the stage tests below."""
    from torch.utils.data import default_collate

    from demon_lab.data.datasets import SyntheticDataset

    ds = SyntheticDataset("synthetic_sun3d", "train", length=2, size=(64, 64), supersample=1, cache_dir=False)
    return default_collate([{k: v for k, v in ds[i].items() if k != "id"} for i in range(2)])


def _module(chain, spec, **options):
    """The LightningModule that trains ``spec`` (a stage of its kind) on ``chain``, with the released code's
    loss weights."""
    from demon_lab.pipeline.stages.base import StageModule

    return StageModule(chain, spec, weights=_preset("released_code"), **options)


def _terms_at(stage, batch, gt, steps) -> dict[int, dict]:
    """The stage's loss terms on ``batch`` with its global step at each of ``steps``."""
    from unittest import mock

    out = {}
    for step in steps:
        with mock.patch.object(type(stage), "global_step", new_callable=mock.PropertyMock, return_value=step):
            out[step] = {k: float(v) for k, v in stage.stage_loss(batch, gt)[1].items()}
    return out


@pytest.mark.parametrize("sig_start", [0.0, 0.5, 1.0])
def test_flow_stage_sig_terms_start_at_sig_start(sig_start):
    from demon_lab.pipeline.kinds import FlowStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    stage = _module(chain, FlowStage(name="flow1", steps=300, lr=1e-3, net="flow1", sig_start=sig_start))
    batch = _stage_batch()
    terms = _terms_at(stage, batch, losses.ground_truth(batch), (0, 100, 149, 151, 250, 299))
    sig = {step: t["flow2_sig"] for step, t in terms.items()}
    if sig_start == 1.0:  # never: the whole stage trains without the sig terms
        assert set(sig.values()) == {0.0}
        return
    expected = {s: losses.ease_out_quad(max(s - sig_start * 300, 0), 100) for s in sig}
    unit = sig[250] / expected[250]  # the full-weight sig term (ramp 1 at step 250 either way)
    assert sig == pytest.approx({s: unit * e for s, e in expected.items()}, rel=1e-5)
    assert (sig[149] == 0) == (sig_start == 0.5) and sig[151] > 0


def test_a_sig_term_of_weight_zero_is_skipped_bit_for_bit(monkeypatch):
    """At ramp 0 the sig images are not computed; the loss and every gradient are those of the
    full product weight x sig, to the last bit."""
    torch.manual_seed(0)
    batch = _stage_batch()
    gt = losses.ground_truth(batch)
    pred5 = torch.randn(2, 4, *gt["flow5"].shape[-2:], requires_grad=True)
    pred2 = torch.randn(2, 4, *gt["flow2"].shape[-2:], requires_grad=True)
    weights = _preset("released_code")

    def loss_and_grads(fn):
        pred5.grad = pred2.grad = None
        total, terms = fn()
        total.backward()
        return total.detach(), {k: v.detach() for k, v in terms.items()}, pred5.grad.clone(), pred2.grad.clone()

    sig = losses.sig_loss
    monkeypatch.setattr(losses, "sig_loss", lambda *a: (_ for _ in ()).throw(AssertionError("sig computed")))
    skipped = loss_and_grads(lambda: losses.flow_loss(pred5, pred2, gt, weights, ramp=0.0))
    assert skipped[1]["flow2_sig"] == 0 and skipped[1]["conf2_sig"] == 0
    # the product, written out: the terms of flow_loss with weight x ramp x sig at ramp 0
    monkeypatch.setattr(losses, "sig_loss", sig)
    monkeypatch.setattr(losses, "_sig_term", lambda w, p, g, *eps: w * sig(p, g, *eps))
    product = loss_and_grads(lambda: losses.flow_loss(pred5, pred2, gt, weights, ramp=0.0))
    assert torch.equal(skipped[0], product[0]) and torch.equal(skipped[2], product[2])
    assert torch.equal(skipped[3], product[3]) and product[1]["flow2_sig"] == 0


def test_the_depth_sig_terms_keep_their_eps_and_ramp():
    """At ramp > 0 the depth-sig terms are weight x ramp x sig_loss with DeMoN's eps (0.01 on the
    prediction, 0.001 on the ground truth), in the depth-motion and the refinement loss."""
    torch.manual_seed(0)
    batch = _stage_batch()
    gt = losses.ground_truth(batch)
    weights = _preset("released_code")
    inv2 = torch.rand_like(gt["inv_depth2"]) + 0.1
    _, terms = losses.depth_motion_loss(inv2, torch.randn(2, 3, *inv2.shape[-2:]), torch.randn(2, 6), gt, weights,
                                        ramp=0.3)
    expect = weights["depth_sig"] * 0.3 * losses.sig_loss(inv2, gt["inv_depth2"], 1e-2, 1e-3)
    assert torch.equal(terms["depth2_sig"], expect)
    assert not torch.equal(expect, weights["depth_sig"] * 0.3 * losses.sig_loss(inv2, gt["inv_depth2"]))
    refined = torch.rand(2, 1, *gt["inv_depth0"].shape[-2:]) + 0.1
    _, terms = losses.refine_loss(refined, gt, weights, ramp=0.6)
    assert torch.equal(terms["depth0_sig"],
                       weights["refine_depth_sig"] * 0.6 * losses.sig_loss(refined, gt["inv_depth0"], 1e-2, 1e-3))


@pytest.mark.parametrize("fade", [None, 1.0, 3.0])
def test_flow_stage_level5_terms_fade_over_level5_fade(fade):
    """DeMoN fades the level-5 terms out over the first third of a flow stage; ``level5_fade`` sets
    that fraction (3: at the stage's end the term is still at 1 - (1/3)^2 of its weight)."""
    from demon_lab.pipeline.kinds import FlowStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    kwargs = {} if fade is None else {"level5_fade": fade}
    stage = _module(chain, FlowStage(name="flow1", steps=300, lr=1e-3, net="flow1", sig_start=1.0, **kwargs))
    batch = _stage_batch()
    terms = _terms_at(stage, batch, losses.ground_truth(batch), (0, 50, 99, 100, 150, 299))
    level5 = {step: t.get("flow5", 0.0) for step, t in terms.items()}
    duration = 300 * (1 / 3 if fade is None else fade)
    expected = {s: losses.ease_in_quad_down(s, duration) for s in level5}
    unit = level5[0]  # the full-weight term
    assert unit > 0 and level5 == pytest.approx({s: unit * e for s, e in expected.items()}, rel=1e-5)
    assert (level5[100] == 0) == (fade is None) and (level5[299] > 0) == (fade is not None)


@pytest.mark.parametrize("warmup", [0.0, 0.5])
def test_depth_motion_stage_is_fed_ground_truth_flow_for_gt_flow_warmup(warmup):
    """``gt_flow_warmup``: ground-truth flow (with full confidence) for that first part of the stage,
    the frozen flow net's output after it; 0 (DeMoN): the flow net's throughout."""
    from unittest import mock

    from demon_lab.nets.chain import ground_truth_inputs
    from demon_lab.pipeline.kinds import DepthMotionStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    stage = _module(chain, DepthMotionStage(name="dm1", steps=300, lr=1e-3, net="dm1", gt_flow_warmup=warmup))
    batch = _stage_batch()
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    truth = ground_truth_inputs(batch, batch["intrinsics"]).flow
    with torch.no_grad():
        predicted = chain.flow1(pair)[1][:, :2]
    fed = []
    real = chain.depth_motion1  # dm1 on the flow and confidence it is fed

    def spy(pair, image2_2, flow, conf, *args):
        fed.append((flow.clone(), conf.clone()))
        return real(pair, image2_2, flow, conf, *args)

    steps = (0, 149, 150, 299)
    with mock.patch.object(chain, "depth_motion1", spy):
        _terms_at(stage, batch, losses.ground_truth(batch), steps)
    assert len(fed) == len(steps)
    for step, (flow, conf) in zip(steps, fed, strict=True):
        if step < warmup * 300:
            assert torch.equal(flow.nan_to_num(7.0), truth.nan_to_num(7.0)), step
            assert torch.equal(conf, torch.isfinite(truth).float()), step
        else:
            assert torch.equal(flow, predicted), step
    assert not torch.equal(truth.nan_to_num(0.0), predicted)


@pytest.mark.parametrize("sig_start", [0.0, 0.5, 1.0])
def test_iterative_stage_flow_sig_terms_start_at_sig_start(sig_start):
    """DeMoN's iterative stage starts at full weights (sig_start 0); with sig_start the flow sig
    terms are 0 before that fraction of the stage and at full weight after; depth-sig unaffected."""
    from demon_lab.pipeline.kinds import IterativeStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    stage = _module(chain, IterativeStage(name="iterative", steps=300, lr=1e-3, queue_size=0, sig_start=sig_start))
    for step, terms in _terms_at(stage, _stage_batch(), None, (0, 149, 151, 299)).items():
        on = step >= sig_start * 300
        assert (terms["flow2_sig"] > 0) == on and (terms["conf2_sig"] > 0) == on
        assert terms["depth2_sig"] > 0


def test_flow_sig_gradient_swamps_the_flow_term_near_zero_flow():
    """Why the cpu scale leaves out the flow stages' sig terms (conf/scale/cpu.yaml): with the released
    code's weights, the gradient of flow2_sig on the predicted flow is hundreds of times the flow2
    term's when the prediction is near zero (where an untrained flow net sits), and an order of
    magnitude less so near the ground truth. ``pytest -s -k sig_gradient`` prints the ratios."""
    from torch.utils.data import default_collate

    from demon_lab.data.datasets import SyntheticDataset

    torch.manual_seed(0)
    weights = losses.check_weights(_preset("released_code"))
    ds = SyntheticDataset("synthetic_sun3d", "train", length=8, size=(96, 128), supersample=1, cache_dir=False)
    gt = losses.ground_truth(default_collate([{k: v for k, v in ds[i].items() if k != "id"} for i in range(8)]))
    target = gt["flow2"]
    noise = torch.randn_like(target)
    ratios = {}
    for name, pred in (("zero + 0.001", 1e-3 * noise), ("zero + 0.01", 1e-2 * noise),
                       ("GT + 0.02", torch.nan_to_num(target) + 0.02 * noise),
                       ("GT + 0.05", torch.nan_to_num(target) + 0.05 * noise)):
        f = pred.clone().requires_grad_()
        g_flow, = torch.autograd.grad(weights["flow"] * losses.pointwise_l2(f, target), f)
        g_sig, = torch.autograd.grad(weights["flow_sig"] * losses.sig_loss(f, target), f)
        ratios[name] = float(g_sig.norm() / g_flow.norm())
    print("flow2_sig / flow2 gradient norm:", {k: round(v, 1) for k, v in ratios.items()})
    assert ratios["zero + 0.001"] > 100 and ratios["zero + 0.01"] > 20
    assert ratios["zero + 0.001"] > 5 * ratios["GT + 0.05"]


def test_ground_truth_is_computed_as_a_loss_reads_it_with_the_eager_values():
    """The loss targets are DeMoN's prepare_ground_truth_tensors, tensor by tensor, computed on
    first access: a flow stage builds no normals and no deeper pyramid than level 5 needs."""
    from demon_lab.core import geometry as geo
    from demon_lab.core import loss_maps

    torch.manual_seed(5)
    batch = {"inv_depth": torch.rand(2, 1, 64, 96) + 0.2, "motion": torch.tensor([[0.02, 0.1, 0, 1.0, 0.1, 0]] * 2),
             "intrinsics": torch.tensor([[0.9, 1.2, 0.5, 0.5]] * 2)}
    batch["inv_depth"][0, 0, :3, :3] = 0  # invalid pixels become NaN in the pyramid
    pyramid = loss_maps.inverse_depth_pyramid(batch["inv_depth"], levels=5)
    k = batch["intrinsics"]
    eager = {"inv_depth0": pyramid[0], "inv_depth1": pyramid[1], "inv_depth2": pyramid[2], "inv_depth5": pyramid[5],
             "flow1": geo.flow_from_depth_motion(pyramid[1], batch["motion"], k, k),
             "flow2": geo.flow_from_depth_motion(pyramid[2], batch["motion"], k, k),
             "flow5": geo.flow_from_depth_motion(pyramid[5], batch["motion"], k, k),
             "normals0": geo.normals_from_depth(pyramid[0], k), "normals2": geo.normals_from_depth(pyramid[2], k),
             "motion": batch["motion"]}
    gt = losses.ground_truth(batch)
    weights = losses.check_weights(_preset("supplementary"))
    losses.flow_loss(torch.rand(2, 4, 2, 3), torch.rand(2, 4, 16, 24), gt, weights)
    assert set(gt._values) == {"flow2", "flow5", "motion"}  # what the flow loss read (no normals, no depth)
    assert sorted(gt) == sorted(eager)
    for key, value in eager.items():
        assert torch.equal(torch.nan_to_num(gt[key], nan=-1.0), torch.nan_to_num(value, nan=-1.0)), key


@pytest.mark.parametrize("name", sorted(p.stem for p in (resources.CONF / "loss").glob("*.yaml")))
def test_a_preset_loads_as_hydra_composes_it(name):
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(str(resources.CONF), version_base="1.3"):
        composed = OmegaConf.to_container(compose("config", overrides=[f"loss={name}"]).loss, resolve=True)
    assert losses.preset(name) == losses.check_weights(composed)
