"""MLflow's dashboard on demon_lab's runs: ``python -m demon_lab.dashboard``.

Serves the tracking store with MLflow's own UI on 127.0.0.1 and prints, per experiment, the link to
its runs in the machine-learning view (MLflow 3 opens in its GenAI view, which hides training
runs). With ``--screenshot PNG`` it instead loads an experiment's runs page once in headless
Chromium, saves what a user would see, and stops the server::

    python -m demon_lab.dashboard                               # serve until Ctrl-C
    python -m demon_lab.dashboard --experiment iterations --screenshot docs/dashboard.png
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator, Sequence
from pathlib import Path

from demon_lab.tracking import LocalServer, TrackingError

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# Headless Chromium as a test harness: no sandbox (containers run as root), no GPU, and nothing
# that reaches the network besides the page itself.
BROWSER_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync")


def runs_url(server: str, experiment_id: str) -> str:
    """The runs table of an experiment, in the machine-learning view."""
    return f"{server.rstrip('/')}/#/experiments/{experiment_id}/runs?workflowType=machine_learning"


def run_url(server: str, experiment_id: str, run_id: str) -> str:
    return f"{server.rstrip('/')}/#/experiments/{experiment_id}/runs/{run_id}?workflowType=machine_learning"


def find_browser() -> str | None:
    """A Chromium-family browser on PATH (``$DEMON_LAB_BROWSER`` first), or None."""
    for name in (os.environ.get("DEMON_LAB_BROWSER"), *BROWSERS):
        if name and (path := shutil.which(name)):
            return path
    return None


def capture(url: str, screenshot: Path | None = None, window: tuple[int, int] = (1600, 900),
            budget_ms: int = 15000, browser: str | None = None) -> str:
    """Load ``url`` in headless Chromium, let its scripts run for ``budget_ms`` of virtual time,
    and return the rendered DOM; with ``screenshot``, also save a PNG of the window."""
    browser = browser or find_browser()
    if browser is None:
        raise TrackingError(f"no Chromium browser found (looked for {', '.join(BROWSERS)}); install Debian's "
                            f"'chromium' or set DEMON_LAB_BROWSER")
    with tempfile.TemporaryDirectory(prefix="demon_lab_browser_") as profile:
        command = [browser, *BROWSER_FLAGS, f"--user-data-dir={profile}", f"--window-size={window[0]},{window[1]}",
                   f"--virtual-time-budget={budget_ms}", "--dump-dom"]
        if screenshot is not None:
            screenshot.parent.mkdir(parents=True, exist_ok=True)
            command.append(f"--screenshot={screenshot.resolve()}")
        done = subprocess.run([*command, url], capture_output=True, text=True, timeout=120)
    if done.returncode != 0:
        raise TrackingError(f"{Path(browser).name} exited {done.returncode}: {done.stderr.strip()[-300:]}")
    return done.stdout


def api(server: str, endpoint: str, body: dict | None = None) -> dict:
    """One call of the REST API the dashboard's page uses (``ajax-api/2.0/mlflow/...``)."""
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(f"{server.rstrip('/')}/ajax-api/2.0/mlflow/{endpoint}", data=data,
                                     headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.load(response)


def experiments(server: str) -> dict[str, str]:
    """name -> id of the store's experiments."""
    found = api(server, "experiments/search", {"max_results": 1000}).get("experiments", [])
    return {e["name"]: e["experiment_id"] for e in found}


@contextlib.contextmanager
def serve(uri: str, port: int, artifacts: Path) -> Iterator[str]:
    """MLflow's server (the ``mlflow ui`` app) on 127.0.0.1 for the block; yields its address."""
    server = LocalServer({"port": port, "backend_store_uri": uri, "artifacts_destination": str(artifacts)})
    server.start()
    try:
        yield server.uri
    finally:
        server.stop()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m demon_lab.dashboard", description=__doc__.splitlines()[0])
    parser.add_argument("--tracking-uri", default=os.environ.get("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db"),
                        help="a sqlite:/// store (default: ./mlflow.db)")
    parser.add_argument("--port", type=int, default=5000)
    parser.add_argument("--artifacts", type=Path, default=Path("mlartifacts"),
                        help="where runs of experiments created through this server keep artifacts")
    parser.add_argument("--experiment", help="the experiment whose runs to show (default: the first with runs)")
    parser.add_argument("--screenshot", type=Path, help="save the runs page as PNG and exit")
    args = parser.parse_args(argv)
    if not args.tracking_uri.startswith("sqlite:///"):
        print(f"error: --tracking-uri {args.tracking_uri!r}: expected a sqlite:/// store (a running server "
              f"already has its dashboard at its own address)", file=sys.stderr)
        return 2
    if not Path(args.tracking_uri[len("sqlite:///"):]).is_file():
        print(f"error: --tracking-uri {args.tracking_uri!r}: no such store (run python -m demon_lab first)",
              file=sys.stderr)
        return 2
    try:
        with serve(args.tracking_uri, args.port, args.artifacts) as server:
            ids = experiments(server)
            if args.experiment is not None and args.experiment not in ids:
                raise TrackingError(f"--experiment {args.experiment!r}: not in the store (it has: "
                                    f"{', '.join(sorted(ids))})")
            if args.screenshot is not None:
                name = args.experiment or next(iter(sorted(ids, key=lambda n: n == "Default")))
                capture(runs_url(server, ids[name]), args.screenshot)
                print(f"[demon_lab.dashboard] {name}: {args.screenshot}", flush=True)
                return 0
            for name, experiment_id in sorted(ids.items(), key=lambda kv: int(kv[1])):
                if args.experiment in (None, name):
                    print(f"  {name:<24} {runs_url(server, experiment_id)}", flush=True)
            print("[demon_lab.dashboard] serving; Ctrl-C stops it", flush=True)
            while True:
                time.sleep(3600)
    except TrackingError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    sys.exit(main())
