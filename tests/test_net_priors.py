"""The nets' optional priors: the DIS prior flow, the 5-point RANSAC motion, and each net that corrects a
prior starting at it."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from demon_lab.nets import DeMoN, FlowNet


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
