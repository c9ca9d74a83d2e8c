"""The ONNX model behind the server: an onnxruntime predictor, its contract-v1 metadata, warm-up and inference.

Everything model-specific the server uses (cameras, classes, grid, colours, default calibration) comes from the
model file's ``metadata_props`` (JSON values, docs/contracts.md), never from the training code.

Contract v1 (checked at load time by :func:`occflownet.contract.check_session`, the same check as predict's and
eval's; the session is made by :func:`occflownet.contract.create_session` and run by the one predictor path,
:class:`occflownet.runtime.OnnxPredictor`):
- inputs  ``images`` uint8 [B, 6, H, W, 3] RGB, ``intrinsics`` float32 [B, 6, 3, 3] (for that H×W),
  ``cam2ego`` float32 [B, 6, 4, 4] (OpenCV camera frame → ego frame);
- outputs ``occupancy`` uint8 [B, X, Y, Z] (classes, ``free_index`` = free), ``density`` float32 [B, X, Y, Z].

A request and the warm-up take the same path: :meth:`ModelRuntime.frame` (the tensor size and its calibration,
before any pixel is decoded), :meth:`~occflownet.runtime.FrameCalibration.inputs` (the decoded images),
:meth:`ModelRuntime.infer`.
"""
from __future__ import annotations

import hashlib
import threading
import time
from pathlib import Path

import numpy as np

from occflownet.contract import ContractError, check_session, reduced_size
from occflownet.runtime import FrameCalibration, ModelInputs, OnnxPredictor
from occflownet.serve.calibration import request_calibration
from occflownet.serve.decode import common_size
from occflownet.serve.settings import ServeSettings

__all__ = ["ModelLoadError", "ModelRuntime", "check_providers"]


class ModelLoadError(RuntimeError):
    """The model file is missing, unreadable, not ONNX, or breaks contract v1, or an execution provider asked for is
    not available; the message names the file (or the provider)."""


def check_providers(providers: list[str]) -> None:
    """ModelLoadError unless every one of ``providers`` is an execution provider of this onnxruntime build (a
    misspelt name, or a GPU provider in a CPU-only install, would otherwise fall back to the CPU with only a Python
    warning)."""
    import onnxruntime as ort

    available = ort.get_available_providers()
    missing = [p for p in providers if p not in available]
    if missing:
        known = set(ort.get_all_providers())
        what = ", ".join(f"{p} ({'not in this onnxruntime build' if p in known else 'unknown name'})"
                         for p in missing)
        raise ModelLoadError(f"OCCFLOWNET_PROVIDERS / --providers: {what}; available here: {', '.join(available)}")


def _file_sha256(path: Path) -> str:
    """SHA-256 (hex) of the file at ``path``; ModelLoadError naming it when it is missing, a folder or unreadable
    (an OSError's own words: "permission denied" where onnxruntime would say "system error number 13")."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    except FileNotFoundError:
        raise ModelLoadError(f"model file not found: {path}") from None
    except PermissionError:
        raise ModelLoadError(f"cannot read model {path}: permission denied") from None
    except IsADirectoryError:
        raise ModelLoadError(f"model {path} is a folder, not a file") from None
    except OSError as exc:
        raise ModelLoadError(f"cannot read model {path}: {exc.strerror or exc}") from None
    return digest.hexdigest()


class ModelRuntime:
    """One onnxruntime predictor plus its metadata. ``infer`` is thread-safe (ORT sessions allow concurrent runs)."""

    def __init__(self, predictor: OnnxPredictor, path: Path, sha256: str):
        self.predictor = predictor
        self.metadata = predictor.metadata
        self.path = path
        self.sha256 = sha256
        self.ready = threading.Event()
        self.warmup_error: str | None = None
        self.warmup_seconds: float | None = None
        # (W, H) when the graph fixes the image size (contract v1 allows any; an export may still pin it), else None
        shape = next(a.shape for a in predictor.session.get_inputs() if a.name == "images")
        self.fixed_image_size = (shape[3], shape[2]) if all(isinstance(d, int) for d in shape[2:4]) else None

    @classmethod
    def load(cls, path: str | Path, settings: ServeSettings) -> "ModelRuntime":
        """Open ``path`` with onnxruntime and check contract v1. Raises ModelLoadError naming the file: not found,
        permission denied (the file or a folder on its path), not ONNX, breaking the contract; or naming the
        execution providers asked for that this onnxruntime does not have."""
        path = Path(path)
        if not str(path):
            raise ModelLoadError("no model given: pass --model FILE or set OCCFLOWNET_MODEL")
        settings = settings.resolved()
        check_providers(settings.providers)
        sha256 = _file_sha256(path)  # reads the file first: a file we cannot read is named as such
        from occflownet.contract import create_session

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
        return cls(OnnxPredictor(session, metadata), path, sha256)

    def frame(self, part: bytes | None, sizes: list[tuple[int, int]], reductions: list[int] | None = None
              ) -> FrameCalibration:
        """One frame's calibration, before its images are decoded: the image tensor's (w, h) — the graph's fixed
        size, else the size most of the decoded images have (:func:`common_size`) — and the intrinsics for it
        (:func:`request_calibration`: the ``calibration`` part, None for the model's default). ``sizes``: each
        image's (w, h) as sent; ``reductions``: the 1/n each is decoded at. CalibrationError naming the camera."""
        reductions = [1] * len(sizes) if reductions is None else reductions
        decoded = [reduced_size(w, h, n) for (w, h), n in zip(sizes, reductions)]
        size = self.fixed_image_size or common_size(decoded)
        return request_calibration(part, self.metadata, sizes, reductions, size)

    def infer(self, inputs: ModelInputs) -> np.ndarray:
        """One frame (ModelInputs of a batch of one, :meth:`frame`'s ``inputs``) → occupancy uint8 [X, Y, Z] (ego
        frame, [x, y, z], ``free_index`` = free)."""
        (occ,) = self.predictor.predict(inputs, ("occupancy",))
        if occ.dtype != np.uint8 or occ.shape != (1, *self.metadata.grid_shape):
            raise RuntimeError(f"model returned occupancy {occ.dtype} {occ.shape}, metadata promises uint8 "
                               f"{(1, *self.metadata.grid_shape)}")
        return occ[0]

    def warm_up(self) -> None:
        """Run one inference as a request without a calibration part would, through the same :meth:`frame` and
        :meth:`infer`: six black images at the default calibration's size. Sets ``ready`` on success."""
        size = tuple(int(v) for v in self.metadata.default_calibration["image_size"])
        t0 = time.perf_counter()
        try:
            frame = self.frame(None, [size] * len(self.metadata.cameras))
            self.infer(frame.inputs(np.zeros(frame.image_shape, np.uint8)))
        except Exception as exc:
            self.warmup_error = f"warm-up inference failed: {type(exc).__name__}: {exc}"
            raise
        self.warmup_seconds = time.perf_counter() - t0
        self.ready.set()
