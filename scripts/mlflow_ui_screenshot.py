"""Screenshots of the MLflow UI in a real headless browser: what a user sees of a store.

    python scripts/mlflow_ui_screenshot.py --runs runs --out /tmp/shots [--experiment btf]

Starts ``mlflow ui`` on a free port of 127.0.0.1 on the store ``<runs>/mlflow.db``, opens
in Debian's Chromium (``apt-get install chromium``) the experiment's runs view, and for the
latest sweep of the experiment: its parent run's overview (description, headline metrics)
and ``tables/summary.html`` (figures inlined) and ``summary.md``, the first child run's
overview (its metrics, results first), and for each child run its first figure under
``figures/`` and its ``config/resolved.yaml``, and saves each as a PNG in ``--out``. Prints one line per screenshot (file and URL) and stops the server.

The MLflow UI is a single-page app: Chromium's ``--screenshot`` with a virtual-time budget
lets its scripts fetch and draw before the picture is taken. The flags that keep Chromium
off the network are those this machine needs (it has no internet).
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from mlflow import MlflowClient

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--window-size=1600,1000",
    "--virtual-time-budget=20000",
]
# MLflow 3.17's UI opens every experiment in its GenAI view (Overview, Traces 0) unless its
# workflow switch says "Model training": a setting of the browser (local storage), which
# this query parameter sets; the experiment's mlflow.experimentKind tag no longer decides.
VIEW = "?workflowType=machine_learning"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_up(url: str, seconds: float = 120.0) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            time.sleep(1.0)
    raise SystemExit(f"the MLflow UI did not answer at {url} within {seconds:.0f} s")


def artifact_files(client: MlflowClient, run_id: str, path: str | None = None) -> list[str]:
    files = []
    for info in client.list_artifacts(run_id, path):
        files.extend(artifact_files(client, run_id, info.path) if info.is_dir else [info.path])
    return files


def pages(client: MlflowClient, experiment: str) -> list[tuple[str, str]]:
    """(name, URL fragment) of the pages to photograph, newest sweep first."""
    exp = client.get_experiment_by_name(experiment)
    if exp is None:
        raise SystemExit(f"no experiment {experiment!r} in the store")
    e = exp.experiment_id
    shots = [("experiment_runs", f"#/experiments/{e}")]
    children = client.search_runs(
        [e], "tags.mlflow.parentRunId != ''", order_by=["attributes.start_time DESC"]
    )
    if not children:
        raise SystemExit(f"experiment {experiment!r} has no sweep (no child runs)")
    parent = children[0].data.tags["mlflow.parentRunId"]
    sweep = [r for r in children if r.data.tags.get("mlflow.parentRunId") == parent]
    shots.append(("parent_overview", f"#/experiments/{e}/runs/{parent}"))
    tables = artifact_files(client, parent, "tables")
    for page in ("summary.html", "summary.md"):
        if f"tables/{page}" in tables:
            shots.append(
                (
                    f"parent_tables_{page.replace('.', '_')}",
                    f"#/experiments/{e}/runs/{parent}/artifacts/tables/{page}",
                )
            )
    first = min(sweep, key=lambda r: r.info.start_time)
    shots.append(("child_overview", f"#/experiments/{e}/runs/{first.info.run_id}"))
    for run in sorted(sweep, key=lambda r: r.info.start_time):
        name = run.info.run_name.replace(" ", "_").replace("=", "")
        files = artifact_files(client, run.info.run_id)
        figures = [f for f in files if f.startswith("figures/") and f.endswith(".png")]
        for label, path in (
            ("figure", figures[0] if figures else None),
            ("config", "config/resolved.yaml"),
        ):
            if path in files:
                shots.append(
                    (
                        f"{name}_{label}",
                        f"#/experiments/{e}/runs/{run.info.run_id}/artifacts/{path}",
                    )
                )
    return shots


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", default="runs", help="the pipeline's paths.runs")
    parser.add_argument("--out", required=True, help="folder for the PNG files")
    parser.add_argument("--experiment", default="btf", help="MLflow experiment (default: btf)")
    args = parser.parse_args(argv)
    chromium = shutil.which("chromium")
    if chromium is None:
        raise SystemExit("Chromium not found: apt-get install chromium")
    db = Path(args.runs).resolve() / "mlflow.db"
    if not db.is_file():
        raise SystemExit(f"no MLflow store at {db}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    uri = f"sqlite:///{db}"
    port = free_port()
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "ui",
            "--backend-store-uri",
            uri,
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}/"
    try:
        wait_until_up(base + "health")
        for name, fragment in pages(MlflowClient(uri), args.experiment):
            png = out / f"{name}.png"
            with tempfile.TemporaryDirectory() as profile:
                # An overview's metrics sit below its tags and description: a taller page.
                tall = ["--window-size=1600,2600"] if name.endswith("overview") else []
                subprocess.run(
                    [
                        chromium,
                        *CHROMIUM_FLAGS,
                        *tall,
                        f"--user-data-dir={profile}",
                        f"--screenshot={png}",
                        base + fragment + VIEW,
                    ],
                    check=True,
                    capture_output=True,
                    timeout=180,
                )
            print(f"{png}  {base}{fragment}{VIEW}")
    finally:
        server.terminate()
        server.wait(timeout=30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
