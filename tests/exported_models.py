"""Shared, expensive test fixtures of the model/export/predict tests: one exported tiny model per test session.

Imported by tests/test_export_*.py and tests/test_predict.py; the export runs once per pytest process (lru_cache)
into a temporary folder that is removed at exit.
"""
from __future__ import annotations

import atexit
import functools
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
    path = Path(tempfile.mkdtemp(prefix="occflownet-export-tests-"))
    atexit.register(shutil.rmtree, path, True)
    return path


@functools.lru_cache(maxsize=None)
def exported_tiny():
    """(onnx path, ExportResult, model) of a random-init tiny (seed SEED), parity-checked incl. the real frame."""
    from export.onnx_export import export_model
    from occflownet.model import create_model, get_preset

    model = create_model(get_preset("tiny"), seed=SEED).eval()
    frames = [FRAME] if frame_available() else []
    result = export_model(model, model.cfg, workdir() / "tiny.onnx", parity_frames=frames)
    return result.path, result, model
