"""The official nuscenes-devkit (1.2.0, in its own cached venv) loads a synthetic root, lidarseg included.

The venv lives at ~/.cache/occflownet/devkit-venv (override: OCCFLOWNET_DEVKIT_VENV); it is built on first use with
pip (needs the network once; a few minutes) and the test is skipped, saying why, when that is impossible.
nuscenes-devkit pins numpy<2, so it never goes into the project's own environment.
"""
import fcntl
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

VENV = Path(os.environ.get("OCCFLOWNET_DEVKIT_VENV", Path.home() / ".cache" / "occflownet" / "devkit-venv"))
MARKER = VENV / ".occflownet-devkit-ok"
# nuscenes-devkit's own requirements include heavy extras (shapely, pycocotools, ...) that `import NuScenes` does
# not need; install it without deps plus what the import of nuscenes.nuscenes actually uses.
DEPS = ["numpy<2", "opencv-python-headless<4.12", "matplotlib", "scikit-learn", "pillow", "pyquaternion", "tqdm",
        "cachetools"]


def devkit_python() -> Path:
    py = VENV / "bin" / "python"
    if MARKER.exists() and py.exists():
        return py
    VENV.parent.mkdir(parents=True, exist_ok=True)
    with open(VENV.with_name(VENV.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another test session may be building it right now
        if MARKER.exists() and py.exists():
            return py
        return _build()


def _build() -> Path:
    tmp = VENV.with_name(VENV.name + ".building")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.parent.mkdir(parents=True, exist_ok=True)
    steps = [[sys.executable, "-m", "venv", str(tmp)],
             [str(tmp / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps", "nuscenes-devkit==1.2.0"],
             [str(tmp / "bin" / "python"), "-m", "pip", "install", "-q", *DEPS],
             [str(tmp / "bin" / "python"), "-c", "from nuscenes.nuscenes import NuScenes"]]
    for cmd in steps:
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        except (OSError, subprocess.TimeoutExpired) as e:
            pytest.skip(f"cannot build the nuscenes-devkit venv ({' '.join(cmd[:4])}): {e}")
        if r.returncode != 0:
            pytest.skip(f"cannot build the nuscenes-devkit venv ({' '.join(cmd[2:5])}): {r.stderr.strip()[-400:]}")
    shutil.rmtree(VENV, ignore_errors=True)
    tmp.rename(VENV)
    MARKER.write_text("nuscenes-devkit==1.2.0\n")
    return VENV / "bin" / "python"


def test_nuscenes_devkit_loads_the_synthetic_root(synth_root, synth_params):
    root, version = synth_root
    py = devkit_python()
    script = Path(__file__).with_name("synth_devkit_check.py")
    r = subprocess.run([str(py), str(script), str(root), version], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    frames = synth_params["frames"]
    assert out["samples"] == frames and out["sample_data"] == 7 * frames
    assert out["boxes"] > 0 and out["points"] > 10_000 and out["projected"] > 1000
    # the devkit's own box geometry (global → ego → LiDAR) encloses the LiDAR points we counted for each box
    assert out["box_points_checked"] > 10 and out["box_points_ok"] == out["box_points_checked"], out
    assert {"vehicle.car", "flat.driveable_surface", "static.manmade"} <= set(out["classes"])
