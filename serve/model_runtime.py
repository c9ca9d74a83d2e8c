"""The ONNX model behind the server: an onnxruntime session, its contract-v1 metadata, warm-up and inference.

Everything model-specific the server uses (cameras, classes, grid, colours, default calibration) comes from the
model file's ``metadata_props`` (JSON values, docs/contracts.md), never from the training code.

Contract v1 (checked at load time by :func:`occflownet.contract.check_session`, the same check as predict's and
eval's; the session is made by :func:`occflownet.contract.create_session`):
- inputs  ``images`` uint8 [B, 6, H, W, 3] RGB, ``intrinsics`` float32 [B, 6, 3, 3] (for that H×W),
  ``cam2ego`` float32 [B, 6, 4, 4] (OpenCV camera frame → ego frame);
- outputs ``occupancy`` uint8 [B, X, Y, Z] (classes, ``free_index`` = free), ``density`` float32 [B, X, Y, Z].
"""
from __future__ import annotations

import hashlib
import threading
import time
from pathlib import Path

import numpy as np

from occflownet.contract import ContractError, ModelMetadata, check_session, make_feeds
from occflownet.serve.calibration import request_calibration
from occflownet.serve.decode import intrinsics_for_size
from occflownet.serve.settings import ServeSettings

__all__ = ["ModelLoadError", "ModelRuntime"]


class ModelLoadError(RuntimeError):
    """The model file is missing, unreadable, not ONNX, or breaks contract v1; the message names the file."""


class ModelRuntime:
    """One onnxruntime session plus its metadata. ``infer`` is thread-safe (ORT sessions allow concurrent runs)."""

    def __init__(self, session, metadata: ModelMetadata, path: Path, sha256: str):
        self.session = session
        self.metadata = metadata
        self.path = path
        self.sha256 = sha256
        self.ready = threading.Event()
        self.warmup_error: str | None = None
        self.warmup_seconds: float | None = None
        # (W, H) when the graph fixes the image size (contract v1 allows any; an export may still pin it), else None
        shape = next(a.shape for a in session.get_inputs() if a.name == "images")
        self.fixed_image_size = (shape[3], shape[2]) if all(isinstance(d, int) for d in shape[2:4]) else None

    @classmethod
    def load(cls, path: str | Path, settings: ServeSettings) -> "ModelRuntime":
        """Open ``path`` with onnxruntime and check contract v1. Raises ModelLoadError naming the file."""
        path = Path(path)
        if not str(path):
            raise ModelLoadError("no model given: pass --model FILE or set OCCFLOWNET_MODEL")
        if not path.is_file():
            raise ModelLoadError(f"model file not found: {path}")
        from occflownet.contract import create_session

        settings = settings.resolved()
        try:
            session = create_session(path, settings.intra_op_threads, spinning=settings.ort_spin,
                                     providers=settings.providers, check_contract=False)
        except (ValueError, OSError) as exc:
            reason = str(exc).removeprefix(f"{path}: ")
            raise ModelLoadError(f"cannot load model {path}: {reason}") from None
        try:
            metadata = check_session(session, str(path))
        except ContractError as exc:
            raise ModelLoadError(str(exc)) from None
        digest = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        return cls(session, metadata, path, digest.hexdigest())

    def infer(self, images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray) -> np.ndarray:
        """One frame: images uint8 [6, H, W, 3] RGB, intrinsics float32 [6, 3, 3] for H×W, cam2ego float32
        [6, 4, 4] → occupancy uint8 [X, Y, Z] (ego frame, [x, y, z], ``free_index`` = free)."""
        (occ,) = self.session.run(["occupancy"], make_feeds(images[None], intrinsics[None], cam2ego[None]))
        if occ.dtype != np.uint8 or occ.shape != (1, *self.metadata.grid_shape):
            raise RuntimeError(f"model returned occupancy {occ.dtype} {occ.shape}, metadata promises uint8 "
                               f"{(1, *self.metadata.grid_shape)}")
        return occ[0]

    def warm_up(self) -> None:
        """Run one inference as a request without a calibration part would: black uint8 [6, h, w, 3] images of the
        default calibration's size (or the graph's fixed size), the default calibration. Sets ``ready`` on success."""
        size = tuple(int(v) for v in self.metadata.default_calibration["image_size"])
        w, h = self.fixed_image_size or size
        t0 = time.perf_counter()
        try:
            K, T = request_calibration(None, self.metadata, [size] * 6)
            self.infer(np.zeros((6, h, w, 3), np.uint8), intrinsics_for_size(K, [size] * 6, (w, h)), T)
        except Exception as exc:
            self.warmup_error = f"warm-up inference failed: {type(exc).__name__}: {exc}"
            raise
        self.warmup_seconds = time.perf_counter() - t0
        self.ready.set()
