"""The dashboard as a user sees it: MLflow's UI on 127.0.0.1 over a store filled by a smoke sweep,
loaded in headless Chromium (Debian's ``chromium``; ``.ci/run`` installs it)."""

from __future__ import annotations

import os
import re
import struct
import zlib

import pytest

from demon_lab.reporting import dashboard
from tests.conftest import free_port
from tests.jobs import cli, client, smoke_overrides

pytestmark = pytest.mark.dashboard
PANEL = 'data-component-id="mlflow.assistant.chat_panel'
"""In the DOM while MLflow's assistant side panel is open (its chat panel's components)."""


@pytest.fixture(scope="module")
def browser():
    found = dashboard.find_browser()
    if found is None:
        if os.environ.get("CI"):
            pytest.fail("CI must install chromium (.ci/run) for the dashboard test")
        pytest.skip("no Chromium browser here (apt-get install chromium)")
    return found


def _png_rows(path) -> tuple[int, int, list[bytes]]:
    """Width, height and the de-filtered RGB(A) rows of a PNG (enough to tell a page from a blank)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        chunk = data[pos + 8:pos + 8 + length]
        header = chunk if kind == b"IHDR" else header
        idat += chunk if kind == b"IDAT" else b""
        pos += 12 + length
    width, height, depth, colour = struct.unpack(">IIBB", header[:10])
    assert depth == 8 and colour in (2, 6)
    bpp = 3 if colour == 2 else 4
    raw, stride, rows, prev = zlib.decompress(idat), width * bpp, [], bytearray(width * bpp)
    for y in range(height):
        kind, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for x in range(stride):
            a = line[x - bpp] if x >= bpp else 0
            b, c = prev[x], prev[x - bpp] if x >= bpp else 0
            if kind == 1:
                line[x] = (line[x] + a) & 255
            elif kind == 2:
                line[x] = (line[x] + b) & 255
            elif kind == 3:
                line[x] = (line[x] + (a + b) // 2) & 255
            elif kind == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                line[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    return width, height, rows


@pytest.mark.slow
def test_the_dashboard_shows_the_runs_of_a_sweep(tmp_path, browser):
    result = cli("-m", *smoke_overrides(tmp_path), "seed=0,1", "schedule.until=flow1", "iterations=0",
                 "eval.max_samples=1", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    store = client(tmp_path)
    experiment = store.get_experiment_by_name("default")
    runs = store.search_runs([experiment.experiment_id])
    (parent,) = [r for r in runs if r.data.tags.get("demon_lab.kind") == "sweep"]
    jobs = {r.info.run_id: r for r in runs if "demon_lab.run_key" in r.data.tags}
    assert len(jobs) == 2

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    with dashboard.serve(uri, free_port(), tmp_path / "served-artifacts") as server:
        assert server.startswith("http://127.0.0.1:")
        # the REST API the page itself calls lists the sweep: its parent and both jobs, FINISHED
        listed = dashboard.api(server, "runs/search", {"experiment_ids": [experiment.experiment_id]})["runs"]
        by_id = {r["info"]["run_id"]: r for r in listed}
        assert set(jobs) | {parent.info.run_id} <= set(by_id)
        for run_id, job in jobs.items():
            info, data = by_id[run_id]["info"], by_id[run_id]["data"]
            assert info["status"] == "FINISHED" and info["run_name"] == job.info.run_name
            tags = {t["key"]: t["value"] for t in data["tags"]}
            assert tags["mlflow.parentRunId"] == parent.info.run_id
            metrics = {m["key"]: m["value"] for m in data["metrics"]}
            assert metrics and metrics == pytest.approx(job.data.metrics)

        # the runs page, rendered: the sweep's parent row and the run count, and a non-blank picture
        png = tmp_path / "runs.png"
        dom = dashboard.capture(dashboard.runs_url(server, experiment.experiment_id), png, browser=browser,
                                until=dashboard.RUNS_RENDERED)
        assert parent.info.run_name in dom
        assert "<strong>" + str(len(runs)) + "</strong> matching runs" in dom
        width, height, rows = _png_rows(png)
        assert (width, height) == (1600, 900)
        assert len(set(rows)) > 100  # many distinct pixel rows: a rendered table, not an empty page

        # the dashboard's view of the sweep: the job runs with test metrics as columns (names and
        # values in the table), and MLflow's assistant panel closed (it opens on a first visit)
        columns = sorted(k for k in next(iter(jobs.values())).data.metrics if k.startswith("test/"))[:2]
        view = dashboard.share_view(server, experiment.experiment_id, dashboard.view_state(columns))
        dom = dashboard.capture(dashboard.runs_url(server, experiment.experiment_id, view), png, browser=browser,
                                until=dashboard.RUNS_RENDERED)
        assert "<strong>" + str(len(jobs)) + "</strong> matching runs" in dom  # the jobs only
        for key in columns:
            assert key in dom  # the column's header
            assert any(repr(job.data.metrics[key]) in dom for job in jobs.values())  # the values in its cells
        assert all(job.info.run_name in dom for job in jobs.values()) and parent.info.run_name not in dom
        assert PANEL not in dom and "assistant-fab-label" in dom  # the panel is closed, its button there
        width, height, rows = _png_rows(png)
        assert (width, height) == (1600, 900) and len(set(rows)) > 100
        opened = dashboard.capture(dashboard.runs_url(server, experiment.experiment_id, view), browser=browser,
                                   storage={}, until=dashboard.RUNS_RENDERED)
        assert PANEL in opened  # the marker is real: a first visit without the stored state shows the panel

        # a study report on the sweep's parent run (what the sweep callback logs under report/): linked and shown
        assert dashboard.study_report(server, experiment.experiment_id) is None
        store.log_text(parent.info.run_id, "# A study\n\n| row | L1-inv |\n|---|---|\n| row a | 0.123 ± 0.045 |\n",
                       "report/study.md")
        found = dashboard.study_report(server, experiment.experiment_id)
        assert found == (parent.info.run_id, "report/study.md")
        page = dashboard.capture(dashboard.run_url(server, experiment.experiment_id, *found), browser=browser,
                                 until="document.body.innerText.includes('row a')")
        assert re.search(r'role="cell"[^>]*><span[^>]*>0\.123 ± 0\.045</span>', page)  # the Markdown table, rendered
        assert PANEL not in page

        # each job's own page names the job and shows its test metrics
        for run_id, job in jobs.items():
            page = dashboard.capture(dashboard.run_url(server, experiment.experiment_id, run_id), browser=browser)
            assert job.info.run_name in page
            assert any(key in page for key in job.data.metrics if key.startswith("test/"))


def test_dashboard_command_refuses_a_missing_store(tmp_path, capsys):
    assert dashboard.main(["--tracking-uri", f"sqlite:///{tmp_path}/none.db"]) == 2
    assert "no such store" in capsys.readouterr().err


def test_the_view_of_the_runs_names_its_columns_the_ui_way():
    """MLflow's UI keys a runs-table column as metrics.`NAME` (params.`NAME`, tags.`NAME`); sorted by a
    metric, it lists the matching runs themselves rather than nesting them under their parents."""
    state = dashboard.view_state(["test/set/l1_inv", "params.seed", "tags.demon_lab.row"])
    assert state["selectedColumns"] == ["metrics.`test/set/l1_inv`", "params.`seed`", "tags.`demon_lab.row`"]
    assert state["orderByKey"] == "metrics.`test/set/l1_inv`" and state["orderByAsc"] is True
    assert state["searchFilter"] == dashboard.JOBS_FILTER and set(state["columnWidths"]) == set(state["columnOrder"])
    assert "orderByKey" not in dashboard.view_state(["params.seed"])
    url = dashboard.runs_url("http://127.0.0.1:5000/", "3", "demon_lab-abc")
    assert url == ("http://127.0.0.1:5000/#/experiments/3/runs?viewStateShareKey=demon_lab-abc"
                   "&workflowType=machine_learning")
