"""The refinement of the bootstrap flow on warped features (model.flow_refine), its stage and the
schedule's order."""

from __future__ import annotations

import pytest
import torch

from demon_lab.core import losses
from demon_lab.nets.chain import DeMoN, ground_truth_inputs
from demon_lab.nets.flow_refine import FINE_UPDATES, RADIUS, FlowRefine, displacements
from demon_lab.pipeline.config import ConfigError


def _batch(seeds=(0, 1, 2, 3), size=(64, 96)):
    from demon_lab.data import synthetic

    samples = [synthetic.render_pair("synthetic_scenes11", s, size, supersample=1) for s in seeds]
    batch = {k: torch.stack([torch.as_tensor(s[k]).float() for s in samples])
             for k in ("image1", "image2", "intrinsics", "inv_depth", "motion")}
    if batch["inv_depth"].dim() == 3:
        batch["inv_depth"] = batch["inv_depth"][:, None]
    return batch


def test_each_update_moves_the_flow_by_its_matchs_expected_displacement_and_the_chain_reads_the_refined_flow():
    """An untrained update (its correction starting at none) moves each vector by the mean displacement
    of its match probabilities, in the pixels of its level; the fine updates' flow is averaged back to
    level 2; the chain's bootstrap flow is the refinement's last."""
    torch.manual_seed(0)
    batch = _batch(seeds=(0,))
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    flow = 0.01 * torch.randn(1, 2, 16, 24)
    refined = FlowRefine("v1", 0.25, iterations=2)(pair, flow)
    assert len(refined.flows) == len(refined.matches) == 2 + FINE_UPDATES
    assert [m.level for m in refined.matches] == [2, 2] + [1] * FINE_UPDATES
    for k, match in enumerate(refined.matches[:2]):
        probs = match.log_probs.exp()
        torch.testing.assert_close(probs.sum(1), torch.ones(1, 16, 24))
        pixels = torch.tensor([24.0, 16.0]).view(1, 2, 1, 1)
        expected = (probs.unsqueeze(1) * displacements(RADIUS, probs)).sum(2) / pixels
        torch.testing.assert_close(refined.flows[k], match.start + expected)
    assert refined.matches[2].start.shape[2:] == (32, 48)
    torch.testing.assert_close(refined.flows[-1], torch.nn.functional.avg_pool2d(
        refined.matches[-1].start + (refined.matches[-1].log_probs.exp().unsqueeze(1)
                                     * displacements(3, flow)).sum(2) / torch.tensor([48.0, 32.0]).view(1, 2, 1, 1), 2))
    chain = DeMoN("v1", 0.25, (64, 96), flow_refine=2)
    with torch.no_grad():
        raw = chain.flow_net1(pair, refine=False)[1][:, :2]
        out = chain(batch["image1"], batch["image2"], batch["intrinsics"], iterations=0, refine=False)
        torch.testing.assert_close(out.passes[0].flow, chain.refine_flow(pair, raw).flows[-1])
    assert not torch.allclose(out.passes[0].flow, raw)
    assert "flow1_refine" not in dict(DeMoN("v1", 0.25, (64, 96)).named_children())


def test_the_match_target_is_the_true_displacement_split_over_its_four_neighbours():
    """window_target: a displacement on the grid is one displacement of the window, one between grid
    points its bilinear split (the target's mean is the displacement); outside the window or without a
    true flow, no target; match_loss is the cross-entropy with it."""
    h, w, r = 2, 3, 2
    start = torch.zeros(1, 2, h, w)
    pixels = torch.tensor([w, h], dtype=torch.float32).view(1, 2, 1, 1)
    moved = torch.tensor([[[1.0, -0.25, 3.0], [0.0, 1.5, float("nan")]],
                          [[-2.0, 0.75, 0.0], [0.0, -0.5, 0.0]]]).unsqueeze(0)
    target, inside = losses.window_target(start, moved / pixels, r)
    assert inside.tolist() == [[[True, True, False], [True, True, False]]]
    grid = displacements(r, start).view(2, -1)
    mean = torch.einsum("dk,bkhw->bdhw", grid, target)
    torch.testing.assert_close(mean[:, :, inside[0]], moved[:, :, inside[0]])
    assert target[0, :, 0, 0].max() == 1.0 and int((target[0, :, 0, 0] > 0).sum()) == 1
    assert target[0, :, 1, 1].tolist().count(0.25) == 4  # (1.5, -0.5) px: midway between four displacements
    torch.testing.assert_close(target[:, :, inside[0]].sum(1), torch.ones(1, int(inside.sum())))
    log_probs = torch.log_softmax(torch.randn(1, (2 * r + 1) ** 2, h, w), 1)
    expected = -(target * log_probs).sum(1)[inside].mean()
    torch.testing.assert_close(losses.match_loss(log_probs, start, moved / pixels), expected)


def test_the_refinement_learns_to_correct_a_flow_that_is_off_by_a_pixel():
    """Trained on four rendered pairs fed their true level-2 flow moved by 1.5 px, the refinement's
    flow ends far closer to the truth than the flow it is given (its losses reach the features'
    correlation through the warp)."""
    torch.manual_seed(0)
    batch = _batch()
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    truth = ground_truth_inputs(batch, batch["intrinsics"]).flow
    h, w = truth.shape[2:]
    given = torch.nan_to_num(truth) + torch.tensor([1.5 / w, -1.5 / h]).view(1, 2, 1, 1)
    net = FlowRefine("v1", 0.5, iterations=2)
    optimiser = torch.optim.Adam(net.parameters(), lr=2e-3)
    gt = losses.ground_truth(batch)
    before = float(losses.pointwise_l2(given, truth))
    for _ in range(150):
        optimiser.zero_grad()
        loss, _ = losses.refined_flow_loss(net(pair, given), gt, {"flow": 1.0, "flow_match": 0.1})
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        after = float(losses.pointwise_l2(net(pair, given).flows[-1], truth))
    assert after < 0.5 * before, (before, after)


def test_the_options_and_the_order_of_the_stages_are_checked():
    from jobs import compose_config

    from demon_lab.pipeline.settings import JobSettings

    with pytest.raises(ValueError, match="flow_refine: expected null or a number of updates >= 1"):
        DeMoN("v1", 0.25, (64, 96), flow_refine=0)
    with pytest.raises(ConfigError, match=r"schedule\.order: expected each of the stages"):
        JobSettings.of(compose_config(["design=fit", "schedule.order=[flow1,dm1]"]))
    with pytest.raises(ConfigError, match=r"schedule\.stages\.flow1r\.net: expected one of"):
        JobSettings.of(compose_config(["design=fit", "schedule.stages.flow1r.net=flow3"]))


def test_the_refinement_stage_trains_between_flow1_and_dm1_and_keys_them_so():
    """design=fit: flow1r after flow1 and before dm1 (schedule.order); flow1 is the learned design's,
    dm1's key holds flow1r's; the refinement's stage reads only the flow weight."""
    from jobs import compose_config, settings

    from demon_lab.pipeline.stages.schedule import stage_dirs

    job = settings(compose_config(["design=fit"]))
    assert job.schedule.stages[:3] == ("flow1", "flow1r", "dm1")
    dirs = {d.name: d for d in stage_dirs(job)}
    learned = {d.name: d.key for d in stage_dirs(settings(compose_config(["design=learned"])))}
    assert dirs["flow1"].key == learned["flow1"]
    assert dirs["dm1"].description["upstream"] == {"flow1": dirs["flow1"].key, "flow1r": dirs["flow1r"].key}
    assert dirs["flow1r"].description["loss"] == {k: job.loss[k] for k in ("flow", "flow_match", "fit_weight")}
    assert job.stages["flow1r"].trained_nets() == ("flow1_refine",)
    # fit_weights=confidence gives flow1_refine its head: flow1r on holds it, flow1 is shared; a chain with
    # no flow1r stage holds it from dm1 on
    learned_weights = {d.name: d.key for d in stage_dirs(settings(compose_config(["design=fit",
                                                                                  "model.fit_weights=learned"])))}
    assert learned_weights["flow1"] == dirs["flow1"].key and learned_weights["flow1r"] != dirs["flow1r"].key
    no_refine = {d.name: d.key for d in stage_dirs(settings(compose_config(
        ["design=fit", "model.flow_refine=null", "schedule.order=null", "model.fit_weights=confidence"])))}
    no_refine_learned = {d.name: d.key for d in stage_dirs(settings(compose_config(
        ["design=fit", "model.flow_refine=null", "schedule.order=null", "model.fit_weights=learned"])))}
    assert no_refine["flow1"] == no_refine_learned["flow1"] and no_refine["dm1"] != no_refine_learned["dm1"]


def test_confidence_weights_are_the_nets_times_the_refinements_confidence_head():
    """model.fit_weights=confidence: the refinement has a confidence head (0.5 everywhere untrained) that
    dm1 reads as its confidence input; the fit's weights are dm1's times it (DepthMotion.weights); the
    head's cross-entropy with the precise vectors (loss.fit_weight, term flow_precise) reaches it."""
    batch = _batch(seeds=(0,))
    torch.manual_seed(0)
    chain = DeMoN("v1", 0.25, (64, 96), motion_fit=2, flow_refine=1, fit_weights="confidence")
    pair = torch.cat([batch["image1"], batch["image2"]], 1)
    truth = ground_truth_inputs(batch, batch["intrinsics"]).flow
    refinement = chain.refine_flow(pair, truth + 0.01)
    assert refinement.confidence.shape == truth[:, :1].shape
    torch.testing.assert_close(refinement.confidence, torch.full_like(refinement.confidence, 0.5))
    with torch.no_grad():  # a confidence that varies over the pixels
        chain.flow1_refine.confidence[1].conv.bias.fill_(0.3)
        chain.flow1_refine.confidence[1].conv.weight.normal_(0, 0.5)
        _, flowconf2, _ = chain.flow_net1(pair)
        refinement = chain.refine_flow(pair, chain.flow_net1(pair, refine=False)[1][:, :2])
        torch.testing.assert_close(flowconf2[:, 2:], refinement.confidence.expand(-1, 2, -1, -1))
        assert refinement.confidence.std() > 0.01
        dm = chain.depth_motion1(pair, batch["image2"][:, :, ::4, ::4], flowconf2[:, :2], flowconf2[:, 2:],
                                 batch["intrinsics"])
        torch.testing.assert_close(dm.weights, 0.5 * refinement.confidence)  # dm1's own weights start at 0.5
        from demon_lab.core.epipolar import fit_motion

        torch.testing.assert_close(dm.motion, fit_motion(flowconf2[:, :2], dm.weights, batch["intrinsics"], 2))
    refinement = chain.refine_flow(pair, truth + 0.01)
    _, terms = losses.refined_flow_loss(refinement, {"flow2": truth}, {"flow": 1.0, "fit_weight": 2.0})
    terms["flow_precise"].backward()
    assert chain.flow1_refine.confidence[1].conv.weight.grad.abs().sum() > 0
    plain = DeMoN("v1", 0.25, (64, 96), motion_fit=2, flow_refine=1)
    assert plain.flow1_refine.confidence is None and plain.refine_flow(pair, truth).confidence is None


def test_a_joint_dm1_stage_trains_the_refinement_with_dm1_and_its_motion_loss_reaches_it(tmp_path):
    """schedule.stages.dm1.joint=true (design=fit): dm1's stage trains flow1_refine too, its key holds
    the flow weight beside dm1's, and after its steps the refinement's weights differ from flow1r's."""
    from jobs import compose_config, settings, smoke_overrides

    from demon_lab.app.job import run
    from demon_lab.pipeline.stages.schedule import stage_dirs

    steps = [f"scale.steps.{s}={n}" for s, n in (("flow1", 2), ("flow1r", 2), ("dm1", 3))]
    overrides = [*smoke_overrides(tmp_path), "design=fit", *steps, "threads=1", "schedule.until=dm1", "iterations=0",
                 "+schedule.stages.dm1.joint=true", "schedule.stages.dm1.gt_flow_warmup=0",
                 *(f"schedule.stages.{s}.{o}=0" for s in ("flow1", "flow1r", "dm1")
                   for o in ("keep_best", "fresh_scenes"))]
    job = settings(compose_config(overrides))
    assert job.stages["dm1"].trained_nets() == ("dm1", "flow1_refine")
    dirs = {d.name: d for d in stage_dirs(job)}
    assert dirs["dm1"].description["loss"]["flow"] == job.loss["flow"]
    assert run(compose_config(overrides))["status"] == "finished"
    refined, joint = dirs["flow1r"].load()["flow1_refine"], dirs["dm1"].load()
    assert set(joint) == {"dm1", "flow1_refine"}
    assert any(not torch.equal(refined[k], joint["flow1_refine"][k]) for k in refined)
    with pytest.raises(ConfigError, match="joint: only dm1"):
        settings(compose_config(["design=fit", "+schedule.stages.dm2.joint=true"]))
