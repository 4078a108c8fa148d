"""Networks: parameter counts from DeMoN's layer tables (docs/reference.md §1), shapes, gradients; losses: values."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from demon_lab import resources
from demon_lab.core import losses
from demon_lab.nets import DeMoN, DepthMotionNet, FlowNet, RefineNet


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def test_v1_parameter_counts_match_the_layer_tables():
    chain = DeMoN("v1", width=1.0, size=(192, 256))
    bootstrap = count(chain.flow1) + count(chain.dm1)
    iterative = count(chain.flow2) + count(chain.dm2)
    # Sums of the layer tables of docs/reference.md §1.1-§1.3 (DeMoN's v1 blocks), layer by layer:
    assert count(chain.flow1) == 8_279_866
    assert count(chain.dm1) == 14_367_331
    assert bootstrap == 22_647_197 and round(bootstrap / 1e6, 2) == 22.65
    assert iterative == 22_622_557 and round(iterative / 1e6, 2) == 22.62
    assert count(chain.refine_net) == 484_129 and round(count(chain.refine_net) / 1e6, 2) == 0.48
    assert round(count(chain) / 1e6, 2) == 45.75


@pytest.mark.parametrize("variant", ["v1", "v2"])
@pytest.mark.parametrize("size", [(64, 96), (96, 128)])
def test_output_shapes_at_every_level(variant, size):
    H, W = size
    torch.manual_seed(0)
    pair = torch.rand(2, 6, H, W) - 0.5
    flow1 = FlowNet(False, variant, 0.25, size)
    flow5, flow2 = flow1(pair)
    assert flow5.shape == (2, 4, H // 32, W // 32) and flow2.shape == (2, 4, H // 4, W // 4)
    flow_it = FlowNet(True, variant, 0.25, size)
    assert flow_it(pair, torch.rand(2, 9, H // 4, W // 4))[1].shape == (2, 4, H // 4, W // 4)
    with pytest.raises(ValueError, match="extra"):
        flow_it(pair)
    dm = DepthMotionNet(True, variant, 0.25, size)(pair, torch.rand(2, 8, H // 4, W // 4))
    assert dm.inv_depth.shape == (2, 1, H // 4, W // 4) and dm.normals.shape == (2, 3, H // 4, W // 4)
    assert dm.motion.shape == (2, 6) and dm.scale.shape == (2, 1)
    refined = RefineNet(variant, 0.25)(pair[:, :3], dm.inv_depth)
    assert refined.shape == (2, 1 if variant == "v1" else 4, H, W)


def test_depth_is_the_predicted_scale_times_the_raw_depth():
    torch.manual_seed(1)
    net = DepthMotionNet(False, "v1", 0.25, (64, 64))
    pair, extra = torch.rand(1, 6, 64, 64), torch.rand(1, 7, 16, 16)
    out = net(pair, extra)
    with torch.no_grad():
        net.motion_fc3.bias[6] += 1.0  # change only the scale output
    out2 = net(pair, extra)
    raw = out.inv_depth / out.scale[:, :, None, None]
    torch.testing.assert_close(out2.inv_depth, raw * out2.scale[:, :, None, None])
    torch.testing.assert_close(out2.motion, out.motion)


def test_chain_forward_backward_and_iterations():
    torch.manual_seed(2)
    chain = DeMoN("v1", width=0.25, size=(64, 96))
    image1, image2 = torch.rand(2, 3, 64, 96) - 0.5, torch.rand(2, 3, 64, 96) - 0.5
    K = torch.tensor([[0.89, 1.19, 0.5, 0.5]] * 2)
    out = chain(image1, image2, K, iterations=3)
    assert len(out.passes) == 4 and out.refined.shape == (2, 1, 64, 96)
    loss = sum(p.inv_depth.abs().mean() + p.flow.abs().mean() + p.motion.abs().mean() for p in out.passes)
    (loss + out.refined.mean()).backward()
    for name in ("flow1", "dm1", "flow2", "dm2", "refine_net"):
        grads = [p.grad for p in getattr(chain, name).parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads), name
    assert len(chain(image1, image2, K, iterations=0).passes) == 1
    with torch.no_grad():  # without the refinement net: the same passes, nothing refined
        plain, unrefined = chain(image1, image2, K, iterations=2), chain(image1, image2, K, iterations=2, refine=False)
    assert unrefined.refined is None
    for a, b in zip(plain.passes, unrefined.passes, strict=True):
        assert torch.equal(a.flow, b.flow) and torch.equal(a.inv_depth, b.inv_depth) and torch.equal(a.motion, b.motion)


def test_oracles_replace_the_inputs():
    torch.manual_seed(3)
    chain = DeMoN("v1", width=0.25, size=(64, 64)).eval()
    image1, image2 = torch.rand(1, 3, 64, 64) - 0.5, torch.rand(1, 3, 64, 64) - 0.5
    K = torch.tensor([[0.89, 1.19, 0.5, 0.5]])
    gt = {"inv_depth": torch.full((1, 1, 64, 64), 0.3), "motion": torch.tensor([[0.0, 0.05, 0, 0.5, 0, 0]])}
    gt2 = {"inv_depth": torch.full((1, 1, 64, 64), 0.6), "motion": gt["motion"]}
    with torch.no_grad():
        plain = chain(image1, image2, K, iterations=1)
        flow_a = chain(image1, image2, K, iterations=1, oracle="flow", gt=gt)
        flow_b = chain(image1, image2, K, iterations=1, oracle="flow", gt=gt2)
        dm_a = chain(image1, image2, K, iterations=1, oracle="depth_motion", gt=gt)
    # the GT flow changes the depth-motion nets' output but not the flow nets'
    torch.testing.assert_close(flow_a.passes[0].flow, plain.passes[0].flow)
    assert not torch.allclose(flow_a.passes[0].inv_depth, flow_b.passes[0].inv_depth)
    # the depth+motion oracle changes only what the iterative flow net sees
    torch.testing.assert_close(dm_a.passes[0].inv_depth, plain.passes[0].inv_depth)
    assert not torch.allclose(dm_a.passes[1].flow, plain.passes[1].flow)
    with pytest.raises(ValueError, match="needs gt"):
        chain(image1, image2, K, oracle="flow")


@pytest.mark.parametrize("kwargs, message", [
    (dict(size=(100, 128)), "multiples of 32"),
    (dict(variant="v3"), "variant"),
    (dict(width=0.0), "width"),
])
def test_bad_chain_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DeMoN(**{"size": (64, 64), **kwargs})


# ----------------------------------------------------------------------------- losses


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


# ----------------------------------------------------------------------------- stage optimisation


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
    from demon_lab.pipeline.stages.modules import FlowStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    stage = FlowStage(chain, weights=_preset("released_code"), steps=300, lr=1e-3, net="flow1", sig_start=sig_start)
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
    from demon_lab.pipeline.stages.modules import FlowStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    kwargs = {} if fade is None else {"level5_fade": fade}
    stage = FlowStage(chain, weights=_preset("released_code"), steps=300, lr=1e-3, net="flow1", sig_start=1.0,
                      **kwargs)
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
    from demon_lab.pipeline.stages.modules import DepthMotionStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    stage = DepthMotionStage(chain, weights=_preset("released_code"), steps=300, lr=1e-3, net="dm1",
                             gt_flow_warmup=warmup)
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
    from demon_lab.pipeline.stages.modules import IterativeStage

    torch.manual_seed(0)
    chain = DeMoN("v1", width=0.0625, size=(64, 64))
    stage = IterativeStage(chain, weights=_preset("released_code"), steps=300, lr=1e-3, queue_size=0,
                           sig_start=sig_start)
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
    eager = {"inv_depth0": pyramid[0], "inv_depth2": pyramid[2], "inv_depth5": pyramid[5],
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


def test_correlation_peaks_at_the_displacement_between_the_feature_maps():
    from demon_lab.nets.blocks import correlation

    torch.manual_seed(4)
    features1 = torch.randn(2, 64, 12, 16)
    dy, dx = 2, -4  # features2[x + d] = features1[x]
    features2 = torch.roll(features1, shifts=(dy, dx), dims=(2, 3))
    volume = correlation(features1, features2, max_displacement=4, stride=2)
    assert volume.shape == (2, 25, 12, 16)  # displacements -4, -2, 0, 2, 4 in each direction
    k = (dy // 2 + 2) * 5 + (dx // 2 + 2)  # row-major over dy, then dx
    inner = (slice(None), slice(4, -4), slice(4, -4))  # away from the border and the roll's wrap
    assert (volume.argmax(1)[inner] == k).all()
    torch.testing.assert_close(volume[:, k][inner], (features1 * features1).mean(1)[inner])
    # beyond the map the second features are zero
    assert (volume[:, 0, :4, :] == 0).all() and (volume[:, 24, -4:, :] == 0).all()
    # stride 1: every displacement up to the range
    assert correlation(features1, features2, 2, 1).shape[1] == 25


@pytest.mark.parametrize("displacement", [(8, 2), (2, 1), (3, 2)], ids=["8-2", "2-1", "3-2"])
def test_the_correlation_operation_equals_the_shifted_products_in_value_and_gradient(displacement):
    """The one-operation correlation (blocks.Correlation) is the shifted products' correlation: its forward
    pass bit for bit, its gradients within 1e-6 (float32, channels-last too), and its backward pass
    passes gradcheck in float64."""
    from demon_lab.nets.blocks import correlation
    from demon_lab.tools.bench_train import correlation_by_shifts

    torch.manual_seed(5)
    f1, f2 = torch.randn(2, 6, 12, 16), torch.randn(2, 6, 12, 16)
    grad = torch.randn(2, (2 * (displacement[0] // displacement[1]) + 1) ** 2, 12, 16)
    for layout in (torch.contiguous_format, torch.channels_last):
        a, b = (x.contiguous(memory_format=layout).requires_grad_() for x in (f1, f2))
        ours = correlation(a, b, *displacement)
        ours_grads = torch.autograd.grad(ours, (a, b), grad)
        reference = correlation_by_shifts(a, b, *displacement)
        reference_grads = torch.autograd.grad(reference, (a, b), grad)
        assert torch.equal(ours, reference)
        for g, r in zip(ours_grads, reference_grads, strict=True):
            torch.testing.assert_close(g, r, rtol=0, atol=1e-6)
            assert g.abs().max() > 0.1  # (gradients of a real size, not all zero)
    a, b = (torch.randn(1, 3, 6, 7, dtype=torch.float64, requires_grad=True) for _ in range(2))
    assert torch.autograd.gradcheck(lambda x, y: correlation(x, y, *displacement), (a, b))


def test_a_correlation_front_changes_only_the_flow_nets_front():
    plain, corr = DeMoN("v1", 0.25, (64, 96)), DeMoN("v1", 0.25, (64, 96), correlation=(8, 2))
    for name in ("dm1", "dm2", "refine_net"):
        assert count(getattr(plain, name)) == count(getattr(corr, name))
    for net in (corr.flow1, corr.flow2):
        assert net.conv1.y.conv.in_channels == 3  # one image at a time, shared weights
        assert net.conv2_1.y.conv.in_channels == 8 + 81 + (8 if net.iterative else 0)  # c(32) + 9x9 (+ extra)
    torch.manual_seed(5)
    image1, image2 = torch.rand(2, 3, 64, 96) - 0.5, torch.rand(2, 3, 64, 96) - 0.5
    K = torch.tensor([[0.89, 1.19, 0.5, 0.5]] * 2)
    out = corr(image1, image2, K, iterations=1)
    assert out.passes[1].flow.shape == (2, 2, 16, 24)
    out.passes[1].flow.abs().mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in corr.flow2.parameters())
    # the front reads each image: swapping them changes the flow
    with torch.no_grad():
        swapped = corr.flow1(torch.cat([image2, image1], 1))[1]
        assert not torch.allclose(swapped, corr.flow1(torch.cat([image1, image2], 1))[1])
    with pytest.raises(ValueError, match="no correlation front"):
        DeMoN("v1", 0.25, (64, 64), compat="demon_original", correlation=(4, 1))
    with pytest.raises(ValueError, match=r"correlation: expected \[max_displacement, stride\]"):
        DeMoN("v1", 0.25, (64, 64), correlation=(2, 4))


def _textured_pair(shift_px: tuple[int, int], size=(96, 128), seed=3) -> torch.Tensor:
    """A smooth random texture and the same texture moved by ``shift_px`` (x, y) pixels, as one
    (1, 6, H, W) pair in [-0.5, 0.5]: the true flow is ``shift_px`` everywhere inside the image."""
    g = torch.Generator().manual_seed(seed)
    h, w = size
    big = torch.rand(1, 3, h // 4 + 8, w // 4 + 8, generator=g)
    texture = torch.nn.functional.interpolate(big, scale_factor=4, mode="bicubic", align_corners=False) - 0.5
    dx, dy = shift_px
    image1 = texture[:, :, 16:16 + h, 16:16 + w]
    image2 = texture[:, :, 16 - dy:16 - dy + h, 16 - dx:16 - dx + w]  # image2(x + d) = image1(x)
    return torch.cat([image1, image2], 1).clamp(-0.5, 0.5)


def test_the_dis_prior_is_the_pairs_flow_normalised_at_level_2():
    from demon_lab.nets.prior import dis_prior

    pair = _textured_pair((6, -4))
    prior = dis_prior(pair)
    assert prior.shape == (1, 2, 24, 32) and prior.dtype == torch.float32
    inner = prior[0, :, 4:-4, 4:-4]  # away from the borders, where part of the texture leaves the image
    assert torch.allclose(inner[0].median(), torch.tensor(6 / 128), atol=0.25 / 128)
    assert torch.allclose(inner[1].median(), torch.tensor(-4 / 96), atol=0.25 / 96)
    assert dis_prior(pair, level=0).shape == (1, 2, 96, 128)
    # dis_x2: computed on the pair upsampled 2x, in the same units at the same level
    finer = dis_prior(pair, upsample=2)
    assert finer.shape == (1, 2, 24, 32) and dis_prior(pair, level=0, upsample=2).shape == (1, 2, 96, 128)
    assert torch.allclose(finer[0, 0, 4:-4, 4:-4].median(), torch.tensor(6 / 128), atol=0.25 / 128)
    assert torch.allclose(finer[0, 1, 4:-4, 4:-4].median(), torch.tensor(-4 / 96), atol=0.25 / 96)


def test_the_bootstrap_flow_net_with_a_prior_predicts_a_correction_of_it():
    from demon_lab.nets.prior import dis_prior

    torch.manual_seed(0)
    chain = DeMoN("v1", 0.25, (96, 128), flow1_prior="dis")
    plain = DeMoN("v1", 0.25, (96, 128))
    net = chain.flow1
    assert net.conv2_1.y.conv.in_channels == plain.flow1.conv2_1.y.conv.in_channels + 8  # + c(32) from 5 inputs
    assert net.conv2_prior.y.conv.in_channels == 5 and chain.flow2.prior is None
    pair = _textured_pair((6, -4))
    prior = dis_prior(pair)
    with torch.no_grad():
        flow2 = net(pair)[1]
        for head in (net.predict_flow2, net.predict_flow5):  # a net that predicts no correction
            last = [m for m in head.modules() if isinstance(m, torch.nn.Conv2d)][-1]
            last.weight.zero_()
            last.bias.zero_()
        zero5, zero2 = net(pair)
    assert not torch.allclose(flow2[:, :2], prior)
    assert torch.allclose(zero2[:, :2], prior) and torch.allclose(zero2[:, 2:], torch.zeros_like(zero2[:, 2:]))
    assert torch.allclose(zero5[:, :2], torch.nn.functional.avg_pool2d(prior, 8), atol=1e-7)
    # the net reads the prior: a pair whose DIS flow differs gives another output with the same weights
    with torch.no_grad():
        other = net(_textured_pair((-3, 2)))[1]
    assert not torch.allclose(other[:, :2], zero2[:, :2])
    with pytest.raises(ValueError, match="whose nets have no priors"):
        DeMoN("v1", 0.25, (64, 64), compat="demon_original", flow1_prior="dis")
    with pytest.raises(ValueError, match="flow1_prior: expected one of"):
        DeMoN("v1", 0.25, (64, 64), flow1_prior="flownet")
    with pytest.raises(ValueError, match="the iterative flow net has its prior"):
        FlowNet(iterative=True, width=0.25, size=(64, 64), prior="dis")


def test_the_ransac_motion_prior_recovers_the_motion_from_its_flow():
    from demon_lab.core import geometry as geo
    from demon_lab.core import loss_maps, metrics
    from demon_lab.data import synthetic
    from demon_lab.nets.prior import ransac_motion

    flows, cams, motions = [], [], []
    for seed in (1, 2):
        s = synthetic.render_pair("synthetic_scenes11", seed, (96, 128))
        inv = torch.as_tensor(s["inv_depth"]).float().reshape(1, 1, 96, 128)
        inv2 = loss_maps.inverse_depth_pyramid(inv, levels=2)[2]
        motion, K = torch.as_tensor(s["motion"]).float()[None], torch.as_tensor(s["intrinsics"]).float()[None]
        flows.append(geo.flow_from_depth_motion(inv2, motion, K))
        cams.append(K)
        motions.append(motion[0])
    flow, K = torch.cat(flows), torch.cat(cams)
    prior = ransac_motion(flow, K)
    assert prior.shape == (2, 6) and prior.dtype == torch.float32
    assert torch.equal(prior, ransac_motion(flow, K))  # a fixed subset and OpenCV's fixed generator
    for i in range(2):
        errors = metrics.motion_errors(prior[i], motions[i])
        assert errors["rot_deg"] < 0.5 and errors["tran_deg"] < 3.0, errors
        assert torch.isclose(prior[i, 3:].norm(), torch.tensor(1.0))
    # a flow without vectors has no solution: no motion
    assert torch.equal(ransac_motion(torch.full_like(flow, float("nan")), K), torch.zeros(2, 6))


def test_the_bootstrap_depth_motion_net_with_a_motion_prior_starts_at_that_motion():
    from demon_lab.nets.prior import ransac_motion

    torch.manual_seed(0)
    chain, plain = DeMoN("v1", 0.25, (96, 128), dm1_prior="ransac"), DeMoN("v1", 0.25, (96, 128))
    assert chain.dm1.conv2_extra.y.conv.in_channels == 8 and plain.dm1.conv2_extra.y.conv.in_channels == 7
    pair = _textured_pair((6, -4))
    K = torch.tensor([[0.89, 1.19, 0.5, 0.5]])
    with torch.no_grad():
        p = chain.bootstrap(pair, torch.nn.functional.avg_pool2d(pair[:, 3:], 4), K)
        assert torch.allclose(p.motion, ransac_motion(p.flow, K))  # the correction starts at none
        chain.dm1.motion_fc3.bias[3:6] += 0.1  # a correction is added to the prior
        q = chain.bootstrap(pair, torch.nn.functional.avg_pool2d(pair[:, 3:], 4), K)
    assert torch.allclose(q.motion[:, 3:] - p.motion[:, 3:], torch.full((1, 3), 0.1), atol=1e-6)
    with pytest.raises(ValueError, match="dm1_prior: expected one of"):
        DeMoN("v1", 0.25, (64, 64), dm1_prior="lmeds")
    with pytest.raises(ValueError, match=r"ransac_prior reads flow1.s classical prior flow; set flow1_prior"):
        DeMoN("v1", 0.25, (64, 64), dm1_prior="ransac_prior")


def test_ransac_prior_reads_the_motion_from_flow1s_prior_flow_not_its_output():
    """dm1_prior=ransac_prior: the motion dm1 starts from is RANSAC (every level-2 vector, a 1-pixel
    threshold) on flow1's classical prior flow, whatever flow1 makes of it; under the flow oracle, on
    the ground-truth flow."""
    from demon_lab.nets.chain import ground_truth_inputs
    from demon_lab.nets.prior import PRIOR_RANSAC, dis_prior, ransac_motion

    torch.manual_seed(0)
    chain = DeMoN("v1", 0.25, (96, 128), flow1_prior="dis_x2", dm1_prior="ransac_prior")
    pair = _textured_pair((6, -4))
    K = torch.tensor([[0.89, 1.19, 0.5, 0.5]])
    image2_2 = torch.nn.functional.avg_pool2d(pair[:, 3:], 4)
    with torch.no_grad():
        for head in (chain.flow1.predict_flow5, chain.flow1.predict_flow2):  # flow1 moves its prior
            head.out.conv.bias[:2] += 0.05
        prior_flow = dis_prior(pair, upsample=2)
        assert torch.equal(chain.flow_net1(pair)[2], prior_flow)
        p = chain.bootstrap(pair, image2_2, K)
        assert not torch.allclose(p.flow, prior_flow, atol=0.02)
        assert torch.allclose(p.motion, ransac_motion(prior_flow, K, *PRIOR_RANSAC))
        inv = torch.full((1, 1, 96, 128), 0.5)
        motion = torch.tensor([[0.0, 0.02, 0.0, 1.0, 0.0, 0.0]])
        gt = {"inv_depth": inv, "motion": motion}
        q = chain(pair[:, :3], pair[:, 3:], K, iterations=0, oracle="flow", gt=gt, refine=False).passes[0]
        assert torch.allclose(q.motion, ransac_motion(ground_truth_inputs(gt, K).flow, K, *PRIOR_RANSAC))
    with pytest.raises(ValueError, match="whose nets have no priors"):
        DeMoN("v1", 0.25, (64, 64), compat="demon_original", dm1_prior="ransac")


def _iterative_prior_case(**prior: str):
    """A chain with an iterative prior, a textured pair at 128x96 (its image 2 at level 2, the
    intrinsics) and the chain's bootstrap pass on it."""
    torch.manual_seed(0)
    chain = DeMoN("v1", 0.25, (96, 128), **prior)
    pair = _textured_pair((6, -4))
    image2_2 = torch.nn.functional.avg_pool2d(pair[:, 3:], 4)
    K = torch.tensor([[0.89, 1.19, 0.5, 0.5]])
    with torch.no_grad():
        return chain, pair, image2_2, K, chain.bootstrap(pair, image2_2, K)


def test_the_iterative_depth_motion_net_with_a_motion_prior_starts_at_the_previous_motion():
    chain, pair, image2_2, K, p0 = _iterative_prior_case(dm2_prior="previous")
    with torch.no_grad():
        p0 = replace(p0, motion=torch.tensor([[0.02, -0.01, 0.03, 0.3, -0.2, 0.9]]))
        p1 = chain.iterate(pair, image2_2, K, p0)
        assert torch.allclose(p1.motion, p0.motion)  # the correction starts at none
        plain = DeMoN("v1", 0.25, (96, 128))
        plain.load_state_dict(chain.state_dict())  # the same nets: only the motion's meaning differs
        assert not torch.allclose(plain.iterate(pair, image2_2, K, p0).motion, p0.motion, atol=1e-4)
        chain.dm2.motion_fc3.bias[3:6] += 0.1  # a correction is added to the previous motion
        p2 = chain.iterate(pair, image2_2, K, p0)
    assert torch.allclose(p2.motion[:, 3:] - p0.motion[:, 3:], torch.full((1, 3), 0.1), atol=1e-6)
    with pytest.raises(ValueError, match="dm2_prior: expected one of"):
        DeMoN("v1", 0.25, (64, 64), dm2_prior="ransac")


def test_the_iterative_flow_net_with_a_flow_prior_starts_at_the_previous_flow():
    chain, pair, image2_2, K, p0 = _iterative_prior_case(flow2_prior="previous")
    with torch.no_grad():
        p0 = replace(p0, flow=torch.randn_like(p0.flow) * 0.05, flow5=torch.randn_like(p0.flow5) * 0.05)
        p1 = chain.iterate(pair, image2_2, K, p0)
        assert torch.allclose(p1.flow, p0.flow) and torch.allclose(p1.flow5, p0.flow5)  # no correction yet
        assert p1.conf.abs().sum() > 0  # the confidence is the net's own, not zeroed
        plain = DeMoN("v1", 0.25, (96, 128))
        plain.load_state_dict(chain.state_dict())  # the same nets: only the flow's meaning differs
        assert not torch.allclose(plain.iterate(pair, image2_2, K, p0).flow, p0.flow, atol=1e-4)
        chain.flow2.predict_flow2.out.conv.bias[:2] += 0.1  # a correction is added to the previous flow
        p2 = chain.iterate(pair, image2_2, K, p0)
    assert torch.allclose(p2.flow - p0.flow, torch.full_like(p0.flow, 0.1), atol=1e-6)
    with pytest.raises(ValueError, match="flow2_prior: expected one of"):
        DeMoN("v1", 0.25, (64, 64), flow2_prior="dis")
    with pytest.raises(ValueError, match="whose nets have no priors"):
        DeMoN("v1", 0.25, (64, 64), compat="demon_original", flow2_prior="previous")
