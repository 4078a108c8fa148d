"""The benchmark command writes its table and keeps the other sections of the report."""

from __future__ import annotations

import re

import pytest
import torch
from conftest import table_alignment, table_rows

from demon_lab.core import geometry as geo
from demon_lab.data import throughput
from demon_lab.tools import bench, bench_train
from tests.jobs import settings


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
    rows = {r[0]: r[1:] for r in table_rows(text)}
    assert rows["op"] == ["ms / call", "Mpixel/s", "vs OpenCV (same run)"]
    assert table_alignment(text) == [["l", "r", "r", "l"]]
    for op in ("warp_image", "flow_from_depth_motion", "depth_from_flow_motion", "normals_from_depth"):
        assert float(rows[op][0]) > 0 and float(rows[op][1]) > 0, op
    assert re.fullmatch(r"[0-9.]+x cv2\.remap \([0-9.]+ ms\)", rows["warp_image"][2])
    assert re.fullmatch(r"[0-9.]+x cv2\.Rodrigues loop \([0-9.]+ ms\)", rows["angle_axis_to_matrix (B=8)"][2])
    assert rows["angle_axis_to_matrix (B=8)"][1] == ""


def test_the_benchmark_tables_hold_their_cells_as_the_hand_written_tables_did():
    """The train section's design table and the data section's HDF5 table from known rates: the cells
    and the column alignment (numbers right, the yes/no column centred)."""
    from demon_lab.tools import bench_data

    bare = {"profile": {"flow1": {"rate": 20.0, "flops": 50e9, "top": [("aten::conv", 0.4), ("aten::mul", 0.1)]},
                        "dm1": {"rate": 10.0, "flops": 25e9, "top": []}}}
    parts = {"trainingepochloop.train_dataloader_next": 0.05, "callback.StageValidation.on_train_batch_end": 0.02,
             "outside": 0.01, "callback.KeepBest.on_train_batch_end": 0.0}
    loop = {"profile": {"flow1": {"rate": 18.0, "stage_rate": 16.5, "parts": parts}}}
    table = bench_train.design_table(bare, loop, peak=500e9)
    assert table_rows(table) == [
        ["design", "stage", "bare step, steps/s", "of matmul", "job's loop, steps/s", "loop / step",
         "whole stage, steps/s", "the step's largest self times", "the loop beside its batches"],
        ["profile", "flow1", "20.00", "10.0%", "18.00", "90.0%", "16.50", "aten::conv 40%, aten::mul 10%",
         "loader 5.0%, StageValidation 2.0%, rest 1.0%"],
        ["profile", "dm1", "10.00", "5.0%", "", "", "", "", ""]]
    assert table_alignment(table) == [["l", "l", "r", "r", "r", "r", "r", "l", "l"]]
    h5 = bench_data.h5_table({0: 320.0, 2: 1280.0}, batch=32, step=5.0)
    assert table_rows(h5) == [["loader workers", "samples/s", "batches/s", "steps/s fed with 4x headroom",
                               "4x the step"],
                              ["0", "320", "10.00", "2.50", "no"], ["2", "1280", "40.00", "10.00", "yes"]]
    assert table_alignment(h5) == [["r", "r", "r", "r", "c"]]  # (was |---:|---:|---:|---:|:---:|)


def test_loop_rates_read_each_stages_rate_and_loop_parts_from_the_job_it_runs(monkeypatch):
    """Each stage's loop rate (``stage/NAME/loop_steps_per_second``, else its whole rate) and whole rate as the
    job's run logged them, and the parts of its loop beside its batches as shares of the stage's time (the job
    here: a stand-in that logs known figures)."""
    import subprocess

    from demon_lab.pipeline.tracking import Tracker

    real = subprocess.run
    commands = []

    def job(cmd, **kwargs):
        if "demon_lab" not in cmd:  # (what else runs a process meanwhile: MLflow's git lookups)
            return real(cmd, **kwargs)
        commands.append(cmd)
        uri = next(a.split("=", 1)[1] for a in cmd if a.startswith("tracking.uri="))
        artifacts = next(a.split("=", 1)[1] for a in cmd if a.startswith("tracking.artifact_dir="))
        tracker = Tracker(uri, "default", artifacts)
        run = tracker.start("job", {})
        tracker.log_metrics(run, {"stage/flow1/steps_per_second": 3.5, "stage/flow1/seconds": 4.0,
                                  "stage/flow1/loop_steps_per_second": 3.75,
                                  "stage/flow1/profile/trainingepochloop.train_dataloader_next_seconds": 0.4,
                                  "stage/flow1/profile/run_training_batch_seconds": 3.0,
                                  "stage/flow1/profile/outside_seconds": 0.2,
                                  "stage/dm1/steps_per_second": 2.25, "stage/dm1/seconds": 2.0})
        tracker.finish(run, "FINISHED")
        return subprocess.CompletedProcess(cmd, 0)

    monkeypatch.setattr(subprocess, "run", job)
    rates = bench_train.loop_rates(("design=learned",))
    assert rates == {"flow1": {"rate": 3.75, "stage_rate": 3.5,
                               "parts": {"trainingepochloop.train_dataloader_next": 0.1, "outside": 0.05}},
                     "dm1": {"rate": 2.25, "stage_rate": 2.25, "parts": {}}}
    (cmd,) = commands
    assert "design=learned" in cmd and "trainer.profile=true" in cmd and "scale.steps.flow1=1000" in cmd


def test_a_designs_bare_steps_are_its_stages_as_the_job_builds_them(tmp_path):
    """bare_steps times every scheduled stage of a design (here the profile at the smoke scale, with its
    priors in the batch) and names its largest costs; the profile's flow1 step reads the batch's priors."""
    from demon_lab.tools.bench_train import bare_steps, training_batch

    overrides = ["scale=smoke", f"cache_dir={tmp_path}", "model.flow1_prior=dis", "model.dm1_prior=ransac_prior"]
    steps = bare_steps(overrides, repeats=1, peak=1e12)
    assert list(steps) == ["flow1", "dm1", "flow2", "dm2", "iterative", "refine"]
    for figures in steps.values():
        assert figures["rate"] > 0 and figures["flops"] > 0
        assert len(figures["top"]) == bench_train.TOP and all(0 < share <= 1 for _, share in figures["top"])
        assert sum(share for _, share in figures["top"]) <= 1
    cfg = bench_train._compose(overrides)
    from demon_lab.pipeline.stages.schedule import build_chain

    batch = training_batch(cfg, build_chain(settings(cfg)), 2)
    assert batch["prior_flow"].shape == (2, 2, 16, 16) and batch["prior_motion"].shape == (2, 6)


def _clock(monkeypatch):
    """time.perf_counter in the throughput module as a clock that moves 1 s per reading."""
    ticks = iter(range(1000))
    monkeypatch.setattr(throughput.time, "perf_counter", lambda: float(next(ticks)))


def test_demon_h5_rates_serve_training_draws_per_worker_count(tmp_path, monkeypatch):
    from demon_lab.data.datasets import DemonH5Dataset

    path = tmp_path / "layout.h5"
    throughput.write_demon_layout_file(path, 3, (64, 96))
    ds = DemonH5Dataset(path, test_phase=False, size=(64, 96))
    assert len(ds) == 6  # 3 scenes, both orders of their pair
    sample = ds.load(0)
    assert sample["image1"].shape == (3, 64, 96) and torch.isfinite(sample["motion"]).all()
    assert float(geo.valid_depth(sample["inv_depth"]).float().mean()) > 0.5
    _clock(monkeypatch)  # 1 s per timed block: a rate is the samples the block served
    rates = throughput.demon_h5_rates(path, [0, 1], batch_size=2, batches=2, size=(64, 96))
    assert rates == {0: 2 * 2, 1: 2 * 4}  # timed batches: max(batches, 4 x workers), after the warm ones
    assert throughput.worker_counts()[0] == 0


def test_demon_h5_pair_times_a_draw_and_an_evaluation_sample(tmp_path, monkeypatch):
    path = tmp_path / "layout.h5"
    throughput.write_demon_layout_file(path, 2, (64, 96))
    _clock(monkeypatch)  # 1 s per timed block of 4 pairs
    draw, evaluation = throughput.demon_h5_pair_ms(path, pairs=4, size=(64, 96))
    assert (draw, evaluation) == (250.0, 250.0)


def test_a_stages_loop_rate_leaves_out_what_the_stage_does_once():
    """loop_rate: batches per second from the end of the first tenth of batches to the last, so a slow
    start (the trainer's set-up, the first batch) does not count; too few batches give no rate."""
    from demon_lab.pipeline.stages.training import loop_rate

    ends = [10.0 + 0.5 * k for k in range(40)]  # the first batch ended 10 s after the stage began
    assert loop_rate(ends) == pytest.approx(2.0)
    ends[-1] += 18.0  # a slow last stretch (scoring, a checkpoint) is the loop's
    assert loop_rate(ends) == pytest.approx(1.0)
    assert loop_rate(ends[:9]) is None
