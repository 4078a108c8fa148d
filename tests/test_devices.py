"""The chain's pieces on each device against a float64 CPU reference: geometry layers, nets, losses
with their gradients, evaluation metrics, a mixed-precision training step and channels-last.

The cuda cases skip where no GPU is (with the reason); ``scripts/device_check.sh`` runs them on one
(``-m cuda``). TF32 is off in these comparisons (PyTorch allows it for cuDNN convolutions by default),
so a float32 result is compared as float32. Nothing here needs Hydra or MLflow: the device check runs
this file on a machine that has only torch, Lightning and the data libraries.
"""

from __future__ import annotations

import pytest
import torch
from conftest import DEVICES, random_scene
from torch.utils.data import default_collate

from demon_lab.core import execution, loss_maps, losses, warping
from demon_lab.core import geometry as geo
from demon_lab.nets.chain import DeMoN
from demon_lab.pipeline.kinds import DepthMotionStage, FlowStage
from demon_lab.pipeline.stages.base import StageModule

WEIGHTS = losses.preset("released_code")


@pytest.fixture(autouse=True)
def no_tf32():
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def _batch(size=(64, 64), n: int = 2, seed: int = 0) -> dict:
    from demon_lab.data import synthetic
    from demon_lab.data.sample import normalize_translation

    samples = []
    for i in range(n):
        s = normalize_translation(synthetic.render_pair("synthetic_sun3d", 20_000 + seed + i, size))
        s.pop("meta", None)
        samples.append(s)
    batch = default_collate(samples)
    batch.pop("id")
    return batch


def _to(batch: dict, device, dtype=None) -> dict:
    return {k: v.to(device=device, dtype=dtype if dtype is not None and v.is_floating_point() else v.dtype)
            for k, v in batch.items()}


def _close(actual: torch.Tensor, reference: torch.Tensor, tol: float) -> None:
    """Within ``tol`` of the reference's largest finite magnitude, NaN where it is NaN."""
    actual, reference = actual.detach().double().cpu(), reference.detach().double().cpu()
    scale = float(reference[torch.isfinite(reference)].abs().max()) or 1.0
    torch.testing.assert_close(actual, reference, rtol=0, atol=tol * scale, equal_nan=True)


@pytest.mark.parametrize("device", DEVICES)
def test_geometry_layers_on_the_device_match_float64(device):
    inv, motion, K = random_scene(2, 48, 64, seed=3)
    image = torch.rand(2, 3, 48, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    ref = {"flow": geo.flow_from_depth_motion(inv, motion, K), "normals": geo.normals_from_depth(inv, K),
           "R": geo.angle_axis_to_matrix(motion[:, :3]), "pyramid": loss_maps.inverse_depth_pyramid(inv, levels=3)[3]}
    ref["depth"] = geo.depth_from_flow_motion(ref["flow"], motion, K)
    ref["warp"] = warping.warp_image(image, ref["flow"])
    ref["r"] = geo.matrix_to_angle_axis(ref["R"])
    d_inv, d_motion, d_K, d_image = (x.to(device, torch.float32) for x in (inv, motion, K, image))
    got = {"flow": geo.flow_from_depth_motion(d_inv, d_motion, d_K), "normals": geo.normals_from_depth(d_inv, d_K),
           "R": geo.angle_axis_to_matrix(d_motion[:, :3]),
           "pyramid": loss_maps.inverse_depth_pyramid(d_inv, levels=3)[3]}
    got["depth"] = geo.depth_from_flow_motion(ref["flow"].to(device, torch.float32), d_motion, d_K)
    got["warp"] = warping.warp_image(d_image, ref["flow"].to(device, torch.float32))
    got["r"] = geo.matrix_to_angle_axis(ref["R"].to(device, torch.float32))
    for key in ref:
        assert got[key].device.type == device and got[key].dtype == torch.float32, key
        _close(got[key], ref[key], 1e-4 if key != "depth" else 1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_nets_on_the_device_match_float64(device):
    torch.manual_seed(0)
    chain = DeMoN("v1", 0.125, (64, 64)).eval()
    batch = _batch()
    with torch.no_grad():
        ref = chain.double()(*(batch[k].double() for k in ("image1", "image2", "intrinsics")), iterations=1)
        out = chain.to(device, torch.float32)(*(batch[k].to(device) for k in ("image1", "image2", "intrinsics")),
                                              iterations=1)
    for k, (p, q) in enumerate(zip(out.passes, ref.passes)):
        for field in ("flow", "conf", "inv_depth", "normals", "motion"):
            assert getattr(p, field).device.type == device
            _close(getattr(p, field), getattr(q, field), 1e-4 if k == 0 else 1e-3)
    _close(out.refined, ref.refined, 1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_losses_and_their_gradients_on_the_device_match_float64(device):
    batch = _batch()
    torch.manual_seed(1)
    flow5 = 0.05 * torch.randn(2, 4, 2, 2, dtype=torch.float64)
    flow2 = 0.05 * torch.randn(2, 4, 16, 16, dtype=torch.float64)
    inv = 0.3 + 0.1 * torch.rand(2, 1, 16, 16, dtype=torch.float64)
    normals = torch.randn(2, 3, 16, 16, dtype=torch.float64)
    motion = 0.1 * torch.randn(2, 6, dtype=torch.float64)

    def run(device, dtype):
        leaves = [x.detach().to(device, dtype).clone().requires_grad_(True)
                  for x in (flow5, flow2, inv, normals, motion)]
        gt = losses.ground_truth(_to(batch, device, dtype))
        f, _ = losses.flow_loss(leaves[0], leaves[1], gt, WEIGHTS, ramp=1.0, level5=0.5)
        d, _ = losses.depth_motion_loss(*leaves[2:], gt, WEIGHTS, ramp=1.0)
        (f + d).backward()
        return f + d, [x.grad for x in leaves]

    ref, ref_grads = run("cpu", torch.float64)
    got, grads = run(device, torch.float32)
    assert got.device.type == device
    torch.testing.assert_close(got.double().cpu(), ref, rtol=1e-4, atol=0)
    for g, r in zip(grads, ref_grads):
        _close(g, r, 1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_evaluation_metrics_on_the_device_match_the_cpu(device):
    from demon_lab.data.datasets import SyntheticDataset
    from demon_lab.pipeline.evaluate import evaluate_dataset

    torch.manual_seed(2)
    chain = DeMoN("v1", 0.125, (64, 64)).eval()
    dataset = SyntheticDataset("synthetic_sun3d", "test", length=3, size=(64, 64))
    ref, _ = evaluate_dataset(chain.double().float(), dataset, iterations=0, batch_size=2)
    got, _ = evaluate_dataset(chain.to(device), dataset, iterations=0, batch_size=2)
    assert len(got) == len(ref)
    for g, r in zip(got, ref):
        assert g["id"] == r["id"] and g["it"] == r["it"]
        for key in ("l1_inv", "sc_inv", "rot_deg", "epe"):  # well-conditioned: relative 1e-3
            assert g[key] == pytest.approx(r[key], rel=1e-3, abs=1e-5), key


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("precision", ["bf16-mixed", "16-mixed"])
def test_a_mixed_precision_training_step_on_the_device_is_close_to_float32(device, precision):
    if execution.precision_problem(precision, device):
        pytest.skip(execution.precision_problem(precision, device))
    # four pairs: the gradient of two pairs at this initialisation is ill-conditioned enough that
    # bf16's rounding alone turns dm1's by up to 0.949 in cosine on some CPUs (0.985 with four)
    batch = _to(_batch(n=4), device)
    results = {}
    for name in ("32-true", precision):
        torch.manual_seed(4)
        chain = DeMoN("v1", 0.125, (64, 64)).to(device)
        stages = [StageModule(chain, FlowStage(name="flow1", steps=10, lr=1e-4, net="flow1"), weights=WEIGHTS),
                  StageModule(chain, DepthMotionStage(name="dm1", steps=10, lr=1e-4, net="dm1"), weights=WEIGHTS)]
        out = []
        for stage in stages:
            stage.freeze_upstream()  # (the stages share one chain: as on_fit_start does)
            stage.train()
            with execution.autocast(device, name):
                loss, terms = stage.stage_loss(batch, losses.ground_truth(batch))
            assert loss.dtype == torch.float32 and all(t.dtype == torch.float32 for t in terms.values())
            params = list(getattr(chain, stage.trained[0]).parameters())
            # float16 gradients underflow without loss scaling: scale as Lightning's GradScaler does,
            # backing off where a scale overflows
            for scale in ((1024.0, 64.0, 1.0) if name == "16-mixed" else (1.0,)):
                grad = torch.cat([g.flatten() for g in torch.autograd.grad(loss * scale, params,
                                                                            retain_graph=True)]) / scale
                if torch.isfinite(grad).all():
                    break
            out.append((loss.detach(), grad))
        results[name] = out
    for net, (loss32, grad32), (loss_mixed, grad_mixed) in zip(("flow1", "dm1"), results["32-true"],
                                                                 results[precision]):
        assert torch.isfinite(loss_mixed) and torch.isfinite(grad_mixed).all()
        cosine = float(torch.nn.functional.cosine_similarity(grad32, grad_mixed, dim=0))
        print(f"{precision} on {device}, {net}: loss {abs(float(loss_mixed / loss32) - 1):.2%} from float32, "
              f"gradient cosine {cosine:.3f}")  # (pytest -s shows it)
        assert float(loss_mixed) == pytest.approx(float(loss32), rel=0.02)
        assert cosine > 0.95


@pytest.mark.parametrize("device", DEVICES)
def test_channels_last_changes_the_layout_not_the_result(device):
    batch = _to(_batch(), device)
    losses_by_layout = []
    for channels_last in (False, True):
        torch.manual_seed(5)
        chain = execution.prepare_nets(DeMoN("v1", 0.125, (64, 64)).to(device), channels_last=channels_last)
        stage = StageModule(chain, FlowStage(name="flow1", steps=10, lr=1e-4, net="flow1"), weights=WEIGHTS,
                            channels_last=channels_last)
        b = stage.on_after_batch_transfer(dict(batch), 0)
        assert b["image1"].is_contiguous(memory_format=torch.channels_last) == channels_last
        assert chain.flow1.conv1.y.conv.weight.is_contiguous(memory_format=torch.channels_last) == channels_last
        loss, _ = stage.stage_loss(b, losses.ground_truth(b))
        losses_by_layout.append(loss.detach())
        state = execution.plain_state(chain.flow1)
        assert all(v.is_contiguous() for v in state.values())
    torch.testing.assert_close(losses_by_layout[1], losses_by_layout[0], rtol=1e-5, atol=0)
