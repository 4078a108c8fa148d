"""Benchmarks: ``python -m demon_lab.bench SECTION [...]`` writes a table per section to
``reports/bench.md`` (other sections of the file are kept).

Absolute times vary between machines, so every section also reports ratios measured in the same
run (a geometry op against its OpenCV counterpart). Sections:

* ``geometry``: the geometry layers at 256x192, batch 8, float32, on the CPU.
* ``data``: synthetic pairs per second, rendered (one core, worker processes) and from the cache; DeMoN's
  HDF5 files decoded on the training path per loader worker count, at 256x192 and batch 32.
* ``train``: training steps/s per stage at the cpu scale, FLOP/s against matmul, channels-last and
  torch.compile, inference pairs/s of the full chain, and the job's own loop (``python -m
  demon_lab`` training flow1 and dm1) against the bare step.
"""

from __future__ import annotations

import argparse
import datetime as dt
import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from demon_lab.core import geometry as geo
from demon_lab.core import warping
from demon_lab.reporting.tables import markdown_table
from demon_lab.tools.bench_data import bench_data
from demon_lab.tools.benchmarking import BLOCK_S, machine_line, measure


def _scene(batch: int, height: int, width: int) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(0)
    inv = 1 / (1.5 + 4 * torch.rand(batch, 1, height, width, generator=g))
    r = (torch.rand(batch, 3, generator=g) - 0.5) * 0.2
    t = torch.randn(batch, 3, generator=g)
    intrinsics = torch.tensor([geo.DEMON_INTRINSICS] * batch)
    image = torch.rand(batch, 3, height, width, generator=g) - 0.5
    return inv, torch.cat([r, t], 1), intrinsics, image


def bench_geometry(repeats: int) -> str:
    import cv2

    cv2.setNumThreads(torch.get_num_threads())
    batch, height, width = 8, 192, 256
    inv, motion, intrinsics, image = _scene(batch, height, width)
    flow = geo.flow_from_depth_motion(inv, motion, intrinsics)
    flow = torch.nan_to_num(flow)
    mpix = batch * height * width / 1e6

    # OpenCV's counterpart of the warp: cv2.remap per image, maps precomputed (pixel indices).
    images_hwc = [np.ascontiguousarray(image[b].permute(1, 2, 0).numpy()) for b in range(batch)]
    xs = np.arange(width, dtype=np.float32)[None]
    ys = np.arange(height, dtype=np.float32)[:, None]
    maps = [(xs + width * flow[b, 0].numpy(), ys + height * flow[b, 1].numpy()) for b in range(batch)]

    def remap() -> None:
        for img, (mx, my) in zip(images_hwc, maps):
            cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    rows = []
    remap_s = measure(remap, repeats)
    for name, fn in [
        ("warp_image", lambda: warping.warp_image(image, flow)),
        ("flow_from_depth_motion", lambda: geo.flow_from_depth_motion(inv, motion, intrinsics)),
        ("depth_from_flow_motion", lambda: geo.depth_from_flow_motion(flow, motion, intrinsics)),
        ("normals_from_depth", lambda: geo.normals_from_depth(inv, intrinsics)),
    ]:
        with torch.no_grad():
            seconds = measure(fn, repeats)
        ratio = f"{seconds / remap_s:.2f}x cv2.remap ({remap_s * 1e3:.2f} ms)" if name == "warp_image" else ""
        rows.append((name, f"{seconds * 1e3:.2f}", f"{mpix / seconds:.1f}", ratio))

    # Where the warp's time goes: the sampling kernel alone on the same samples (no mask).
    grid = torch.stack([(2 * torch.from_numpy(mx) + 1) / width - 1 for mx, _ in maps]
                       + [(2 * torch.from_numpy(my) + 1) / height - 1 for _, my in maps])
    grid = grid.view(2, batch, height, width).permute(1, 2, 3, 0).contiguous()
    sample_s = measure(lambda: torch.nn.functional.grid_sample(
        image, grid, mode="bilinear", padding_mode="zeros", align_corners=False), repeats)
    rows.insert(1, ("  of which grid_sample alone", f"{sample_s * 1e3:.2f}", f"{mpix / sample_s:.1f}",
                    f"{sample_s / remap_s:.2f}x cv2.remap"))

    # Rotation conversions against cv2.Rodrigues (one call per rotation, as OpenCV offers).
    for n in (batch, 4096):
        r = (torch.rand(n, 3, generator=torch.Generator().manual_seed(1)) - 0.5) * 2
        r_np = [x.reshape(3, 1).astype(np.float64) for x in r.double().numpy()]
        R = geo.angle_axis_to_matrix(r)
        R_np = [np.ascontiguousarray(m, dtype=np.float64) for m in R.double().numpy()]
        cv_fwd = measure(lambda r_np=r_np: [cv2.Rodrigues(x) for x in r_np], repeats)
        cv_inv = measure(lambda R_np=R_np: [cv2.Rodrigues(m) for m in R_np], repeats)
        with torch.no_grad():
            fwd = measure(lambda r=r: geo.angle_axis_to_matrix(r), repeats)
            inv_s = measure(lambda R=R: geo.matrix_to_angle_axis(R), repeats)
        rows.append((f"angle_axis_to_matrix (B={n})", f"{fwd * 1e3:.3f}", "",
                     f"{fwd / cv_fwd:.2f}x cv2.Rodrigues loop ({cv_fwd * 1e3:.3f} ms)"))
        rows.append((f"matrix_to_angle_axis (B={n})", f"{inv_s * 1e3:.3f}", "",
                     f"{inv_s / cv_inv:.2f}x cv2.Rodrigues loop ({cv_inv * 1e3:.3f} ms)"))

    lines = [
        "## geometry",
        "",
        f"`python -m demon_lab.bench geometry` — {dt.date.today().isoformat()}, {machine_line()}.",
        f"Maps at {width}x{height}, batch {batch}, float32, CPU, forward only (median per call, "
        f"torch.utils.benchmark's blocked_autorange over at least {repeats * BLOCK_S:g} s). Ratios below 1 "
        "mean demon_lab is faster than OpenCV in the same run; "
        "cv2.remap gets precomputed maps and one call per image.",
        "",
        markdown_table(["op", "ms / call", "Mpixel/s", "vs OpenCV (same run)"], rows, "lrrl"),
        "",
    ]
    return "\n".join(lines)


def _matmul_flops(repeats: int) -> float:
    a, b = torch.rand(2048, 2048), torch.rand(2048, 2048)
    return 2 * 2048**3 / measure(lambda: a @ b, max(3, repeats // 2))


def bench_train(repeats: int) -> str:
    """Training steps per second per stage at the cpu scale, achieved FLOP/s against this
    machine's float32 matmul FLOP/s, channels-last and torch.compile, inference pairs/s."""
    import warnings

    from torch.utils.data import default_collate
    from torch.utils.flop_counter import FlopCounterMode

    from demon_lab.core import losses
    from demon_lab.data import synthetic
    from demon_lab.data.sample import normalize_translation
    from demon_lab.nets.chain import DeMoN
    from demon_lab.pipeline.stages.modules import DepthMotionStage, FlowStage, IterativeStage, RefineStage

    warnings.filterwarnings("ignore")
    size, width, batch_size = (96, 128), 0.25, 8  # the cpu scale (conf/scale/cpu.yaml)
    weights = losses.preset("released_code")
    samples = []
    for i in range(batch_size):
        s = normalize_translation(synthetic.render_pair("synthetic_sun3d", 10_000 + i, size))
        s.pop("meta", None)
        samples.append(s)
    batch = default_collate(samples)
    batch.pop("id")
    peak = _matmul_flops(repeats)

    def stage_rate(make, channels_last: bool = False, compile_step: bool = False, correlation=None,
                   flow1_prior=None):
        chain = DeMoN("v1", width, size, correlation=correlation, flow1_prior=flow1_prior)
        if channels_last:
            chain = chain.to(memory_format=torch.channels_last)
        module = make(chain)
        module.train()
        opt = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=1e-4, eps=1e-6)
        b = {k: v.contiguous(memory_format=torch.channels_last) if channels_last and v.dim() == 4 else v
             for k, v in batch.items()}

        def step():
            loss, _ = module.stage_loss(b, losses.ground_truth(b))
            opt.zero_grad()
            loss.backward()
            opt.step()

        fn = torch.compile(step) if compile_step else step
        fn()
        fn()
        with FlopCounterMode(display=False) as counter:
            step()
        flops = counter.get_total_flops()
        seconds = measure(fn, max(3, repeats // 4), block_s=0.125)
        return 1 / seconds, flops / seconds

    def mid_stage(module):
        """The step as the profile trains it past its first step: the flow stages and the iterative
        stage without their flow sig terms (``sig_start: 1``), the depth sig terms of the others on
        (outside a Trainer the step count stays 0, where their ramps are 0 and the terms skipped)."""
        module.ramp = lambda *args, **kwargs: 1.0
        return module

    kinds = [
        ("flow1", lambda c: FlowStage(c, weights=weights, steps=1000, lr=1e-4, net="flow1", sig_start=1.0)),
        ("dm1", lambda c: mid_stage(DepthMotionStage(c, weights=weights, steps=1000, lr=1e-4, net="dm1"))),
        ("flow2", lambda c: FlowStage(c, weights=weights, steps=1000, lr=1e-4, net="flow2", sig_start=1.0)),
        ("dm2", lambda c: mid_stage(DepthMotionStage(c, weights=weights, steps=1000, lr=1e-4, net="dm2"))),
        ("iterative", lambda c: IterativeStage(c, weights=weights, steps=1000, lr=1e-4, queue_size=8, sig_start=1.0)),
        ("refine", lambda c: mid_stage(RefineStage(c, weights=weights, steps=1000, lr=1e-4))),
    ]
    rows = []
    for name, make in kinds:
        rate, flops = stage_rate(make)
        rows.append((name, "default", f"{rate:.2f}", f"{flops / 1e9:.1f}", f"{flops / peak:.1%}"))
    correlation = lambda c: FlowStage(c, weights=weights, steps=1000, lr=1e-4, net="flow1", sig_start=1.0)  # noqa: E731
    rate, flops = stage_rate(correlation, correlation=(8, 2))
    rows.append(("flow1", "correlation [8, 2]", f"{rate:.2f}", f"{flops / 1e9:.1f}", f"{flops / peak:.1%}"))
    rate, flops = stage_rate(correlation, flow1_prior="dis")  # flops: the nets' (DIS runs in OpenCV)
    rows.append(("flow1", "DIS prior", f"{rate:.2f}", f"{flops / 1e9:.1f}", f"{flops / peak:.1%}"))
    for label, kw in (("channels-last", {"channels_last": True}), ("torch.compile", {"compile_step": True})):
        try:
            rate, flops = stage_rate(kinds[0][1], **kw)
            rows.append(("flow1", label, f"{rate:.2f}", f"{flops / 1e9:.1f}", f"{flops / peak:.1%}"))
        except Exception as e:
            rows.append(("flow1", label, f"failed: {type(e).__name__}", "", ""))
    logging_share = _logging_share(kinds[0][1], batch, size, width)
    job = job_rates(JOB_COMMAND, ("flow1", "dm1"))
    bare = {r[0]: float(r[2]) for r in rows if r[1] == "default"}
    chain = DeMoN("v1", 1.0, (192, 256)).eval()
    images = torch.rand(1, 3, 192, 256) - 0.5
    K = torch.tensor([[0.89115971, 1.18821287, 0.5, 0.5]])
    with torch.no_grad():
        infer = measure(lambda: chain(images, images, K, iterations=3), max(3, repeats // 4), block_s=0.25)
    lines = [
        "## train",
        "",
        f"`python -m demon_lab.bench train` — {dt.date.today().isoformat()}, {machine_line()}.",
        f"Training steps per second of each stage at the `cpu` scale ({size[1]}x{size[0]}, width {width}, batch "
        f"{batch_size}; iterative: 8 new + 8 queued), forward+backward+Adam. Achieved FLOP/s = FLOPs of a step "
        "(torch.utils.flop_counter) / its time, against this machine's float32 matmul "
        f"(2048x2048) measured in the same run: {peak / 1e9:.0f} GFLOP/s.",
        "",
        markdown_table(["stage", "variant", "steps/s", "GFLOP/s", "of matmul peak"], rows, "llrrr"),
        "",
        f"Inference of the full chain (v1, full width, 256x192, bootstrap + 3 iterations + refinement, batch 1): "
        f"{1 / infer:.2f} pairs/s.",
        "",
        f"Share of training wall time spent in MLflow logging (flow1 stage, 300 steps through Lightning, "
        f"metrics every 10 steps to a fresh SQLite store): {logging_share:.2%}.",
        "",
        f"The real loop: `{' '.join(JOB_COMMAND)}` ({JOB_STEPS} steps per stage, the job's data path, "
        "validation, checkpoints and MLflow logging; an empty stage cache, the data cache as the user has it), "
        "each stage's `stage/<name>/steps_per_second` from its MLflow run against the step above:",
        "",
        job_table(job, bare),
        "",
    ]
    return "\n".join(lines)


def job_table(job: Mapping[str, float], bare: Mapping[str, float]) -> str:
    """The train section's last table: per stage, its steps/s in the job (``job``), the bare step's
    (``bare``) and their ratio."""
    return markdown_table(["stage", "job steps/s", "step alone, steps/s", "job / step"],
                          [[k, f"{v:.2f}", f"{bare[k]:.2f}", f"{v / bare[k]:.1%}"] for k, v in job.items()], "lrrr")


JOB_STEPS = 1000
JOB_COMMAND = ("python", "-m", "demon_lab", "schedule.until=dm1", "iterations=0", f"scale.steps.flow1={JOB_STEPS}",
               f"scale.steps.dm1={JOB_STEPS}")


def job_rates(command: Sequence[str], stages: Sequence[str]) -> dict[str, float]:
    """Steps/s of ``stages`` as the job trains them: ``command`` (``python -m demon_lab ...``) in a
    subprocess with a temporary stage cache and MLflow store, each stage's
    ``stage/<name>/steps_per_second`` read from the job's run."""
    import subprocess
    import sys
    import tempfile

    import mlflow

    with tempfile.TemporaryDirectory() as tmp:
        uri = f"sqlite:///{tmp}/mlflow.db"
        cmd = [sys.executable, *command[1:], f"cache_dir={tmp}/cache", f"tracking.uri={uri}",
               f"tracking.artifact_dir={tmp}/artifacts", f"hydra.run.dir={tmp}/out"]
        subprocess.run(cmd, check=True, cwd=tmp, stdout=subprocess.DEVNULL)
        client = mlflow.MlflowClient(tracking_uri=uri)
        runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
        rates = {}
        for run in runs:
            for name in stages:
                value = run.data.metrics.get(f"stage/{name}/steps_per_second")
                if value is not None:
                    rates[name] = value
        return {name: rates[name] for name in stages}


def _logging_share(make, batch, size, width, steps: int = 300) -> float:
    """Train a stage through Lightning with the stage logger of a job (Lightning's MLFlowLogger on
    an MLflow run); the logger's time over the whole fit's time."""
    import tempfile

    import lightning as L
    from lightning.pytorch.loggers import MLFlowLogger

    from demon_lab.nets.chain import DeMoN
    from demon_lab.pipeline.tracking import Tracker, process_tracking_uri

    class TimedLogger(MLFlowLogger):
        seconds = 0.0

        def log_metrics(self, metrics, step=None):
            start = time.perf_counter()
            super().log_metrics(metrics, step)
            TimedLogger.seconds += time.perf_counter() - start

    class Repeat(torch.utils.data.Dataset):
        def __len__(self):
            return steps

        def __getitem__(self, i):
            return {k: v[i % v.shape[0]] for k, v in batch.items()}

    with tempfile.TemporaryDirectory() as tmp, process_tracking_uri():  # the logger sets it process-wide
        tracker = Tracker(f"sqlite:///{tmp}/mlflow.db", "bench", f"{tmp}/artifacts")
        run_id = tracker.start("bench", {})
        logger = TimedLogger(tracking_uri=tracker.uri, run_id=run_id)
        module = make(DeMoN("v1", width, size))
        trainer = L.Trainer(max_steps=steps, logger=logger, log_every_n_steps=10, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
        start = time.perf_counter()
        trainer.fit(module, torch.utils.data.DataLoader(Repeat(), batch_size=batch["image1"].shape[0]))
        total = time.perf_counter() - start
        return TimedLogger.seconds / total


SECTIONS: dict[str, Callable[[int], str]] = {"geometry": bench_geometry, "data": bench_data, "train": bench_train}


def write_section(path: Path, name: str, body: str) -> None:
    """Replace (or append) the section ``name`` of the markdown file, keeping the others."""
    start, end = f"<!-- bench:{name} -->", f"<!-- /bench:{name} -->"
    block = f"{start}\n{body.rstrip()}\n{end}\n"
    text = path.read_text() if path.exists() else "# demon_lab benchmarks\n\n"
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end) + r"\n?", re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sections", nargs="+", choices=[*SECTIONS, "all"])
    parser.add_argument("--repeats", type=int, default=20,
                        help="effort: each geometry timing runs at least REPEATS x 50 ms; the data and train "
                        "sections scale their samples and timings with it")
    parser.add_argument("--out", type=Path, default=Path("reports/bench.md"))
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    names = list(SECTIONS) if "all" in args.sections else args.sections
    for name in names:
        body = SECTIONS[name](args.repeats)
        print(body)
        write_section(args.out, name, body)
    print(f"wrote {args.out}")
    return 0

