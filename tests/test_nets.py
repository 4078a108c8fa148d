"""DeMoN's nets and chain: parameter counts against the layer tables, shapes at every level, the depth's scale,
the chain's passes and oracles, its option checks, and the correlation front."""

from __future__ import annotations

import pytest
import torch

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
