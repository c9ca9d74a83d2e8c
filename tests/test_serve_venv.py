"""The serving image's environment without Docker: a fresh venv with only ``pip install <repo>[serve]``.

It is what docker/Dockerfile builds (slim Python + the ``serve`` extra, no torch). The venv is cached under
``~/.cache/occflownet/serve-venv-<hash of pyproject.toml>`` (dependencies are installed once, which needs PyPI and
takes a few minutes the first time); each run re-installs just the package from a copy of the working tree, then
starts ``occflownet serve`` from the venv on a free 127.0.0.1 port against the fake model, checks /readyz and one
POST, and that torch cannot be imported there. Skipped, saying why, when pip cannot reach a package index.
"""
import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from serve_fixtures import build_fake_model, free_port, image_files, stop_server, synthetic_images

from occflownet.serve.client import wait_ready

REPO = Path(__file__).resolve().parents[1]
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "occflownet"
NETWORK_SIGNS = ("Could not find a version", "No matching distribution", "NewConnectionError",
                 "Failed to establish a new connection", "Temporary failure in name resolution",
                 "Network is unreachable", "ConnectTimeoutError", "ReadTimeoutError", "ProxyError",
                 "Max retries exceeded")


def _source_copy(dest: Path) -> Path:
    """What a Docker build context would hold: pyproject, README and the three packages (no .venv, no tests)."""
    dest.mkdir(parents=True)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, dest / name)
    for package in ("occflownet", "export", "serve"):
        shutil.copytree(REPO / package, dest / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return dest


def _pip(python: Path, *args: str, timeout: int = 1500) -> None:
    proc = subprocess.run([str(python), "-m", "pip", "install", "--disable-pip-version-check", *args],
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        output = proc.stdout + proc.stderr
        if any(sign in output for sign in NETWORK_SIGNS):
            pytest.skip(f"pip could not reach a package index to build the serving venv: {output.strip()[-400:]}")
        raise AssertionError(f"pip install {' '.join(args)} failed:\n{output[-3000:]}")


def _remove_stale_venvs(keep: Path) -> None:
    """Delete venvs of older pyproject versions (~300 MB each) that no run is using (their lock is free)."""
    for other in CACHE.glob("serve-venv-*"):
        if other == keep or not other.is_dir():
            continue
        with open(f"{other}.lock", "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            shutil.rmtree(other, ignore_errors=True)
        Path(f"{other}.lock").unlink(missing_ok=True)


@pytest.fixture(scope="module")
def serve_venv(tmp_path_factory) -> Path:
    key = hashlib.sha256((REPO / "pyproject.toml").read_bytes()).hexdigest()[:12]
    venv = CACHE / f"serve-venv-{key}"
    python = venv / "bin" / "python"
    CACHE.mkdir(parents=True, exist_ok=True)
    source = _source_copy(tmp_path_factory.mktemp("serve-venv") / "src")
    with open(CACHE / f"serve-venv-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)   # concurrent test runs share one venv
        if not (venv / ".deps-installed").exists():
            _remove_stale_venvs(keep=venv)
            shutil.rmtree(venv, ignore_errors=True)
            subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
            _pip(python, "--upgrade", "pip", "setuptools>=68")
            _pip(python, f"{source}[serve]")
            (venv / ".deps-installed").write_text(f"pyproject sha256 prefix {key}\n")
        else:  # dependencies cached: refresh only the package itself from this working tree
            _pip(python, "--no-deps", "--force-reinstall", "--no-build-isolation", str(source), timeout=600)
    return venv


def test_serving_venv_has_no_torch_and_serves(serve_venv, tmp_path):
    python = serve_venv / "bin" / "python"
    probe = subprocess.run([str(python), "-c", "import torch"], capture_output=True, text=True, cwd=tmp_path)
    assert probe.returncode != 0 and "No module named 'torch'" in probe.stderr
    model = build_fake_model(tmp_path / "model.onnx")
    port = free_port()
    proc = subprocess.Popen([str(serve_venv / "bin" / "occflownet"), "serve", "--model", str(model), "--port",
                             str(port), "--no-access-log"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    base = f"http://127.0.0.1:{port}"
    try:
        wait_ready(base, timeout=60, proc=proc)
        r = httpx.post(f"{base}/v1/occupancy", files=image_files(synthetic_images((96, 54))),
                       headers={"Accept": "application/octet-stream"}, timeout=30)
        assert r.status_code == 200, r.text
        grid = np.frombuffer(r.content, np.uint8)
        assert grid.size == 640_000 and grid.max() <= 17
        modules = subprocess.run([str(python), "-c", "import occflownet.serve.app, sys; print(occflownet.serve.app.__file__); "
                                  "print('torch' in sys.modules)"], capture_output=True, text=True, cwd=tmp_path)
        assert str(serve_venv) in modules.stdout and modules.stdout.strip().endswith("False"), modules
    finally:
        stop_server(proc)
