"""One stage's bare training step timed on a device (forward in the precision's autocast region,
backward, Adam), at the sizes of a :class:`Dims`: what the accelerator check and the benchmarks
compare the job's own loop and the data loaders with."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from demon_lab.core import execution

STAGES = ("flow1", "dm1", "flow2", "dm2", "iterative", "refine")


@dataclass(frozen=True)
class Dims:
    size: tuple[int, int]
    width: float
    batch: int
    new: int  # iterative stage: new samples per step (the rest of the batch is queued)
    scale: str  # the job's scale profile of parts 5 and 6 ("paper"/"cpu", or "smoke" in a dry run)
    loop_steps: int
    workers: int
    seconds: float  # timed seconds per rate


PAPER = Dims((192, 256), 1.0, 32, 8, "paper", 150, 8, 1.5)
DRY = Dims((64, 64), 0.0625, 2, 1, "smoke", 4, 0, 0.2)


_SAMPLES: dict[tuple[int, int], list[dict]] = {}


def batch_of(dims: Dims, n: int, device: torch.device) -> dict[str, torch.Tensor]:
    """``n`` training samples at ``dims.size`` (8 distinct rendered pairs, rendered once, repeated)."""
    from torch.utils.data import default_collate

    from demon_lab.data import synthetic
    from demon_lab.data.sample import normalize_translation

    if dims.size not in _SAMPLES:
        presets = sorted(synthetic.PRESETS)
        rendered = [normalize_translation(synthetic.render_pair(presets[i % 3], 30_000 + i, dims.size))
                    for i in range(8)]
        _SAMPLES[dims.size] = [{k: v for k, v in s.items() if k not in ("meta", "id")} for s in rendered]
    distinct = _SAMPLES[dims.size]
    batch = default_collate([distinct[i % len(distinct)] for i in range(n)])
    return {k: v.to(device) for k, v in batch.items() if isinstance(v, torch.Tensor)}


def _stage(kind: str, chain, dims: Dims):
    from demon_lab.core.losses import preset
    from demon_lab.pipeline.kinds import DepthMotionStage, FlowStage, IterativeStage, RefineStage
    from demon_lab.pipeline.stages.base import StageModule

    w = dict(name=kind, steps=1000, lr=1e-4)
    if kind in ("flow1", "flow2"):
        spec = FlowStage(net=kind, **w)
    elif kind in ("dm1", "dm2"):
        spec = DepthMotionStage(net=kind, **w)
    elif kind == "iterative":
        spec = IterativeStage(queue_size=dims.batch - dims.new, **w)
    else:
        spec = RefineStage(iterations=3, **w)
    return StageModule(chain, spec, weights=preset("released_code"))


def step_rate(device: torch.device, dims: Dims, kind: str, precision: str, channels_last: bool = False,
              compile: bool = False) -> dict[str, float]:
    """Steps/s of one stage's bare training step on ``device``, its peak memory and its first
    steps' time."""
    from demon_lab.core import losses
    from demon_lab.nets.chain import DeMoN

    torch.manual_seed(0)
    chain = execution.prepare_nets(DeMoN("v1", dims.width, dims.size).to(device), channels_last, compile)
    module = _stage(kind, chain, dims)
    # Outside a Trainer global_step stays 0, where every sig weight's ramp is 0 and its term is skipped;
    # DeMoN's stages have them on for all but their first steps: time the step with them.
    module.ramp = lambda *args, **kwargs: 1.0
    module.freeze_upstream()
    module.train()
    optimizer = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=1e-4, eps=1e-6,
                                 foreach=True)
    batch = execution.channels_last_batch(batch_of(dims, dims.new if kind == "iterative" else dims.batch,
                                                 device), channels_last)

    def step():
        with execution.autocast(device, precision):
            loss, _ = module.stage_loss(batch, losses.ground_truth(batch))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    with execution.peak_memory(device) as memory:
        start = time.perf_counter()
        for _ in range(4):  # warm-up (the iterative stage's queue fills; compilation happens here)
            step()
        sync(device)
        first = time.perf_counter() - start
        start = time.perf_counter()
        for _ in range(3):
            step()
        sync(device)
        per_step = (time.perf_counter() - start) / 3
        n = max(5, int(dims.seconds / max(per_step, 1e-6)))
        start = time.perf_counter()
        for _ in range(n):
            step()
        sync(device)
        rate = n / (time.perf_counter() - start)
    return {"steps_per_second": rate, "first_steps_s": first, **memory}


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
