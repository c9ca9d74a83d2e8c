"""Headless Chromium for the browser tests and benchmarks/bench_viewer.py: Debian's ``chromium`` and
``chromium-driver`` (installed by ``scripts/setup-browser``) driven by selenium, with WebGL through SwiftShader
(software, any machine) and every background service of the browser off, so that it reaches nothing but the pages
it is sent to.

:func:`browser` starts one (a fresh profile in a temporary folder each time); :func:`wait_for` polls a script.
"""
from __future__ import annotations

import base64
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


def save(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path

