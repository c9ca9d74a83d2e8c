"""The server page (``GET /ui``) in a real browser against a real ``occflownet serve`` process serving a briefly
trained model: upload the real nuScenes frame (six JPEGs and calib.json), wait for the answer, and check what is
drawn — the top-down canvas equals, pixel for pixel, the server's own ``image/png`` answer for the same request, the
3D canvas shows the class colours of the grid — and that the latencies the page shows are the server's own. Five
images show the API's own 422 message, and the server keeps serving. The page fetches nothing but this server.
How long the page takes beside the API is measured by ``benchmarks/perf/bench_serve_page.py``, not asserted here.

Screenshots: ``<tmp>/screenshots/`` (and docs/ with OCCFLOWNET_UPDATE_DOCS=1)."""
from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from browser import (browser, check_drawn, data_url_rgb, keep_screenshot, png_rgb, setup_browser, top_classes,
                     wait_for)
from exported_models import FRAME, exported_trained_tiny, frame_available
from selenium.webdriver.common.by import By
from serve_fixtures import free_port, post_frame, send_from_page, stop_server

from occflownet.occ3d import CAMERAS, CLASS_COLORS
from occflownet.serve.client import wait_ready

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not frame_available(), reason=f"real frame not found at {FRAME}")


@pytest.fixture(scope="module")
def server():
    model = exported_trained_tiny()[0]
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "occflownet", "serve", "--model", str(model), "--port", str(port),
                             "--no-access-log", "--log-level", "warning"], cwd=REPO)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_ready(base, 120, proc=proc)
        yield base
    finally:
        stop_server(proc)


@pytest.fixture(scope="module")
def page(server):
    setup_browser()
    with browser() as d:
        d.get(f"{server}/ui")
        wait_for(d, "window.occPage && window.occPage.metadata")
        yield d


def test_real_frame_round_trip_draws_the_answer_and_reports_latency(server, page, tmp_path):
    last = send_from_page(page)
    assert last["ok"] and last["status"] == 200, last
    assert last["shownMs"] > 0 and last["drawnMs"] >= last["shownMs"]  # the page times the answer, then the 3D view

    # what the page reports is what the server measured (for the request on screen)
    text = page.find_element(By.ID, "latency").text
    assert f"server: {last['server']['total']:.0f} ms" in text and "inference" in text
    assert last["serverTiming"].startswith("queue;dur=")
    # the top-down canvas is the server's own image/png answer for the same request, pixel for pixel
    png, _ = post_frame(server, "image/png")
    canvas = data_url_rgb(page.execute_script("return document.getElementById('top-down').toDataURL('image/png')"))
    np.testing.assert_array_equal(canvas, png_rgb(png.content))
    # the 3D view shows the grid's classes in their colours
    npy, _ = post_frame(server, "application/x-npy")
    grid = np.load(io.BytesIO(npy.content))
    expected = top_classes(grid, min_columns=25)
    assert expected and sum(last["classCounts"].values()) - last["classCounts"]["free"] == int((grid != 17).sum())
    check_drawn(png_rgb(page.find_element(By.CSS_SELECTOR, "#view3d .occ-canvas canvas").screenshot_as_png),
                expected, CLASS_COLORS)
    origins = page.execute_script("return performance.getEntriesByType('resource').map(e => new URL(e.name).origin)")
    assert set(origins) == {server}, origins                           # nothing but this server
    keep_screenshot(tmp_path, "serve_page.png", page.get_screenshot_as_png())


def test_five_images_show_the_api_error_and_the_server_keeps_serving(server, page, tmp_path):
    five = CAMERAS[:5]
    r, _ = post_frame(server, cameras=five)
    assert r.status_code == 422
    err = r.json()["error"]
    last = send_from_page(page, five)
    assert not last["ok"] and last["status"] == 422
    shown = page.find_element(By.ID, "error").text
    assert shown == f"HTTP 422 {err['code']}: {err['message']}", shown
    assert not page.find_element(By.ID, "result").is_displayed()       # no earlier answer under the error
    keep_screenshot(tmp_path, "serve_page_error.png", page.get_screenshot_as_png())
    # the server keeps serving, the page too
    assert post_frame(server)[0].status_code == 200
    again = send_from_page(page)
    assert again["ok"] and not page.find_element(By.ID, "error").is_displayed()


def test_page_shows_the_api_key_error_then_works_with_the_key(tmp_path):
    """With OCCFLOWNET_API_KEY the page loads, says the API needs the key (the API's 401 message), and works once
    the key is typed in."""
    model = exported_trained_tiny()[0]
    port = free_port()
    env = {**os.environ, "OCCFLOWNET_API_KEY": "page-test-key"}
    proc = subprocess.Popen([sys.executable, "-m", "occflownet", "serve", "--model", str(model), "--port", str(port),
                             "--no-access-log", "--log-level", "warning"], cwd=REPO, env=env)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_ready(base, 120, proc=proc)
        setup_browser()
        with browser() as d:
            d.get(f"{base}/ui")
            message = wait_for(d, "document.getElementById('error').textContent")
            assert message.startswith("HTTP 401 unauthorized: missing or wrong API key"), message
            d.find_element(By.ID, "api-key").send_keys("page-test-key")
            d.execute_script("document.getElementById('api-key').dispatchEvent(new Event('change'))")
            wait_for(d, "window.occPage.metadata")
            assert send_from_page(d)["ok"]
    finally:
        stop_server(proc)
