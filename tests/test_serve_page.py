"""The server page (``GET /ui``) in a real browser against a real ``occflownet serve`` process serving a briefly
trained model: upload the real nuScenes frame (six JPEGs and calib.json), wait for the answer, and check what is
drawn — the top-down canvas equals, pixel for pixel, the server's own ``image/png`` answer for the same request, the
3D canvas shows the class colours of the grid — and the latency the page reports: the page's round trip (click to
the answer on screen: top-down picture and latencies) may add at most 150 ms to the API's own round trip for the
same request, measured here by httpx (the median of five interleaved pairs, the best of up to three rounds on a
shared machine, printed); the 3D view drawn after it (its first frame in software WebGL) is printed and bounded. Five images show the API's own 422 message, and the server keeps serving. The page
fetches nothing but this server.

Screenshots: ``<tmp>/screenshots/`` (and docs/ with OCCFLOWNET_UPDATE_DOCS=1)."""
from __future__ import annotations

import io
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from browser import (browser, check_drawn, data_url_rgb, keep_screenshot, png_rgb, setup_browser, top_classes,
                     wait_for)
from exported_models import FRAME, exported_trained_tiny, frame_available
from selenium.webdriver.common.by import By
from serve_fixtures import free_port, stop_server

from occflownet.occ3d import CAMERAS, CLASS_COLORS
from occflownet.serve.client import wait_ready

REPO = Path(__file__).resolve().parents[1]
OVERHEAD_TARGET_MS = 150.0
PAIRS = 5
ROUNDS = 3
# the 3D view's first frame in software WebGL (SwiftShader) comes on top: bounded, not the target
DRAWN_LIMIT_MS = 600.0
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


def frame_files(cameras=CAMERAS) -> dict:
    files = {c: (f"{c}.jpg", (FRAME / f"{c}.jpg").read_bytes(), "image/jpeg") for c in cameras}
    files["calibration"] = ("calib.json", (FRAME / "calib.json").read_bytes(), "application/json")
    return files


def direct(server: str, accept: str = "application/json", cameras=CAMERAS) -> tuple[httpx.Response, float]:
    t0 = time.perf_counter()
    r = httpx.post(f"{server}/v1/occupancy", files=frame_files(cameras), headers={"Accept": accept}, timeout=60)
    if accept == "application/json" and r.status_code == 200:
        r.json()
    return r, (time.perf_counter() - t0) * 1e3


def send(page, cameras=CAMERAS, calibration: bool = True) -> dict:
    """Choose the images (and calib.json) in the page's file inputs, press the button, wait for the outcome."""
    page.execute_script("window.occPage.last = null; document.getElementById('images').value = '';")
    page.find_element(By.ID, "images").send_keys("\n".join(str(FRAME / f"{c}.jpg") for c in cameras))
    if calibration:
        page.find_element(By.ID, "calibration").send_keys(str(FRAME / "calib.json"))
    page.find_element(By.ID, "run").click()
    return wait_for(page, "window.occPage.last", timeout=120)


def _round(server, page) -> dict[str, float]:
    """PAIRS interleaved pairs (the API's round trip by httpx; the page's click → answer shown (top-down picture and
    latencies) and click → 3D view drawn), the order alternating → {"shown", "drawn": median over the pairs of
    page − API in ms, "last": the page's last outcome}; each pair printed."""
    pairs = []
    for i in range(PAIRS):
        if i % 2:
            last, api_ms = send(page), direct(server)[1]
        else:
            api_ms = direct(server)[1]
            last = send(page)
        assert last["ok"] and last["status"] == 200, last
        pairs.append((api_ms, last["shownMs"], last["drawnMs"]))
        t = last["viewer"]["timings"]
        print(f"\n  API {api_ms:.0f} ms; page: answer {last['fetchMs']:.0f} ms, shown {last['shownMs']:.0f} ms, 3D "
              f"{last['drawnMs']:.0f} ms (surface {t['built'] - t['decoded']:.0f}, first frame "
              f"{last['viewer']['firstFrameMs'] - t['built']:.0f} ms); server total {last['server']['total']:.0f} ms")
    shown = statistics.median(s - a for a, s, _ in pairs)
    drawn = statistics.median(d - a for a, _, d in pairs)
    pane = last["viewer"]["panes"][0]
    print(f"real frame ({pane['voxels']} voxels, {pane['quads']} rectangles): API round trip p50 "
          f"{statistics.median(a for a, _, _ in pairs):.0f} ms; the page adds {shown:.0f} ms to the answer on screen, "
          f"{drawn:.0f} ms to the 3D view drawn (medians of {PAIRS} pairs)")
    return {"shown": shown, "drawn": drawn, "last": last}


def test_real_frame_round_trip_draws_the_answer_and_reports_latency(server, page, tmp_path):
    first = send(page)                                                 # warm: the first canvas, the first upload
    assert first["ok"], first
    rounds = []
    for _ in range(ROUNDS):                                            # a shared machine's noise: best round counts
        rounds.append(_round(server, page))
        if rounds[-1]["shown"] <= OVERHEAD_TARGET_MS and rounds[-1]["drawn"] <= DRAWN_LIMIT_MS:
            break
    best = min(rounds, key=lambda r: r["shown"])
    print(f"the page adds {best['shown']:.0f} ms to the API's round trip until the answer is on screen (target ≤ "
          f"{OVERHEAD_TARGET_MS:.0f} ms), {best['drawn']:.0f} ms until its 3D view is drawn (SwiftShader; bound "
          f"{DRAWN_LIMIT_MS:.0f} ms); rounds: {[(round(r['shown']), round(r['drawn'])) for r in rounds]}")
    assert best["shown"] <= OVERHEAD_TARGET_MS
    assert min(r["drawn"] for r in rounds) <= DRAWN_LIMIT_MS

    # what the page reports is what the server measured (for the request on screen: the last one)
    last = page.execute_script("return window.occPage.last")
    text = page.find_element(By.ID, "latency").text
    assert f"server: {last['server']['total']:.0f} ms" in text and "inference" in text
    assert last["serverTiming"].startswith("queue;dur=")
    # the top-down canvas is the server's own image/png answer for the same request, pixel for pixel
    png, _ = direct(server, "image/png")
    canvas = data_url_rgb(page.execute_script("return document.getElementById('top-down').toDataURL('image/png')"))
    np.testing.assert_array_equal(canvas, png_rgb(png.content))
    # the 3D view shows the grid's classes in their colours
    npy, _ = direct(server, "application/x-npy")
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
    r, _ = direct(server, cameras=five)
    assert r.status_code == 422
    err = r.json()["error"]
    last = send(page, five)
    assert not last["ok"] and last["status"] == 422
    shown = page.find_element(By.ID, "error").text
    assert shown == f"HTTP 422 {err['code']}: {err['message']}", shown
    assert not page.find_element(By.ID, "result").is_displayed()       # no earlier answer under the error
    keep_screenshot(tmp_path, "serve_page_error.png", page.get_screenshot_as_png())
    # the server keeps serving, the page too
    assert direct(server)[0].status_code == 200
    again = send(page)
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
            assert send(d)["ok"]
    finally:
        stop_server(proc)
