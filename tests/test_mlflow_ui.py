"""End to end in a browser: after a smoke sweep, plain ``mlflow ui`` in the launch directory shows the sweep's parent
run with its jobs and the table's metric columns, through the link the sweep prints (ablate.store.tracker.runs_link) and
through the clicks a user makes from the home page.

Needs Debian's Chromium (``apt-get install chromium``; .ci/run installs it) and Playwright's Python driver (the
``browser`` extra); it is skipped, saying which is missing, otherwise.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from scripts.tracking_server import wait_healthy
from tests.scaleout import free_port, need, output, runs
from tests.shared import smoke_table2

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Chromium as root in a sandbox with no network: no sandbox, no GPU, none of its background connections.
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
ROWS = ("chinet seed=0", "unet seed=0", "fusenet seed=0")
#: The published table the UI's store also holds, loaded as ``python -m ablate.report --load`` loads it.
LOADED = "bifnet_table4"
LOADED_LINK = ""


@pytest.fixture(scope="module")
def ui(tmp_path_factory) -> tuple[Path, str, str]:
    """A smoke ChiNet Table II sweep (the session's, tests/shared.py, in a directory of its own), then ``mlflow ui``
    there on a free port: (the directory, the address of the UI, the link the sweep printed, pointed at that
    port)."""
    if CHROMIUM is None:
        pytest.skip("Chromium is not installed (apt-get install chromium)")
    need("playwright")
    cwd, out = smoke_table2(tmp_path_factory, "ui")
    assert out.returncode == 0, output(out)
    found = re.search(r"Runs in the MLflow UI.*?: (http://127\.0\.0\.1:5000/\S+)", out.stdout + out.stderr)
    assert found, output(out)
    from ablate.analysis.load import load_table  # a published table loaded beside the sweep (report --load)
    from ablate.store import Tracker

    global LOADED_LINK
    LOADED_LINK = load_table(Tracker(f"sqlite:///{cwd}/mlflow.db"), LOADED)[1]
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    # MLflow's server-side job runner (huey consumers for its GenAI features) off, as scripts/tracking_server.py
    # has it: the UI of runs never uses it, and it starts eight more processes, each importing MLflow
    env["MLFLOW_SERVER_ENABLE_JOB_EXECUTION"] = "false"
    log = cwd / "mlflow_ui.log"
    with log.open("w") as out:
        server = subprocess.Popen(
            [str(Path(sys.executable).parent / "mlflow"), "ui", "--host", "127.0.0.1", "--port", str(port)],
            cwd=cwd,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    base = f"http://127.0.0.1:{port}"
    try:
        wait_healthy(base, server, log, timeout_s=120)  # fails with the UI's log if it exits or never answers
        yield cwd, base, found.group(1).replace("http://127.0.0.1:5000", base)
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def browser():
    need("playwright")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


def test_printed_link_shows_the_parent_its_jobs_and_the_metric_columns(ui, browser):
    cwd, _, link = ui
    page = browser.new_page(viewport={"width": 2400, "height": 1000})
    page.goto(link)
    page.get_by_text("chinet_table2 scale=smoke").first.wait_for(timeout=60_000)  # the sweep, named after its table
    page.locator(".ag-row", has_text="chinet_table2 scale=smoke").first.locator(
        "button"
    ).first.click()  # unfold its jobs
    for name in ROWS:
        page.get_by_text(name, exact=True).first.wait_for(timeout=20_000)
    headers = " ".join(page.locator(".ag-header-cell").all_inner_texts())
    for metric in ("det_rate", "iou_free_space", "iou_road_objects", "latency_ms"):
        assert metric in headers, headers
    # the job's row (its name and its values are two grid rows of one row-index) carries its Det. Rate
    index = page.locator(".ag-row", has_text="unet seed=0").first.get_attribute("row-index")
    cells = " ".join(page.locator(f'.ag-row[row-index="{index}"]').all_inner_texts())
    _, jobs = runs(f"sqlite:///{cwd}/mlflow.db", "chinet_table2")
    unet = next(r for r in jobs if r.info.run_name == "unet seed=0")
    assert repr(unet.data.metrics["det_rate"]) in cells, cells


def test_a_user_clicks_from_the_home_page_to_the_runs(ui, browser):
    _, base, _ = ui
    page = browser.new_context(viewport={"width": 1600, "height": 1000}).new_page()
    page.goto(base + "/")
    page.get_by_text("Model training", exact=True).first.click()
    page.get_by_text("chinet_table2", exact=True).first.click()
    page.get_by_text("chinet_table2 scale=smoke").first.wait_for(timeout=60_000)  # the sweep, named after its table
    assert "workflowType=machine_learning" in page.url, page.url


def test_a_loaded_table_shows_its_parent_with_every_rows_primary_metric_in_model_training_mode(ui, browser):
    """``--load``'s parent run, named like the table, carries each row's mean primary metric as a column of the
    saved view, and the link opens the model-training view of the runs."""
    cwd, base, _ = ui
    page = browser.new_page(viewport={"width": 2400, "height": 1000})
    page.goto(LOADED_LINK.replace("http://127.0.0.1:5000", base))
    page.get_by_text(f"{LOADED} (published)").first.wait_for(timeout=60_000)
    assert "workflowType=machine_learning" in page.url, page.url
    client, loaded = runs(f"sqlite:///{cwd}/mlflow.db", LOADED, kind="imported")
    (parent,) = [r for r in loaded if r.info.run_name == f"{LOADED} (published)"]
    assert {r.data.tags.get("mlflow.parentRunId") for r in loaded if r is not parent} == {parent.info.run_id}
    assert all(r.data.params and r.inputs.dataset_inputs for r in loaded if r is not parent)
    assert sorted(a.path for a in client.list_artifacts(parent.info.run_id, "table"))[:2] == [
        f"table/{LOADED}.csv", f"table/{LOADED}.md"
    ]  # fmt: skip
    headers = " ".join(page.locator(".ag-header-cell").all_inner_texts())
    index = page.locator(".ag-row", has_text=f"{LOADED} (published)").first.get_attribute("row-index")
    cells = " ".join(page.locator(f'.ag-row[row-index="{index}"]').all_inner_texts())
    page.locator(".ag-row", has_text=f"{LOADED} (published)").first.locator("button").first.click()  # its runs
    row = page.locator(".ag-row", has_text="bifnet_dst_sum seed=0 (imported)").first.get_attribute("row-index")
    shown = " ".join(page.locator(f'.ag-row[row-index="{row}"]').all_inner_texts())
    assert "row" in headers.split() and "bifnet_dst_sum" in shown.replace("bifnet_dst_sum seed=0", ""), shown
    for key, value in parent.data.metrics.items():  # one per row: <row>/max_f, its mean over the seeds
        assert key in headers and repr(value) in cells, (key, value, headers, cells)
