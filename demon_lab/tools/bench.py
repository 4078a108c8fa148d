"""Benchmarks: ``python -m demon_lab.bench SECTION [...]`` writes a table per section to
``reports/bench.md`` (other sections of the file are kept).

Absolute times vary between machines, so every section also reports ratios measured in the same
run (a geometry op against its OpenCV counterpart). Sections:

* ``geometry``: the geometry layers at 256x192, batch 8, float32, on the CPU.
* ``data``: synthetic pairs per second, rendered (one core, worker processes) and from the cache; DeMoN's
  HDF5 files decoded on the training path per loader worker count, at 256x192 and batch 32.
* ``train``: each stage of each design at the cpu scale, its bare step against the job's own loop, with
  the largest costs of each (:mod:`demon_lab.tools.bench_train`).
"""

from __future__ import annotations

import argparse
import datetime as dt
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from demon_lab.core import geometry as geo
from demon_lab.core import warping
from demon_lab.reporting.tables import markdown_table
from demon_lab.tools.bench_data import bench_data
from demon_lab.tools.bench_train import bench_train
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

