"""The accelerator check: ``scripts/device_check.sh [--dry-run] [--budget SECONDS] [--out FILE]``
(or ``python -m demon_lab.device_check``) prints one table and writes it to ``reports/device_check.md``.

In order, each within what is left of the time budget (default 420 s; a part that would not fit is
listed as skipped, one that fails is listed with its error, and the check goes on):

1. the device-parametrised tests on CUDA (``pytest -m cuda``: geometry, nets, losses with their
   gradients, metrics and a mixed-precision training step, each against a float64 CPU reference);
2. full-chain inference pairs/s at 256x192 (bootstrap + 3 iterations + refinement), batch 1 and
   32, in float32 and in bf16-mixed with channels-last;
3. training steps/s of every stage at ``scale=paper`` (256x192, full width, batch 32; iterative:
   8 new + 24 queued) in float32 and bf16-mixed + channels-last, flow1 and dm1 also in float32 +
   channels-last and plain bf16-mixed, and the peak GPU memory of each (the bare step: forward in
   the precision's autocast region with the sig terms on, backward, Adam), flow1 with
   cudnn.benchmark on, and DeMoN's full schedule at those rates;
4. DeMoN's HDF5 training path per loader worker count (past the loader's prefetch) against 4x the
   fastest step of part 3;
5. the job's own loop at ``scale=paper`` (flow1, 150 steps through Lightning with the profile's 8
   loader workers, bf16-mixed, channels-last) against its bare step;
6. the ``cpu`` profile's six stages trained on the GPU (the default job's schedule), per stage;
7. torch.compile (``model.compile``) of flow1 and dm1 in bf16-mixed with channels-last, each in a
   subprocess the budget stops (dm1 only if time is left): compile time and steps/s.

Parts 5 and 6 compose the job's config and so need Hydra and OmegaConf (on a GPU host without
demon_lab's environment, ``scripts/device_check.sh`` installs their wheels from ``.whl/``:
docs/running.md, "Paper scale"); MLflow is not used. ``--dry-run`` runs every part on whatever
device there is at toy sizes (64x64, width 1/16, batch 2; compile left out), as CI does on its CPU.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from demon_lab.core import execution
from demon_lab.tools.step_rate import DRY, PAPER, STAGES, Dims, batch_of, step_rate


@dataclass
class Check:
    budget: float
    dry_run: bool
    device: torch.device
    rows: list[tuple[str, str, str, str]] = field(default_factory=list)
    start: float = field(default_factory=time.perf_counter)

    def left(self) -> float:
        return self.budget - (time.perf_counter() - self.start)

    def add(self, part: str, setting: str, result: str, note: str = "") -> None:
        self.rows.append((part, setting, result, note))
        print(f"[device_check] {part} | {setting} | {result} | {note}", flush=True)

    def part(self, part: str, needs: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` if ``needs`` seconds are left, else list it as skipped; an error is a row."""
        if self.left() < needs:
            self.add(part, "all", f"skipped: {self.left():.0f} s of the budget left, it needs ~{needs:.0f} s")
            return
        try:
            fn()
        except Exception as e:  # the check reports and goes on: one broken part must not hide the others
            self.add(part, "all", f"failed: {type(e).__name__}: {str(e).splitlines()[0][:200] if str(e) else ''}")

    def sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)


def _release(device: torch.device) -> None:
    """Free the last measurement's chain, optimiser and activations before the next one's peak."""
    import gc

    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()


def _fmt_rate(r: dict[str, float], unit: str = "steps/s") -> str:
    mem = f", peak {r['peak_gib']:.1f} GiB" if "peak_gib" in r else ""
    return f"{r['steps_per_second']:.2f} {unit}{mem}"


def part_tests(check: Check) -> None:
    from demon_lab.resources import PACKAGE

    root = PACKAGE.resolve().parent  # the checkout, when demon_lab runs from one
    files = ["tests/test_devices.py"] + ([] if check.dry_run else ["tests/test_geometry.py"])
    marker = "not cuda" if check.dry_run else "cuda"
    if not (root / files[0]).is_file():
        check.add("1 tests", marker, "skipped: run from a source checkout (tests/ is not installed)")
        return
    cmd = [sys.executable, "-m", "pytest", *files, "-m", marker, "-q", "-p", "no:cacheprovider", "-o", "addopts=-ra"]
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=max(30.0, check.left() - 60))
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    summary = next((line.strip("= ") for line in reversed(lines) if " in " in line and (
        "passed" in line or "failed" in line or "skipped" in line or "error" in line)), f"exit {proc.returncode}")
    failed = [line for line in lines if line.startswith(("FAILED", "ERROR"))]
    check.add("1 tests", f"{' '.join(files)} -m '{marker}' on {check.device.type}", summary,
              "; ".join(failed)[:300] if failed else ("all passed" if proc.returncode == 0 else proc.stderr[-200:]))


def part_inference(check: Check, dims: Dims) -> None:
    """The evaluation's loop (:func:`demon_lab.pipeline.evaluate.run_chain`) on one batch, repeated."""
    from demon_lab.nets.chain import DeMoN
    from demon_lab.pipeline.evaluate import run_chain

    torch.manual_seed(0)
    for batch_size in (1, dims.batch):
        for precision, channels_last in (("32-true", False), ("bf16-mixed", True)):
            chain = execution.prepare_nets(DeMoN("v1", dims.width, dims.size).to(check.device).eval(), channels_last)
            # the batch in the layout run_chain gives it: the timed loop is the chain's alone
            b = execution.channels_last_batch(batch_of(dims, batch_size, check.device), channels_last)
            outputs = run_chain(chain, itertools.repeat(b), 3, precision=precision, channels_last=channels_last)
            with execution.peak_memory(check.device) as memory:
                next(outputs)
                check.sync()
                start = time.perf_counter()
                n = 0
                while n < 3 or time.perf_counter() - start < dims.seconds:
                    next(outputs)
                    check.sync()
                    n += 1
                rate = n * batch_size / (time.perf_counter() - start)
            check.add("2 inference", f"batch {batch_size}, {precision}{', channels-last' if channels_last else ''}",
                      _fmt_rate({"steps_per_second": rate, **memory}, "pairs/s"))


def part_steps(check: Check, dims: Dims, rates: dict[tuple, float]) -> None:
    """flow1 and dm1 in all four variants, the other stages in float32 and bf16-mixed + channels-last."""
    every = [("32-true", False), ("32-true", True), ("bf16-mixed", False), ("bf16-mixed", True)]
    for kind in STAGES:
        for precision, channels_last in every if kind in ("flow1", "dm1") else [every[0], every[3]]:
            label = f"{kind}, {precision}{', channels-last' if channels_last else ''}"
            if check.left() < 25:
                check.add("3 train steps", label, "skipped: budget")
                continue
            try:
                r = step_rate(check.device, dims, kind, precision, channels_last)
                rates[(kind, precision, channels_last)] = r["steps_per_second"]
                check.add("3 train steps", label, _fmt_rate(r))
            except Exception as e:
                check.add("3 train steps", label, f"failed: {type(e).__name__}: {str(e).splitlines()[0][:160]}")
            _release(check.device)
    schedule = paper_schedule()
    for precision, channels_last in (("32-true", False), ("bf16-mixed", True)):
        got = {k: rates.get((k, precision, channels_last)) for k in STAGES}
        if all(got.values()):
            days = sum(schedule[k] / got[k] for k in STAGES) / 86400
            check.add("3 full schedule", f"{precision}{', channels-last' if channels_last else ''}",
                      f"{days:.1f} days", f"DeMoN's {sum(schedule.values()) / 1e6:.2f} M steps (conf/scale/paper.yaml) "
                      "at these bare-step rates, one GPU; the job's loop is slower by part 5's ratio")
    if check.device.type == "cuda" and check.left() > 40:
        saved = torch.backends.cudnn.benchmark
        torch.backends.cudnn.benchmark = True
        try:
            r = step_rate(check.device, dims, "flow1", "bf16-mixed", True)
            check.add("3 train steps", "flow1, bf16-mixed, channels-last, cudnn.benchmark", _fmt_rate(r),
                      "the job trains with cudnn.benchmark off (deterministic kernels where they exist)")
        finally:
            torch.backends.cudnn.benchmark = saved


def paper_schedule() -> dict[str, int]:
    """The steps of each stage at scale=paper (conf/scale/paper.yaml)."""
    import yaml

    from demon_lab.resources import CONF

    return {k: int(v) for k, v in yaml.safe_load((CONF / "scale" / "paper.yaml").read_text())["scale"]["steps"].items()}


def part_data(check: Check, dims: Dims, rates: dict[tuple, float]) -> None:
    from demon_lab.data import throughput

    fastest = max(rates.values()) if rates else None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "demon_layout.h5"
        throughput.write_demon_layout_file(path, 3 if check.dry_run else 24, dims.size)
        workers = [0, 1] if check.dry_run else throughput.worker_counts()
        got = throughput.demon_h5_rates(path, workers, dims.batch, batches=2 if check.dry_run else 6, size=dims.size,
                                   pin_memory=check.device.type == "cuda")
    for w, r in got.items():
        fed = r / dims.batch / 4
        verdict = "" if fastest is None else (
            f"{'meets' if fed >= fastest else 'below'} the goal: 4x the fastest step of part 3 ({fastest:.2f} steps/s)")
        check.add("4 DeMoN HDF5 data", f"{w} loader workers, batch {dims.batch}",
                  f"{r:.0f} samples/s = {fed:.2f} steps/s fed with 4x headroom", verdict)


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    from demon_lab.resources import CONF

    with initialize_config_dir(str(CONF), version_base="1.3"):
        return compose("config", overrides=overrides)


def part_loop(check: Check, dims: Dims, rates: dict[tuple, float]) -> None:
    from demon_lab.pipeline.stages.training import prepare_chain
    from demon_lab.pipeline.validate import validate

    with tempfile.TemporaryDirectory() as tmp:
        cfg = _compose([f"scale={dims.scale}", "schedule.until=flow1", "iterations=0",
                        f"scale.steps.flow1={dims.loop_steps}", "precision=bf16-mixed", "model.channels_last=true",
                        f"data.num_workers={dims.workers}", f"cache_dir={tmp}", f"data.cache_dir={tmp}/data",
                        # 48 scenes per preset at paper scale (its 200,000 are for training, not timing)
                        *(["data.train_length=48"] if dims.scale == "paper" else [])])
        job = validate(cfg)
        # the Trainer turns deterministic algorithms on process-wide (deterministic="warn"): put back
        # what the later parts measure with
        saved = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
        start = time.perf_counter()
        try:
            _, _, figures = prepare_chain(job, progress=False)
        finally:
            torch.use_deterministic_algorithms(saved[0], warn_only=saved[1])
        wall = time.perf_counter() - start
    rate = figures["flow1"]["steps_per_second"]
    bare = rates.get(("flow1", "bf16-mixed", True))
    ratio = f"{rate / bare:.0%} of the bare step ({bare:.2f} steps/s)" if bare else "no bare step measured"
    check.add("5 job loop", f"scale={dims.scale} flow1 {dims.loop_steps} steps, bf16-mixed, channels-last, "
              f"{dims.workers} loader workers", f"{rate:.2f} steps/s", f"{ratio}; {wall:.0f} s with rendering")


def part_cpu_profile(check: Check, dims: Dims, timeout: float) -> None:
    """The default job's six stages, trained one after the other in a subprocess (each stage's time
    is written as it finishes, so a stage cut off by the budget still leaves the ones before it)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "stages.jsonl"
        scale = "smoke" if check.dry_run else "cpu"
        cmd = [sys.executable, "-m", "demon_lab.device_check", "--profile-worker", str(out), "--scale", scale,
               "--cache", str(Path(tmp) / "cache")]
        start = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
            error = None if proc.returncode == 0 else (proc.stderr.strip().splitlines() or ["?"])[-1][:200]
        except subprocess.TimeoutExpired:
            error = f"stopped at the budget ({timeout:.0f} s)"
        wall = time.perf_counter() - start
        done = [json.loads(line) for line in out.read_text().splitlines()] if out.is_file() else []
    for entry in done:
        if entry["stage"] == "render":
            check.add("6 cpu profile", "render the training scenes", f"{entry['seconds']:.1f} s")
        else:
            check.add("6 cpu profile", f"{entry['stage']} ({entry['steps']} steps)",
                      f"{entry['seconds']:.1f} s, {entry['steps_per_second']:.1f} steps/s")
    trained = sum(e["seconds"] for e in done if e["stage"] != "render")
    stages = [e["stage"] for e in done if e["stage"] != "render"]
    total = f"{len(stages)} of 6 stages in {trained:.0f} s of training ({wall:.0f} s with start-up and rendering)"
    check.add("6 cpu profile", f"scale={scale}, the six stages", total, error or "")


def profile_worker(out: Path, scale: str, cache: Path) -> None:
    from demon_lab.data.datasets import warm_cache
    from demon_lab.pipeline.config import instantiate
    from demon_lab.pipeline.stages.training import prepare_chain
    from demon_lab.pipeline.validate import validate

    def write(entry):
        with out.open("a") as f:
            f.write(json.dumps(entry) + "\n")

    base = [f"scale={scale}", f"cache_dir={cache}", f"data.cache_dir={cache}/data", "iterations=0"]
    cfg = _compose(base)
    start = time.perf_counter()
    warm_cache([instantiate(e.dataset) for e in cfg.data.train])
    write({"stage": "render", "seconds": time.perf_counter() - start})
    for stage in STAGES:
        cfg = _compose([*base, f"schedule.until={stage}"])
        _, _, figures = prepare_chain(validate(cfg), progress=False)
        fig = figures[stage]
        write({"stage": stage, "steps": int(cfg.schedule.stages[stage].steps), "seconds": fig["seconds"],
               "steps_per_second": fig["steps_per_second"]})


def part_compile(check: Check, dims: Dims, rates: dict[tuple, float]) -> None:
    """Each compiled stage in a subprocess that the budget stops (a compilation cannot be cut short
    from inside), so the check ends on time whatever the compiler takes."""
    problem = execution.compile_problem(check.device.type)
    if problem:
        check.add("7 torch.compile", "flow1, dm1", f"refused: {problem}")
        return
    for kind in ("flow1", "dm1"):
        label = f"{kind}, bf16-mixed, channels-last, compiled"
        if check.left() < 60:
            check.add("7 torch.compile", label, f"skipped: {check.left():.0f} s of the budget left")
            continue
        cmd = [sys.executable, "-m", "demon_lab.device_check", "--compile-worker", kind]
        timeout = check.left() - 10
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            check.add("7 torch.compile", label, f"stopped at the budget ({timeout:.0f} s): compilation not finished")
            continue
        if proc.returncode != 0:
            error = (proc.stderr.strip().splitlines() or ["?"])[-1][:200]
            check.add("7 torch.compile", label, f"failed: {error}")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        bare = rates.get((kind, "bf16-mixed", True))
        vs = f"; {r['steps_per_second'] / bare:.2f}x the uncompiled step" if bare else ""
        check.add("7 torch.compile", label, _fmt_rate(r),
                  f"compilation and 4 warm-up steps: {r['first_steps_s']:.0f} s{vs}")


def compile_worker(kind: str) -> None:
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    r = step_rate(device, PAPER, kind, "bf16-mixed", True, compile=True)
    print(json.dumps(r), flush=True)


def machine(device: torch.device) -> str:
    if device.type == "cuda":
        p = torch.cuda.get_device_properties(device)
        gpu = f"{p.name}, {p.total_memory / 2**30:.0f} GiB, {p.multi_processor_count} SMs, CUDA {torch.version.cuda}"
    else:
        gpu = f"no GPU ({device.type})"
    return f"{gpu}; torch {torch.__version__}; {os.cpu_count()} CPU cores"


def report(check: Check, command: str) -> str:
    lines = [
        "# demon_lab device check",
        "",
        f"`{command}` — {dt.date.today().isoformat()}, {machine(check.device)}; "
        f"{time.perf_counter() - check.start:.0f} s of a {check.budget:.0f} s budget"
        f"{' (dry run: toy sizes, not a measurement)' if check.dry_run else ''}.",
        "",
        "Parts: 1 the device-parametrised tests; 2 full-chain inference at "
        f"{'256x192' if not check.dry_run else '64x64'} (3 iterations + refinement); 3 the bare training step of each "
        "stage at scale=paper (full width, batch 32; iterative 8 new + 24 queued), PyTorch's default TF32 settings; "
        "4 DeMoN's HDF5 training path; 5 the job's loop; 6 the cpu profile's six stages on this device; "
        "7 torch.compile.",
        "",
        "| part | configuration | result | note |",
        "|---|---|---|---|",
        *[f"| {a} | {b} | {c} | {d} |" for a, b, c, d in check.rows],
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="scripts/device_check.sh", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dry-run", action="store_true", help="every part at toy sizes on any device (CI)")
    parser.add_argument("--budget", type=float, default=420.0, help="seconds for the whole check (default 420)")
    parser.add_argument("--out", type=Path, default=Path("reports/device_check.md"))
    parser.add_argument("--profile-worker", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--scale", default="cpu", help=argparse.SUPPRESS)
    parser.add_argument("--cache", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--compile-worker", choices=STAGES, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.profile_worker is not None:
        profile_worker(args.profile_worker, args.scale, args.cache)
        return 0
    if args.compile_worker is not None:
        compile_worker(args.compile_worker)
        return 0
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.type != "cuda" and not args.dry_run:
        print("[device_check] no CUDA device here: run it on a GPU, or pass --dry-run", file=sys.stderr)
        return 2
    dims = DRY if args.dry_run else PAPER
    check = Check(args.budget, args.dry_run, device)
    print(f"[device_check] {machine(device)}; budget {args.budget:.0f} s", flush=True)
    rates: dict[tuple, float] = {}
    check.part("1 tests", 30, lambda: part_tests(check))
    check.part("2 inference", 20, lambda: part_inference(check, dims))
    check.part("3 train steps", 60, lambda: part_steps(check, dims, rates))
    check.part("4 DeMoN HDF5 data", 30, lambda: part_data(check, dims, rates))
    with contextlib.suppress(Exception):
        import hydra  # noqa: F401  (parts 5 and 6 compose the job's config)
    if "hydra" not in sys.modules:
        for part in ("5 job loop", "6 cpu profile"):
            check.add(part, "all", "skipped: hydra-core and omegaconf are not importable (carry their wheels: "
                                   "docs/running.md)")
    else:
        check.part("5 job loop", 60, lambda: part_loop(check, dims, rates))
        reserve = 0 if check.dry_run else 100  # part 7: one compiled stage at least
        check.part("6 cpu profile", 60,
                   lambda: part_cpu_profile(check, dims, min(240.0, max(30.0, check.left() - reserve))))
    if check.dry_run:
        check.add("7 torch.compile", "flow1, dm1", "not run in a dry run (tests/test_execution.py compiles a "
                                                    "smoke stage)")
    else:
        check.part("7 torch.compile", 60, lambda: part_compile(check, dims, rates))
    command = "scripts/device_check.sh" + (" --dry-run" if args.dry_run else "") + (
        f" --budget {args.budget:.0f}" if args.budget != 420 else "")
    text = report(check, command)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"[device_check] wrote {args.out}", flush=True)
    return 1 if any(r[2].startswith("failed") for r in check.rows) else 0

