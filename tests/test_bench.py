"""The benchmark command writes its table and keeps the other sections of the report."""

from __future__ import annotations

import re

import pytest
import torch

from demon_lab.core import geometry as geo
from demon_lab.data import throughput
from demon_lab.tools import bench


def test_write_section_replaces_only_its_own_section(tmp_path):
    path = tmp_path / "bench.md"
    bench.write_section(path, "geometry", "## geometry\nold")
    bench.write_section(path, "data", "## data\nkept")
    bench.write_section(path, "geometry", "## geometry\nnew")
    text = path.read_text()
    assert "new" in text and "old" not in text and "kept" in text
    assert text.count("<!-- bench:geometry -->") == 1


def test_geometry_benchmark_reports_every_op_with_numbers(tmp_path):
    out = tmp_path / "bench.md"
    assert bench.main(["geometry", "--repeats", "1", "--out", str(out)]) == 0
    text = out.read_text()
    for op in ("warp_image", "flow_from_depth_motion", "depth_from_flow_motion", "normals_from_depth"):
        row = re.search(rf"^\| {op} \| ([0-9.]+) \| ([0-9.]+) \|", text, re.M)
        assert row and float(row.group(1)) > 0 and float(row.group(2)) > 0, op
    assert re.search(r"\| warp_image .*\| [0-9.]+x cv2\.remap", text)
    assert re.search(r"angle_axis_to_matrix \(B=8\) .*x cv2\.Rodrigues", text)


@pytest.mark.slow
def test_job_rates_reads_each_stage_rate_from_the_job_it_runs():
    command = ("python", "-m", "demon_lab", "scale=smoke", "schedule.until=dm1", "iterations=0",
               "scale.steps.flow1=12", "scale.steps.dm1=6")
    rates = bench.job_rates(command, ("flow1", "dm1"))
    assert set(rates) == {"flow1", "dm1"} and all(r > 0 for r in rates.values())


def test_demon_h5_rates_serve_training_draws_per_worker_count(tmp_path):
    from demon_lab.data.datasets import DemonH5Dataset

    path = tmp_path / "layout.h5"
    throughput.write_demon_layout_file(path, 3, (64, 96))
    ds = DemonH5Dataset(path, test_phase=False, size=(64, 96))
    assert len(ds) == 6  # 3 scenes, both orders of their pair
    sample = ds.load(0)
    assert sample["image1"].shape == (3, 64, 96) and torch.isfinite(sample["motion"]).all()
    assert float(geo.valid_depth(sample["inv_depth"]).float().mean()) > 0.5
    rates = throughput.demon_h5_rates(path, [0, 1], batch_size=2, batches=2, size=(64, 96))
    assert set(rates) == {0, 1} and all(r > 0 for r in rates.values())
    assert throughput.worker_counts()[0] == 0


def test_demon_h5_pair_times_a_draw_and_an_evaluation_sample(tmp_path):
    path = tmp_path / "layout.h5"
    throughput.write_demon_layout_file(path, 2, (64, 96))
    draw, evaluation = throughput.demon_h5_pair_ms(path, pairs=4, size=(64, 96))
    assert draw > 0 and evaluation > 0
