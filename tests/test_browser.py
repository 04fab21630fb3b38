"""What a reader sees, in a real browser (Debian's chromium, headless): the report, MLflow's runs and TensorBoard."""

from __future__ import annotations

import functools
import html
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
import urllib.request
from contextlib import contextmanager
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
from test_pipeline import smoke_train_sweep

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="needs Debian's chromium for the browser tests: apt-get install chromium"
)
# Copies of the screenshots outside pytest's temporary folders, for a person to look at.
SHOTS = Path("/tmp/browser_shots")
BIN = Path(sys.executable).parent


def chromium(url: str, *arguments: str, budget_ms: int = 10_000, profile: Path) -> str:
    """Load url in headless chromium with a fresh profile, let its scripts run for budget_ms of virtual time, and
    return what chromium printed (the DOM with --dump-dom)."""
    shutil.rmtree(profile, ignore_errors=True)
    command = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",  # as root
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--hide-scrollbars",
        f"--user-data-dir={profile}",
        "--window-size=1400,2000",
        "--run-all-compositor-stages-before-draw",
        f"--virtual-time-budget={budget_ms}",
        *arguments,
        url,
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def screenshot(url: str, path: Path, profile: Path, budget_ms: int = 10_000) -> Path:
    """A 1400x2000 screenshot of url into path (an artifact of the run folder), copied to SHOTS."""
    path.parent.mkdir(parents=True, exist_ok=True)
    chromium(url, f"--screenshot={path}", budget_ms=budget_ms, profile=profile)
    assert path.stat().st_size > 20_000, f"{path}: an empty page?"
    SHOTS.mkdir(parents=True, exist_ok=True)
    shutil.copy(path, SHOTS / path.name)
    return path


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def fetch_json(url: str, body: dict | None = None):
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return json.loads(response.read())


@contextmanager
def server(command: list[str], ready_url: str, log: Path, ready=lambda answer: True, wait_s: float = 90):
    """A dashboard server started by this test (in its own process group, its workers too), yielded once ready_url
    answers with JSON that ready() accepts; stopped whatever happens."""
    with open(log, "w") as output:
        process = subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + wait_s
        while True:
            assert process.poll() is None, f"{command[0]} stopped: {log.read_text()[-2000:]}"
            try:
                if ready(fetch_json(ready_url)):
                    break
            except OSError:
                pass
            assert time.monotonic() < deadline, f"{ready_url} not ready after {wait_s} s: {log.read_text()[-2000:]}"
            time.sleep(1)
        yield
    finally:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@contextmanager
def serving(folder: Path):
    """A folder over HTTP on 127.0.0.1 (so a page may look into another of the same origin); yields the base URL."""
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(folder))
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """One data folder for the module's sweeps: the smoke dataset is generated once."""
    return tmp_path_factory.mktemp("browser")


@pytest.fixture(scope="module")
def mlflow_sweep(workdir) -> Path:
    """Two models on one variant at budget=smoke, logged to MLflow (workdir/outputs/mlflow.db), with its report."""
    sweep = workdir / "mlflow_sweep"
    result = smoke_train_sweep(
        ["model=mujoco_default,sysid", "variant=frictioncubes_0", "logger=mlflow"], sweep, workdir
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = subprocess.run(
        [sys.executable, "-m", "contactbench.evaluation.report", str(sweep)], capture_output=True, text=True
    )
    assert report.returncode == 0, report.stderr[-3000:]
    return sweep


# Loads a page of the same origin (?page=...) in a frame, waits for its images to decode or fail, and writes what it
# found into its own DOM, where chromium's --dump-dom reads it.
CHECKER = """<!doctype html><html><body>
<iframe id="page" style="width:1400px;height:2000px"></iframe><pre id="found">not loaded</pre>
<script>
const frame = document.getElementById("page");
frame.addEventListener("load", () => {  // after every image of the page has loaded, or failed to
  const doc = frame.contentDocument;
  const images = [...doc.images];
  const tables = [...doc.querySelectorAll("table")].map((table) => table.rows[0].innerText);
  const found = images.map((image) => ({width: image.naturalWidth, height: image.naturalHeight}));
  // the markers are split here so that the script's own text in the dumped DOM never reads as a result
  document.getElementById("found").textContent = "FOU" + "ND" + JSON.stringify({tables, images: found}) + "E" + "ND";
});
frame.src = new URLSearchParams(location.search).get("page");
</script></body></html>
"""


def rendered(base: str, page: str, profile: Path) -> dict:
    """What the checker page saw of page after its scripts and images had loaded."""
    for budget_ms in (10_000, 60_000):  # virtual time; a loaded machine may need more to decode every image
        dom = chromium(
            f"{base}/check.html?page={urllib.parse.quote(page)}", "--dump-dom", budget_ms=budget_ms, profile=profile
        )
        found = re.search(r"FOUND(.*?)END", html.unescape(dom), flags=re.S)
        if found:
            return json.loads(found.group(1))
    raise AssertionError(f"the checker page never finished: {dom[-1000:]}")


def test_results_html_shows_its_grid_figures_and_renders_with_no_broken_image(mlflow_sweep, tmp_path):
    (mlflow_sweep / "check.html").write_text(CHECKER)
    # a control: the checker must see a broken image as broken
    (mlflow_sweep / "broken.html").write_text(
        '<table><tr><td>x</td></tr></table><img src="data:image/png;base64,AAAA">'
    )
    markdown = (mlflow_sweep / "results.md").read_text()
    pictures = re.findall(r"^!\[[^]]*\]\((figures|renders)/", markdown, flags=re.M)
    assert "figures" in pictures and "renders" in pictures
    with serving(mlflow_sweep) as base:
        assert rendered(base, "broken.html", tmp_path / "profile")["images"] == [{"width": 0, "height": 0}]
        page = rendered(base, "results.html", tmp_path / "profile")
        shot = screenshot(f"{base}/results.html", mlflow_sweep / "screenshots" / "results_html.png", tmp_path / "p")
    assert len(page["images"]) == len(pictures)
    assert all(image["width"] > 100 and image["height"] > 100 for image in page["images"]), page["images"]
    grid = [row for row in page["tables"] if row.startswith("dataset\tvariant")]
    assert grid and "mujoco_default" in grid[0] and "sysid" in grid[0]
    assert shot.is_file()


def test_mlflow_ui_lists_every_run_of_the_sweep_with_its_scores(mlflow_sweep, workdir, tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    command = [str(BIN / "mlflow"), "server", "--host", "127.0.0.1", "--port", str(port), "--workers", "1"]
    command += ["--backend-store-uri", f"sqlite:///{workdir}/outputs/mlflow.db"]
    with server(
        command, f"{url}/api/2.0/mlflow/experiments/get-by-name?experiment_name=contactbench", tmp_path / "log"
    ):
        experiment = fetch_json(f"{url}/api/2.0/mlflow/experiments/get-by-name?experiment_name=contactbench")
        experiment_id = experiment["experiment"]["experiment_id"]
        runs = fetch_json(f"{url}/api/2.0/mlflow/runs/search", {"experiment_ids": [experiment_id]})["runs"]
        page = f"{url}/#/experiments/{experiment_id}/runs"
        dom = html.unescape(chromium(page, "--dump-dom", budget_ms=15_000, profile=tmp_path / "profile"))
        shot = screenshot(page, mlflow_sweep / "screenshots" / "mlflow_runs.png", tmp_path / "p", budget_ms=15_000)
    assert sorted(tag_of(run, "model") for run in runs) == ["mujoco_default", "sysid"]
    for run in runs:
        metrics = {metric["key"]: metric["value"] for metric in run["data"]["metrics"]}
        name = run["info"]["run_name"]
        # the name, the one column the runs table shows by default, starts with the run's test scores
        assert name.startswith(f"test {metrics['test/pos_err']:.3f}/{metrics['test/rot_err_rad']:.3f} ")
        assert f"{metrics['val/pos_err']:.4f}" in tag_of(run, "mlflow.note.content")
        assert name in dom, f"run {name!r} not on the experiment page"
    assert "automatically detected the experiment type" not in dom  # no prompt over the page's tools
    assert shot.is_file()


def tag_of(run: dict, key: str) -> str:
    return next(tag["value"] for tag in run["data"]["tags"] if tag["key"] == key)


def test_tensorboard_scalars_page_shows_the_val_and_test_curves(workdir, tmp_path):
    sweep = workdir / "tensorboard_sweep"
    result = smoke_train_sweep(
        ["model=mujoco_default,sysid", "variant=frictioncubes_0", "logger=tensorboard"], sweep, workdir
    )
    assert result.returncode == 0, result.stderr[-3000:]
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    command = [str(BIN / "tensorboard"), "--logdir", str(sweep), "--host", "127.0.0.1", "--port", str(port)]
    curves = {f"{split}/{key}_by_frame" for split in ("val", "test") for key in ("pos_err", "rot_err_rad")}

    def loaded(tags: dict) -> bool:  # TensorBoard reads the event files after it answers
        return len(tags) == 2 and all(curves | {"val/pos_err", "test/pos_err"} <= set(run) for run in tags.values())

    with server(command, f"{url}/data/plugin/scalars/tags", tmp_path / "log", ready=loaded):
        for run in fetch_json(f"{url}/data/plugin/scalars/tags"):
            query = urllib.parse.urlencode({"run": run, "tag": "test/pos_err_by_frame"})
            points = fetch_json(f"{url}/data/plugin/scalars/scalars?{query}")
            assert len(points) > 100 and all(point[2] >= 0 for point in points)  # a point per frame after the context
        # the scalars dashboard (drawn in SVG, unlike the time-series one's WebGL), the per-frame curves first
        shot = screenshot(
            f"{url}/#scalars&tagFilter=by_frame",
            sweep / "screenshots" / "tensorboard_scalars.png",
            tmp_path / "profile",
        )
    assert shot.is_file()
