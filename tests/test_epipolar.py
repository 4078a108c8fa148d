"""The motion layer with geometry in it (model.motion_fit): the weighted fit of the camera motion to a
flow, its gradient, the geometric residual, and the chain and keys that use it."""

from __future__ import annotations

import pytest
import torch

from demon_lab.core import geometry as geo
from demon_lab.core import losses
from demon_lab.core.epipolar import fit_motion, sampson_px
from demon_lab.core.metrics import motion_errors
from demon_lab.nets.chain import DeMoN, ground_truth_inputs


def _pairs(presets=("synthetic_sun3d", "synthetic_scenes11"), seeds=(0, 1, 2), size=(96, 128)):
    """Rendered pairs as a batch: image1, image2, intrinsics, inv_depth (B, 1, H, W), motion, and the
    true flow at level 2."""
    from demon_lab.data import synthetic

    samples = [synthetic.render_pair(p, s, size, supersample=1) for p in presets for s in seeds]
    batch = {k: torch.stack([torch.as_tensor(s[k]).float() for s in samples])
             for k in ("image1", "image2", "intrinsics", "inv_depth", "motion")}
    if batch["inv_depth"].dim() == 3:
        batch["inv_depth"] = batch["inv_depth"][:, None]
    batch["flow2"] = ground_truth_inputs(batch, batch["intrinsics"]).flow
    return batch


def _degrees(motion: torch.Tensor, truth: torch.Tensor) -> list[dict[str, float]]:
    return [motion_errors(m.detach().double().numpy(), t.double().numpy()) for m, t in zip(motion, truth, strict=True)]


def test_on_the_true_flow_with_uniform_weights_the_fit_returns_the_true_motion():
    """Every rendered pair of both presets: rotation and translation within 0.1 degrees (they are
    within 1e-3 degrees), for 1 and 3 steps, and its Sampson residual is zero."""
    batch = _pairs()
    for steps in (1, 3):
        motion = fit_motion(batch["flow2"], torch.ones_like(batch["flow2"][:, :1]), batch["intrinsics"], steps)
        for e in _degrees(motion, batch["motion"]):
            assert e["rot_deg"] < 0.1 and e["tran_deg"] < 0.1, (steps, e)
    distance, valid = sampson_px(batch["flow2"], batch["motion"], batch["intrinsics"])
    assert valid.float().mean() > 0.5 and distance[valid].max() < 1e-3


def test_more_starts_keep_the_fit_of_lowest_cost_and_read_the_true_motion_of_the_true_flow():
    """fit_motion(starts=16): on the true flow, the true motion within 0.1 degrees (the translation's
    sign by cheirality); on the true flow moved by noise of 1.5 level-2 px on every vector, a fit whose
    robust cost is never above the 8-point start's own fit's, and below it for some pairs (the other
    starts find deeper minima); the gradient reaches the weights through the kept fit."""
    from demon_lab.core.epipolar import ROBUST_PX, bearings, robust_cost

    batch = _pairs()
    flow, K = batch["flow2"], batch["intrinsics"]
    uniform = torch.ones_like(flow[:, :1])
    for e in _degrees(fit_motion(flow, uniform, K, 3, starts=16), batch["motion"]):
        assert e["rot_deg"] < 0.1 and e["tran_deg"] < 0.1, e
    torch.manual_seed(0)
    noisy = flow + 1.5 * torch.randn_like(flow) / flow.new_tensor([flow.shape[3], flow.shape[2]]).view(1, 2, 1, 1)
    x1, x2, _ = bearings(noisy.double(), K.double())
    scale = ROBUST_PX / (K.double()[:, 0] * flow.shape[3])

    def cost(motion):
        R = geo.angle_axis_to_matrix(motion[:, :3].double())
        return robust_cost(R, motion[:, 3:].double(), x1, x2, torch.ones_like(x1[..., 0]), scale)

    weights = uniform.clone().requires_grad_(True)
    one, many = fit_motion(noisy, uniform, K, 10), fit_motion(noisy, weights, K, 10, starts=16)
    assert (cost(many) <= cost(one) + 1e-6).all() and (cost(many) < 0.99 * cost(one)).any()
    many.square().sum().backward()
    assert torch.isfinite(weights.grad).all() and weights.grad.abs().sum() > 0


def test_the_weights_decide_which_vectors_the_motion_is_read_from():
    """A third of the vectors moved 3-8 px off: with uniform weights the fit is pulled off the true
    motion; with those vectors' weights at zero it reads the true motion again."""
    batch = _pairs(seeds=(0, 1))
    flow, K = batch["flow2"], batch["intrinsics"]
    generator = torch.Generator().manual_seed(0)
    off = torch.rand(flow[:, :1].shape, generator=generator) < 1 / 3
    h, w = flow.shape[2:]
    shift = 3 + 5 * torch.rand(flow.shape, generator=generator)
    shift = shift * torch.sign(torch.randn(flow.shape, generator=generator))
    corrupted = torch.where(off, flow + shift / torch.tensor([w, h]).view(1, 2, 1, 1), flow)
    uniform = _degrees(fit_motion(corrupted, torch.ones_like(off, dtype=torch.float32), K, 1), batch["motion"])
    picked = _degrees(fit_motion(corrupted, (~off).float(), K, 1), batch["motion"])
    assert max(e["tran_deg"] for e in uniform) > 2.0, uniform
    assert all(e["rot_deg"] < 0.1 and e["tran_deg"] < 0.1 for e in picked), picked


def test_the_fits_gradient_in_the_weights_and_the_flow_is_the_derivative_of_its_steps():
    """torch.autograd.gradcheck on a small noisy flow in float64: the gradient of the Gauss-Newton steps
    (with their reweighting) matches finite differences of the whole fit, whose start carries no
    gradient but, after enough steps, no longer moves the result."""
    batch = _pairs(presets=("synthetic_sun3d",), seeds=(1,), size=(64, 96))
    flow = ground_truth_inputs(batch, batch["intrinsics"]).flow[:, :, :8, :12].double()
    flow = flow + 0.01 * torch.randn(flow.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    weights = torch.rand(flow[:, :1].shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64) + 0.5
    K = batch["intrinsics"].double()
    assert torch.autograd.gradcheck(lambda w, f: fit_motion(f, w, K, 20),
                                    (weights.requires_grad_(), flow.requires_grad_()), eps=1e-6, atol=1e-4, rtol=1e-3,
                                    fast_mode=True)


def test_the_motions_geometric_residual_is_zero_for_the_true_motion_and_gives_a_gradient_otherwise():
    batch = _pairs(seeds=(0,))
    K, flow = batch["intrinsics"], batch["flow2"]
    assert losses.motion_residual(batch["motion"], flow, K) < 1e-4
    wrong = (batch["motion"] + torch.tensor([0.02, -0.01, 0.0, 0.3, 0.0, 0.0])).requires_grad_()
    residual = losses.motion_residual(wrong, flow, K)
    residual.backward()
    assert residual > 0.1 and torch.isfinite(wrong.grad).all() and wrong.grad.abs().sum() > 0
    weights = {k: 1.0 for k in losses.WEIGHT_KEYS}
    gt = losses.ground_truth(batch)
    _, plain = losses.depth_motion_loss(gt["inv_depth2"], gt["normals2"], wrong, gt, weights)
    _, fitted = losses.depth_motion_loss(gt["inv_depth2"], gt["normals2"], wrong, gt, {**weights, "fit_residual": 2.0},
                                         intrinsics=K)
    assert "fit_residual" not in plain and float(fitted["fit_residual"]) == pytest.approx(2 * float(residual), rel=1e-5)


def test_the_weight_loss_classifies_each_vector_by_its_distance_to_the_truth_in_input_pixels():
    """loss.fit_weight: a vector is precise within 1 px of the input (a level-2 grid of 2 x 4 is an
    input of 8 x 16); the loss is the weights' cross-entropy with that label over the known truth, its
    gradient raises the precise vectors' weights and lowers the others'; depth_motion_loss adds it
    times its weight where it is given the weights."""
    truth = torch.zeros(1, 2, 2, 4)
    truth[0, :, 1, 3] = float("nan")  # unknown: left out
    flow = torch.zeros(1, 2, 2, 4)
    flow[0, 0, 0, 0] = 0.9 / 16  # 0.9 px in x: precise
    flow[0, 1, 0, 1] = 0.9 / 8  # 0.9 px in y: precise
    flow[0, 0, 0, 2] = 1.1 / 16  # 1.1 px: not
    flow[0, 1, 1, 0] = 2.0 / 8  # 2 px: not
    flow[0, :, 1, 1] = torch.tensor([0.6 / 16, 0.6 / 8])  # 0.6 px in x and y, 0.85 px: precise
    flow[0, :, 1, 2] = torch.tensor([0.8 / 16, 0.8 / 8])  # 0.8 px in x and y, 1.13 px: not
    precise = torch.tensor([[1, 1, 0, 1], [0, 1, 0, 0]], dtype=torch.bool)  # (0, 3): exact
    weights = torch.full((1, 1, 2, 4), 0.7, requires_grad=True)
    loss = losses.fit_weight_loss(weights, flow, truth)
    known = torch.ones(2, 4, dtype=torch.bool)
    known[1, 3] = False
    expected = torch.where(precise, -torch.log(torch.tensor(0.7)), -torch.log(torch.tensor(0.3)))[known].mean()
    assert float(loss) == pytest.approx(float(expected), rel=1e-5)
    loss.backward()
    grad = weights.grad[0, 0]
    assert (grad[precise & known] < 0).all() and (grad[~precise & known] > 0).all() and grad[1, 3] == 0
    gt = {"inv_depth2": torch.rand(1, 1, 2, 4), "normals2": torch.rand(1, 3, 2, 4), "motion": torch.rand(1, 6),
          "flow2": truth}
    weights_preset = {**{k: 1.0 for k in losses.WEIGHT_KEYS}, "fit_weight": 3.0}
    _, terms = losses.depth_motion_loss(gt["inv_depth2"], gt["normals2"], gt["motion"], gt, weights_preset,
                                        fit_weights=weights.detach(), fit_flow=flow)
    assert float(terms["fit_weight"]) == pytest.approx(3 * float(expected), rel=1e-5)
    _, plain = losses.depth_motion_loss(gt["inv_depth2"], gt["normals2"], gt["motion"], gt, weights_preset)
    assert "fit_weight" not in plain  # no weights given (the iterative stage's passes return none)


def test_an_untrained_chain_with_the_fit_reads_the_true_motion_from_the_true_flow():
    """The chain's bootstrap pass under oracle=flow, its nets untrained (every weight 0.5): the
    motion is the true motion (within 0.1 degrees), and each iterative pass fits again; the loss's
    gradient reaches the depth-motion net's weight channel."""
    batch = _pairs(seeds=(0,), size=(64, 96))
    chain = DeMoN("v1", 0.125, (64, 96), motion_fit=3)
    out = chain(batch["image1"], batch["image2"], batch["intrinsics"], iterations=1, oracle="flow",
                gt=batch, refine=False)
    for p in out.passes:
        for e in _degrees(p.motion, batch["motion"]):
            assert e["rot_deg"] < 0.1 and e["tran_deg"] < 0.1, e
    flow = batch["flow2"] + 0.002 * torch.randn(batch["flow2"].shape, generator=torch.Generator().manual_seed(0))
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    dm = chain.depth_motion1(pair, batch["image2"][:, :, ::4, ::4], flow, torch.ones_like(flow), batch["intrinsics"])
    (dm.motion - batch["motion"]).square().sum().backward()
    grad = chain.dm1.predict_depth2.out.conv.weight.grad
    assert grad is not None and grad[4].abs().sum() > 0 and torch.isfinite(grad).all()


@pytest.mark.parametrize("options, message", [
    (dict(motion_fit=0), "motion_fit: expected null or a number of Gauss-Newton steps >= 1"),
    (dict(motion_fit=3, dm1_prior="ransac"), "dm1_prior: the motion fit"),
    (dict(motion_fit=3, dm2_prior="previous"), "dm2_prior: the motion fit"),
    (dict(motion_fit=2, compat="demon_original"), "motion_fit: compat=demon_original"),
    (dict(fit_starts=4), "fit_starts: 4 starts of the motion fit; set motion_fit"),
    (dict(motion_fit=2, fit_starts=-1), "fit_starts: expected a number of further starts >= 0"),
])
def test_the_fits_option_is_checked(options, message):
    with pytest.raises(ValueError, match=message):
        DeMoN("v1", 0.125, (64, 96), **options)


def test_the_fit_design_shares_the_learned_designs_flow1_and_leaves_every_other_key_as_it_was():
    """design=fit changes dm1 on (model.motion_fit is a dm1 option; loss.fit_residual enters the
    depth-motion stages' keys only where it is set), so its flow1 is the learned design's, and the
    learned design's keys do not hold the new options."""
    from jobs import compose_config, settings

    from demon_lab.pipeline.stages.schedule import stage_dirs

    fit = {d.name: d.key for d in stage_dirs(settings(compose_config(["design=fit"])))}
    learned = {d.name: d.key for d in stage_dirs(settings(compose_config(["design=learned"])))}
    assert fit["flow1"] == learned["flow1"] and fit["dm1"] != learned["dm1"]
    plain = settings(compose_config(["design=learned"]))
    assert plain.model.motion_fit is None and plain.loss.get("fit_residual", 0.0) == 0.0
    from demon_lab.pipeline.identity import describe_stage

    described = describe_stage(plain, "dm1", {})
    assert "fit_residual" not in described["loss"] and "motion_fit" not in described["model"]


def test_uniform_fit_weights_fit_every_vector_alike_and_need_the_fit():
    """model.fit_weights=uniform: the motion fit ignores the net's weights (here far from uniform), so
    the uniform row measures what the learned weights add."""
    batch = _pairs(seeds=(0,), size=(64, 96))
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    flow = batch["flow2"].clone()
    flow[..., : flow.shape[-1] // 2] += 0.05  # half the vectors far off
    motions = {}
    for weights in ("learned", "uniform"):
        chain = DeMoN("v1", 0.125, (64, 96), motion_fit=3, fit_weights=weights)
        with torch.no_grad():  # the net's weights vary from pixel to pixel
            chain.dm1.predict_depth2.out.conv.weight[4].normal_(0, 1)
            dm = chain.depth_motion1(pair, batch["image2"][:, :, ::4, ::4], flow, torch.ones_like(flow),
                                     batch["intrinsics"])
        motions[weights] = dm.motion
    uniform = fit_motion(flow, torch.ones_like(flow[:, :1]), batch["intrinsics"], 3)
    torch.testing.assert_close(motions["uniform"], uniform)
    assert not torch.allclose(motions["learned"], motions["uniform"])
    with pytest.raises(ValueError, match="fit_weights: uniform weighs the motion fit's vectors; set motion_fit"):
        DeMoN("v1", 0.125, (64, 96), fit_weights="uniform")
