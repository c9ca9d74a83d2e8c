"""Shared, expensive test fixtures of the model/export/predict tests: one exported tiny model per test session.

Imported by tests/test_export_*.py and tests/test_predict.py; the export runs once per pytest process (lru_cache)
into a temporary folder that is removed at exit.
"""
from __future__ import annotations

import atexit
import functools
import os
import shutil
import tempfile
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared"
FRAME = SHARED / "data" / "nuscenes-frame"
SEED = 0


def frame_available() -> bool:
    return (FRAME / "calib.json").is_file() and (FRAME / "CAM_FRONT.jpg").is_file()


@functools.lru_cache(maxsize=None)
def workdir() -> Path:
    """A temporary folder removed at exit; with OCCFLOWNET_TEST_KEEP=DIR, DIR instead, kept (developer runs only:
    the trained checkpoint found there is reused, so delete DIR after changing the model or the training)."""
    if os.environ.get("OCCFLOWNET_TEST_KEEP"):
        path = Path(os.environ["OCCFLOWNET_TEST_KEEP"])
        path.mkdir(parents=True, exist_ok=True)
        return path
    path = Path(tempfile.mkdtemp(prefix="occflownet-export-tests-"))
    atexit.register(shutil.rmtree, path, True)
    return path


@functools.lru_cache(maxsize=None)
def exported_tiny():
    """(onnx path, ExportResult, model) of a random-init tiny (seed SEED), parity-checked incl. the real frame."""
    from occflownet.export.onnx_export import export_model
    from occflownet.model import create_model, get_preset

    model = create_model(get_preset("tiny"), seed=SEED).eval()
    frames = [FRAME] if frame_available() else []
    result = export_model(model, model.cfg, workdir() / "tiny.onnx", parity_frames=frames)
    return result.path, result, model


@functools.lru_cache(maxsize=None)
def trained_tiny_checkpoint() -> Path:
    """A tiny checkpoint trained briefly (3D labels inside mask_camera, the quickstart's recipe, 80 steps) on a
    1-scene × 6-frame synthetic world, so that its grid has occupied voxels of several classes: paths compared on it
    (torch vs onnxruntime, Python vs C++, two runtimes) disagree visibly where they differ, unlike a random-init
    model whose grid is all free. (Trained on every voxel instead, 80 steps mostly learn "free", which the Occ3D
    labels are everywhere nothing was observed: 0.2 % occupied on the random parity images against 1.1 % masked.)
    Trained in float32 (``--precision fp32``, explicit though it is the CPU default): under bf16 autocast the
    occupied fraction after 80 steps swung from 0.42 % to 1.4 % with the thread count (a CI run fell under the
    tests' 0.5 % floor); float32 gave 0.8–1.2 % at 1 and 2 threads (AVX-512 CPU with native bf16), and float32 runs
    the same arithmetic whether or not a CPU has bf16."""
    from occflownet.cli import main

    root = workdir() / "trained-world"
    if not (root / "v1.0-trainval" / "sample.json").is_file():
        assert main(["synth", "--out", str(root), "--scenes", "1", "--frames", "6", "--seed", "11",
                     "--width", "320", "--height", "180", "--margin", "60", "--no-progress"]) == 0
        assert main(["prepare", "--dataroot", str(root), "--quiet"]) == 0
    run = workdir() / "trained-run"
    if os.environ.get("OCCFLOWNET_TEST_KEEP") and (run / "checkpoints" / "last.pt").is_file():
        return run / "checkpoints" / "last.pt"
    assert main(["train", "--recipe", "quickstart-3d", "--preset", "tiny", "--dataroot", str(root), "--out", str(run),
                 "--split", "all", "--max-steps", "80", "--num-workers", "0", "--quiet", "--seed", "0",
                 "--precision", "fp32"]) == 0
    return run / "checkpoints" / "last.pt"


@functools.lru_cache(maxsize=None)
def exported_trained_tiny():
    """(onnx path, ExportResult, model) of ``trained_tiny_checkpoint()`` exported with the parity check (incl. the
    real frame when present): the model whose grid has occupied voxels, for runtime and path comparisons."""
    from occflownet.export.onnx_export import export_model
    from occflownet.model import load_checkpoint

    model, cfg, _ = load_checkpoint(trained_tiny_checkpoint())
    model.eval()
    frames = [FRAME] if frame_available() else []
    result = export_model(model, cfg, workdir() / "trained-tiny.onnx", parity_frames=frames)
    return result.path, result, model
