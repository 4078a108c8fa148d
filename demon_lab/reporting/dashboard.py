"""MLflow's dashboard on demon_lab's runs: ``python -m demon_lab.dashboard``.

Serves the tracking store with MLflow's own UI on 127.0.0.1 and prints, per experiment, the link to
its runs in the machine-learning view (MLflow 3 opens in its GenAI view, which hides training
runs), showing the job runs (not the sweeps' parent runs nor the stage runs) with the key test
metrics as columns (``--columns``), and the link to the study report that a sweep logged on its
parent run (``report/``, see ``python -m demon_lab.report``). With ``--screenshot PNG`` it instead
loads that runs view (or, with ``--page report``, that report) once in headless Chromium, saves
what a user would see, and stops the server::

    python -m demon_lab.dashboard                               # serve until Ctrl-C
    python -m demon_lab.dashboard --experiment iterations --screenshot docs/dashboard.png

How MLflow 3.17's UI is told what to show (its source: ``mlflow/server/js/src/`` in mlflow/mlflow;
checked against MLflow 3.17.2's build):

- columns, filter and order of the runs table: a *shared view*, what the UI's "share view" does:
  the experiment tag ``mlflow.sharedViewState.<key>`` holds the view state as JSON (search facets
  such as ``searchFilter`` and ``orderByKey``, UI state such as ``selectedColumns`` and
  ``columnWidths``; column keys read ``metrics.`NAME```) and the URL parameter
  ``viewStateShareKey=<key>`` applies it (``experiment-tracking/components/experiment-page/``:
  ``hooks/useSharedExperimentViewState.ts``, ``models/ExperimentPageUIState.tsx``). The dashboard
  writes that tag into each experiment it links (the same key for the same view, so once).
- the assistant side panel: on a local server the UI opens it on the first visit and remembers
  that in the browser's local storage (``assistant/AssistantFloatingButton.tsx``:
  ``mlflow.assistant.fab.autoOpenedOnFirstLoad_v1``; ``assistant/AssistantContext.tsx``:
  ``mlflow.assistant.panelOpen_v1``). A URL cannot set those, so the screenshot drives Chromium
  through its DevTools protocol (``--remote-debugging-pipe``: no port, no extra package) and
  stores both before the page's scripts run. In one's own browser, closing the panel once is
  remembered the same way.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import hashlib
import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from demon_lab.pipeline.tracking import LocalServer, TrackingError

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# Headless Chromium as a test harness: no sandbox (containers run as root), no GPU, and nothing
# that reaches the network besides the page itself.
BROWSER_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync")
KEY_METRICS = ("tags.demon_lab.seed", "tags.demon_lab.iterations", "test/synthetic_sun3d/l1_inv",
               "test/synthetic_sun3d/rot_deg", "test/synthetic_sun3d/tran_deg", "test/synthetic_sun3d/epe")
"""The default ``--columns``: which job a row is (its seed and number of passes; add
``tags.demon_lab.method`` or ``tags.demon_lab.oracle`` for the baselines and oracle studies) and
the summary test metrics of the synthetic SUN3D-like test set."""
JOBS_FILTER = "tags.`demon_lab.run_key` LIKE '%'"
"""MLflow search syntax for the job runs: the sweeps' parent runs and the stage runs have no run key."""
SHARED_VIEW_TAG = "mlflow.sharedViewState."
"""MLflow UI's EXPERIMENT_PAGE_VIEW_STATE_SHARE_TAG_PREFIX (experiment-tracking/constants.ts)."""
ASSISTANT_CLOSED = {"mlflow.assistant.fab.autoOpenedOnFirstLoad_v1": "true", "mlflow.assistant.panelOpen_v1": "false"}
"""Local storage of MLflow's UI (its useLocalStorage hook stores KEY_v<version> as JSON): the assistant panel
was opened once already (so it is not opened on this first visit) and is closed."""


def runs_url(server: str, experiment_id: str, view: str | None = None) -> str:
    """The runs table of an experiment, in the machine-learning view (with a shared view's key:
    that view's columns and filter, see :func:`share_view`)."""
    query = {**({"viewStateShareKey": view} if view else {}), "workflowType": "machine_learning"}
    return f"{server.rstrip('/')}/#/experiments/{experiment_id}/runs?{urllib.parse.urlencode(query)}"


def run_url(server: str, experiment_id: str, run_id: str, artifact: str | None = None) -> str:
    """A run's page (with ``artifact``, its artifacts tab showing that file)."""
    tab = f"/artifacts/{artifact}" if artifact else ""
    return f"{server.rstrip('/')}/#/experiments/{experiment_id}/runs/{run_id}{tab}?workflowType=machine_learning"


def column_key(name: str) -> str:
    """The UI's key of a runs-table column: ``metrics.`NAME```; ``params.NAME`` and ``tags.NAME``
    name a param or tag column, ``metrics.NAME`` a metric spelled with its prefix."""
    kind, _, rest = name.partition(".")
    if kind in ("metrics", "params", "tags", "attributes") and rest:
        return f"{kind}.`{rest.strip('`')}`"
    return f"metrics.`{name}`"


def view_state(columns: Sequence[str], search_filter: str = JOBS_FILTER) -> dict[str, Any]:
    """A shared view of the runs table: the runs matching ``search_filter`` with these columns
    (wide enough for their names), sorted by the first metric column, lowest first. Sorted by
    anything but the start time, the UI lists the matching runs themselves, not nested under
    their parent runs (it fetches missing parents only for that order)."""
    keys = [column_key(c) for c in columns]
    state: dict[str, Any] = {"searchFilter": search_filter, "selectedColumns": keys, "columnOrder": keys,
                             "columnWidths": {k: 7 * len(c.split(".", 1)[1] if c.startswith(("tags.", "params."))
                                                           else c) + 44 for k, c in zip(keys, columns)}}
    metric = next((k for k in keys if k.startswith("metrics.")), None)
    if metric is not None:
        state |= {"orderByKey": metric, "orderByAsc": True}
    return state


def share_view(server: str, experiment_id: str, state: Mapping[str, Any]) -> str:
    """Stores ``state`` as a shared view of the experiment (the experiment tag the UI's "share view"
    writes) and returns its key for :func:`runs_url`; the key is a hash of the state, so the same
    view is the same tag."""
    text = json.dumps(state, sort_keys=True)
    key = "demon_lab-" + hashlib.sha256(text.encode()).hexdigest()[:12]
    api(server, "experiments/set-experiment-tag", {"experiment_id": experiment_id, "key": SHARED_VIEW_TAG + key,
                                                   "value": text})
    return key


def study_report(server: str, experiment_id: str) -> tuple[str, str] | None:
    """(run id, artifact path) of the study report (``report/NAME.md``) on the experiment's newest
    sweep parent run that has one, or None."""
    found = api(server, "runs/search", {"experiment_ids": [experiment_id], "max_results": 50,
                                        "filter": "tags.`demon_lab.kind` = 'sweep'",
                                        "order_by": ["attributes.start_time DESC"]}).get("runs", [])
    for run in found:
        run_id = run["info"]["run_id"]
        try:
            files = api(server, f"artifacts/list?{urllib.parse.urlencode({'run_id': run_id, 'path': 'report'})}")
        except TrackingError:  # artifacts this server cannot read (another machine's folder): no link
            continue
        reports = sorted(f["path"] for f in files.get("files", []) if f["path"].endswith(".md"))
        if reports:
            return run_id, reports[0]
    return None


def find_browser() -> str | None:
    """A Chromium-family browser on PATH (``$DEMON_LAB_BROWSER`` first), or None."""
    for name in (os.environ.get("DEMON_LAB_BROWSER"), *BROWSERS):
        if name and (path := shutil.which(name)):
            return path
    return None


# Runs a command with two inherited fds moved to 3 and 4, where --remote-debugging-pipe expects them
# (via fds >= 10 first, so neither end overwrites the other; dup2 makes them inheritable).
_ON_FDS_3_AND_4 = ("import fcntl, os, sys; fds = [int(fd) for fd in sys.argv[1:3]]; "
                   "a, b = (fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in fds); os.dup2(a, 3); os.dup2(b, 4); "
                   "[os.close(fd) for fd in (a, b, *fds) if fd not in (3, 4)]; os.execv(sys.argv[3], sys.argv[3:])")


class DevTools:
    """Chromium driven through its DevTools protocol over ``--remote-debugging-pipe``: commands go
    to the browser's fd 3 and replies come from its fd 4, JSON messages ending in NUL (no port, no
    websocket client needed)."""

    def __init__(self, browser: str, flags: Sequence[str]):
        commands, self._to_browser = os.pipe()
        self._from_browser, replies = os.pipe()
        self._log = tempfile.TemporaryFile()
        self.name = Path(browser).name
        self.process = subprocess.Popen([sys.executable, "-c", _ON_FDS_3_AND_4, str(commands), str(replies), browser,
                                         *flags, "--remote-debugging-pipe"], pass_fds=(commands, replies),
                                        stdin=subprocess.DEVNULL, stdout=self._log, stderr=self._log)
        os.close(commands)
        os.close(replies)
        self._buffer, self._id = b"", 0
        self.events: list[dict[str, Any]] = []

    def send(self, method: str, params: Mapping[str, Any] | None = None, session: str | None = None,
             timeout: float = 60.0) -> dict[str, Any]:
        self._id += 1
        message = {"id": self._id, "method": method, "params": dict(params or {}),
                   **({"sessionId": session} if session else {})}
        data = json.dumps(message).encode() + b"\0"
        while data:
            data = data[os.write(self._to_browser, data):]
        deadline = time.monotonic() + timeout
        while True:
            reply = self._read(deadline, method)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise TrackingError(f"{self.name}: {method}: {reply['error'].get('message', reply['error'])}")
                return reply.get("result", {})
            self.events.append(reply)

    def _read(self, deadline: float, method: str) -> dict[str, Any]:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TrackingError(f"{self.name}: no answer to {method} within the time limit")
            if select.select([self._from_browser], [], [], left)[0]:
                chunk = os.read(self._from_browser, 1 << 20)
                if not chunk:
                    raise TrackingError(f"{self.name} exited {self.process.poll()}: {self.log()[-300:]}")
                self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(line)

    def evaluate(self, expression: str, session: str) -> Any:
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True}, session)
        return result.get("result", {}).get("value")

    def log(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace").strip()

    def close(self) -> None:
        with contextlib.suppress(TrackingError, OSError):
            self.send("Browser.close", timeout=10)
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for fd in (self._to_browser, self._from_browser):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._log.close()


def _storage_script(storage: Mapping[str, str]) -> str:
    """JavaScript that puts ``storage`` into the page's local storage (pages without one: skipped)."""
    sets = "".join(f"localStorage.setItem({json.dumps(k)}, {json.dumps(v)});" for k, v in storage.items())
    return f"try {{ {sets} }} catch (e) {{}}"


def capture(url: str, screenshot: Path | None = None, window: tuple[int, int] = (1600, 900),
            budget_ms: int = 30000, browser: str | None = None, storage: Mapping[str, str] | None = None,
            until: str | None = None) -> str:
    """Load ``url`` in headless Chromium with ``storage`` in its local storage before the page's
    scripts run (default: MLflow's assistant panel closed), wait until the JavaScript condition
    ``until`` holds (if given) and the page has stopped changing (at most ``budget_ms``), and
    return the rendered DOM; with ``screenshot``, also save a PNG of the window."""
    browser = browser or find_browser()
    if browser is None:
        raise TrackingError(f"no Chromium browser found (looked for {', '.join(BROWSERS)}); install Debian's "
                            f"'chromium' or set DEMON_LAB_BROWSER")
    storage = ASSISTANT_CLOSED if storage is None else storage
    with tempfile.TemporaryDirectory(prefix="demon_lab_browser_") as profile:
        tools = DevTools(browser, [*BROWSER_FLAGS, f"--user-data-dir={profile}",
                                   f"--window-size={window[0]},{window[1]}", "about:blank"])
        try:
            target = tools.send("Target.createTarget", {"url": "about:blank"})["targetId"]
            session = tools.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            tools.send("Emulation.setDeviceMetricsOverride", {"width": window[0], "height": window[1],
                                                              "deviceScaleFactor": 1, "mobile": False}, session)
            tools.send("Page.enable", session=session)  # (scripts for new documents need the Page domain)
            if storage:
                tools.send("Page.addScriptToEvaluateOnNewDocument", {"source": _storage_script(storage)}, session)
            tools.send("Page.navigate", {"url": url}, session)
            _settle(tools, session, budget_ms / 1000, until)
            dom = tools.evaluate("document.documentElement.outerHTML", session) or ""
            if screenshot is not None:
                screenshot.parent.mkdir(parents=True, exist_ok=True)
                shot = tools.send("Page.captureScreenshot", {"format": "png"}, session)
                screenshot.write_bytes(base64.b64decode(shot["data"]))
        finally:
            tools.close()
    return dom


def _settle(tools: DevTools, session: str, budget_s: float, until: str | None, quiet_s: float = 1.5) -> None:
    """Wait (at most ``budget_s``) until the page has loaded, ``until`` holds and its DOM has not
    changed for ``quiet_s`` (MLflow's pages render after their API calls return)."""
    probe = f"[document.readyState, document.documentElement.outerHTML.length, Boolean({until or 'true'})]"
    deadline = time.monotonic() + budget_s
    last, since = None, time.monotonic()
    while time.monotonic() < deadline:
        state, size, ready = tools.evaluate(probe, session) or ("loading", 0, False)
        now = time.monotonic()
        if (state, size, ready) != last:
            last, since = (state, size, ready), now
        elif state == "complete" and ready and now - since >= quiet_s:
            return
        time.sleep(0.25)


def api(server: str, endpoint: str, body: dict | None = None) -> dict:
    """One call of the REST API the dashboard's page uses (``ajax-api/2.0/mlflow/...``)."""
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(f"{server.rstrip('/')}/ajax-api/2.0/mlflow/{endpoint}", data=data,
                                     headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return json.load(response)
    except urllib.error.HTTPError as e:
        detail = e.read().decode(errors="replace")[:200]
        raise TrackingError(f"{server}: {endpoint}: HTTP {e.code} {detail}") from None
    except (urllib.error.URLError, OSError) as e:
        raise TrackingError(f"{server}: {endpoint}: {getattr(e, 'reason', e)}") from None


def experiments(server: str) -> dict[str, str]:
    """name -> id of the store's experiments."""
    found = api(server, "experiments/search", {"max_results": 1000}).get("experiments", [])
    return {e["name"]: e["experiment_id"] for e in found}


@contextlib.contextmanager
def serve(uri: str, port: int, artifacts: Path) -> Iterator[str]:
    """MLflow's server (the ``mlflow ui`` app) on 127.0.0.1 for the block; yields its address."""
    server = LocalServer(port, uri, str(artifacts))
    server.start()
    try:
        yield server.uri
    finally:
        server.stop()


RUNS_RENDERED = ("Boolean(document.querySelector('.ag-center-cols-container .ag-row')"
                 " || document.body.innerText.includes('No runs'))")
"""JavaScript: the runs table has drawn its rows (or said it has none)."""


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.dashboard", description=__doc__.splitlines()[0])
    parser.add_argument("--tracking-uri", help="a sqlite:/// store (default: $MLFLOW_TRACKING_URI, else "
                                               "sqlite:///mlflow.db)")
    parser.add_argument("--port", type=int, default=5000)
    parser.add_argument("--artifacts", type=Path, default=Path("mlartifacts"),
                        help="where runs of experiments created through this server keep artifacts")
    parser.add_argument("--experiment",
                        help="the experiment whose runs to show (default: the first one besides MLflow's Default)")
    parser.add_argument("--columns", default=",".join(KEY_METRICS),
                        help="comma-separated metrics shown as columns of the job runs (params.NAME, tags.NAME: "
                             "a param or tag; '': MLflow's own columns of every run); default: %(default)s")
    parser.add_argument("--screenshot", type=Path, help="save the runs page as PNG and exit")
    parser.add_argument("--page", choices=("runs", "report"), default="runs",
                        help="what --screenshot shows: the runs with --columns (default), or the study report on "
                             "the newest sweep parent run that has one")
    args = parser.parse_args(argv)
    args.tracking_uri = args.tracking_uri or os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db")
    if not args.tracking_uri.startswith("sqlite:///"):
        print(f"error: --tracking-uri {args.tracking_uri!r}: expected a sqlite:/// store (a running server "
              f"already has its dashboard at its own address)", file=sys.stderr)
        return 2
    if not Path(args.tracking_uri[len("sqlite:///"):]).is_file():
        print(f"error: --tracking-uri {args.tracking_uri!r}: no such store (run python -m demon_lab first)",
              file=sys.stderr)
        return 2
    columns = [c.strip() for c in args.columns.split(",") if c.strip()]
    try:
        with serve(args.tracking_uri, args.port, args.artifacts) as server:
            ids = experiments(server)
            if args.experiment is not None and args.experiment not in ids:
                raise TrackingError(f"--experiment {args.experiment!r}: not in the store (it has: "
                                    f"{', '.join(sorted(ids))})")

            def link(experiment_id: str) -> str:
                view = share_view(server, experiment_id, view_state(columns)) if columns else None
                return runs_url(server, experiment_id, view)

            if args.screenshot is not None:
                name = args.experiment or next(iter(sorted(ids, key=lambda n: n == "Default")))
                if args.page == "report":
                    found = study_report(server, ids[name])
                    if found is None:
                        raise TrackingError(f"--page report: no sweep run of {name!r} has a study report (report/); "
                                            f"python -m demon_lab.report explains how one is made")
                    capture(run_url(server, ids[name], *found), args.screenshot)
                else:
                    capture(link(ids[name]), args.screenshot, until=RUNS_RENDERED)
                print(f"[demon_lab.dashboard] {name}: {args.screenshot}", flush=True)
                return 0
            for name, experiment_id in sorted(ids.items(), key=lambda kv: int(kv[1])):
                if args.experiment in (None, name):
                    print(f"  {name:<24} {link(experiment_id)}", flush=True)
                    found = study_report(server, experiment_id)
                    if found is not None:
                        print(f"  {'':<24} study report: {run_url(server, experiment_id, *found)}", flush=True)
            print("[demon_lab.dashboard] serving; Ctrl-C stops it", flush=True)
            while True:
                time.sleep(3600)
    except TrackingError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0

