"""Headless Chromium for the browser tests and benchmarks/perf/bench_viewer.py: Debian's ``chromium`` and
``chromium-driver`` (installed by ``scripts/setup-browser``) driven by selenium, with WebGL through SwiftShader
(software, any machine) and every background service of the browser off, so that it reaches nothing but the pages
it is sent to.

:func:`browser` starts one (a fresh profile in a temporary folder each time); :func:`wait_for` polls a script.
"""
from __future__ import annotations

import base64
import os
import shutil
import subprocess
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"
FLAGS = (
    "--headless=new", "--no-sandbox",                        # root in CI: no setuid sandbox
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader",  # WebGL in software: no GPU needed
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
    "--disable-default-apps", "--disable-extensions", "--no-default-browser-check", "--disable-dev-shm-usage",
    "--hide-scrollbars", "--force-device-scale-factor=1",
)


def setup_browser() -> None:
    """Run scripts/setup-browser (idempotent: apt-installs chromium and chromium-driver when missing); raises
    AssertionError with its output when it fails."""
    proc = subprocess.run(["bash", str(REPO / "scripts" / "setup-browser")], capture_output=True, text=True,
                          timeout=1200)
    assert proc.returncode == 0, f"scripts/setup-browser failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"


@contextmanager
def browser(width: int = 1400, height: int = 1000):
    """A selenium Chrome driver on headless Chromium, window ``width × height``; quits and removes its profile."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="occflownet-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def wait_for(driver, script: str, timeout: float = 60.0, interval: float = 0.02):
    """Evaluate ``script`` (a JS expression, e.g. ``window.x && window.x.done``) until it is truthy; its value.
    TimeoutError with the browser's console log otherwise."""
    deadline = time.monotonic() + timeout
    while True:
        value = driver.execute_script(f"return ({script});")
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"{script} still false after {timeout} s; console: {console(driver)}")
        time.sleep(interval)


def console(driver) -> list[str]:
    try:
        return [f"{e['level']}: {e['message']}" for e in driver.get_log("browser")]
    except Exception:                                           # noqa: BLE001 - the log is best effort
        return []


def png_rgb(data: bytes) -> np.ndarray:
    """PNG bytes (a screenshot) → RGB uint8 [H, W, 3]."""
    import cv2

    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return np.ascontiguousarray(bgr[:, :, ::-1])


def data_url_rgb(url: str) -> np.ndarray:
    """A ``data:image/png;base64,...`` URL (canvas.toDataURL()) → RGB uint8 [H, W, 3]."""
    return png_rgb(base64.b64decode(url.split(",", 1)[1]))


def keep_screenshot(tmp_path: Path, name: str, png: bytes, docs: bool = True) -> Path:
    """Save a screenshot as ``<tmp_path>/screenshots/<name>`` (the test's artifacts) and, if ``docs`` and
    OCCFLOWNET_UPDATE_DOCS=1, as ``docs/<name>`` (the pictures the README and docs/viewer.md show)."""
    path = tmp_path / "screenshots" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    if docs and os.environ.get("OCCFLOWNET_UPDATE_DOCS") == "1":
        shutil.copyfile(path, REPO / "docs" / name)
    return path



def top_classes(occupancy: np.ndarray, shown: np.ndarray | None = None, free: int = 17, min_columns: int = 40
                ) -> dict[int, int]:
    """{class: columns} of the classes on top of at least ``min_columns`` (x, y) columns of the voxels ``shown``
    (bool [X, Y, Z], default every occupied voxel): what a view from above must show in their colours."""
    occ = np.where(shown if shown is not None else occupancy != free, occupancy, free)
    occupied = occ != free
    top_z = occ.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    top = np.take_along_axis(occ, top_z[..., None], axis=2)[..., 0][occupied.any(axis=2)]
    counts = np.bincount(top, minlength=free + 1)
    return {int(c): int(n) for c, n in enumerate(counts) if c != free and n >= min_columns}


def colour_pixels(rgb: np.ndarray, colour, tolerance: int = 3) -> int:
    """Pixels of ``rgb`` [H, W, 3] within ``tolerance`` of ``colour`` in every channel."""
    return int((np.abs(rgb.astype(np.int16) - np.asarray(colour, np.int16)).max(axis=-1) <= tolerance).sum())


def check_drawn(rgb: np.ndarray, expected: dict[int, int], colors: np.ndarray, background=(242, 243, 245),
                min_pixels: int = 20) -> dict[int, int]:
    """Assert that a screenshot of the 3D canvas is not blank (≥ 10 % of it differs from the background) and that
    every class of ``expected`` shows in its colour (top faces are drawn in the class colour exactly) on at least
    ``min_pixels`` pixels → {class: pixels}."""
    drawn = float((np.abs(rgb.astype(np.int16) - np.asarray(background, np.int16)).max(axis=-1) > 6).mean())
    assert drawn >= 0.10, f"the canvas is nearly blank: {drawn:.1%} of its pixels differ from the background"
    found = {c: colour_pixels(rgb, colors[c]) for c in expected}
    missing = {c: n for c, n in found.items() if n < min_pixels}
    assert not missing, f"class colours missing from the canvas (class: pixels): {missing}; expected {expected}"
    return found
