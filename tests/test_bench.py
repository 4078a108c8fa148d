"""The benchmark command writes its table and keeps the other sections of the report."""

from __future__ import annotations

import re

from demon_lab import bench


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


def test_job_rates_reads_each_stage_rate_from_the_job_it_runs():
    command = ("python", "-m", "demon_lab", "scale=smoke", "schedule.until=dm1", "iterations=0",
               "scale.steps.flow1=12", "scale.steps.dm1=6")
    rates = bench.job_rates(command, ("flow1", "dm1"))
    assert set(rates) == {"flow1", "dm1"} and all(r > 0 for r in rates.values())
