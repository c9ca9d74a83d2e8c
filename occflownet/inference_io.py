"""Torch-free inference pieces: image folders, calibration files, the onnxruntime session, grids and BEV pictures.

Imports numpy, OpenCV and (lazily) onnxruntime only, never torch, so `occflownet predict --model` and embedders can
use it on a machine without torch. Names, shapes, metadata, calibration checks and intrinsics rescaling are the
contract's (:mod:`occflownet.contract`): images uint8 [B, 6, H, W, 3] RGB in ``CAMERAS`` order, intrinsics float32
[B, 6, 3, 3], cam2ego float32 [B, 6, 4, 4] → occupancy uint8 [B, 200, 200, 16] ([x, y, z], 17 = free), density
float32 [B, 200, 200, 16].
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from occflownet import contract
from occflownet.config import CAMERAS, CLASS_COLORS, FREE, GRID
from occflownet.contract import METADATA_KEYS, load_calibration  # noqa: F401  (re-exported for callers)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


# ----------------------------------------------------------------------------------------------- inputs
def decode_image(data: bytes, name: str = "image") -> np.ndarray:
    """JPEG/PNG bytes → uint8 RGB [H, W, 3]; ValueError naming ``name`` if it cannot be decoded."""
    import cv2

    buf = np.frombuffer(data, dtype=np.uint8)
    bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
    if bgr is None:
        raise ValueError(f"{name}: not a decodable JPEG/PNG image")
    return np.ascontiguousarray(bgr[:, :, ::-1])


def find_camera_images(folder: str | Path) -> dict[str, Path]:
    """{camera: path} for ``<folder>/<CAMERA>.jpg`` (or .jpeg/.png); FileNotFoundError listing what is missing."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"image folder not found: {folder}")
    found, missing = {}, []
    for cam in CAMERAS:
        hits = [folder / f"{cam}{suf}" for suf in IMAGE_SUFFIXES if (folder / f"{cam}{suf}").is_file()]
        if hits:
            found[cam] = hits[0]
        else:
            missing.append(f"{cam}.jpg")
    if missing:
        raise FileNotFoundError(f"{folder}: missing camera images {missing} (need one file per camera: "
                                f"{', '.join(c + '.jpg' for c in CAMERAS)})")
    return found


def load_image_folder(folder: str | Path) -> np.ndarray:
    """Six camera images of ``folder`` → uint8 [6, H, W, 3] RGB in ``CAMERAS`` order (all the same size)."""
    images = [decode_image(p.read_bytes(), str(p)) for p in find_camera_images(folder).values()]
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        detail = ", ".join(f"{c}: {im.shape[1]}x{im.shape[0]}" for c, im in zip(CAMERAS, images))
        raise ValueError(f"{folder}: camera images differ in size ({detail}); all six must match")
    return np.stack(images)


def calibration_for_images(calib: dict, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(intrinsics float32 [6, 3, 3], cam2ego float32 [6, 4, 4]) for images of ``width × height``: the contract's
    rule (:func:`occflownet.contract.calibration_arrays`; pixel-centre rescaling when the calibration states another
    size of the same aspect ratio, CalibrationError (a ValueError) when the aspect ratio differs)."""
    return contract.calibration_arrays(calib, width, height)


# ----------------------------------------------------------------------------------------------- onnxruntime
def create_session(model_path: str | Path, threads: int | None = None, spinning: bool = False,
                   providers: list[str] | None = None, check_contract: bool = True):
    """An onnxruntime session (CPU by default) with ``threads`` intra-op threads (default: all cores), checked
    against contract v1 (inputs, outputs, metadata) unless ``check_contract=False``. The one place sessions are
    made: predict, eval --model, export parity and variants, and the server.

    ``spinning=False`` lets idle worker threads sleep instead of busy-waiting: on a loaded machine (a server
    sharing its cores, several processes) this cut tiny's p50 from 172 to 125 ms in our measurements; on an idle
    machine spinning can be a few percent faster. Raises FileNotFoundError, ValueError (cannot load) or
    ContractError (a ValueError), each naming the file."""
    import onnxruntime as ort

    model_path = Path(model_path)
    if not model_path.is_file():
        raise FileNotFoundError(f"ONNX model not found: {model_path}")
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads or os.cpu_count() or 1)
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    try:
        session = ort.InferenceSession(str(model_path), so, providers=providers or ["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises several unrelated types for unreadable files
        raise ValueError(f"{model_path}: onnxruntime cannot load this model ({type(exc).__name__}: {exc})") from exc
    if check_contract:
        contract.check_session(session, str(model_path))
    return session


def read_metadata(session) -> dict:
    """The model's metadata_props, JSON-decoded (keys: ``contract.METADATA_KEYS``, plus any others)."""
    return contract.decode_metadata(session.get_modelmeta().custom_metadata_map)


def run_session(session, images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray,
                outputs: tuple[str, ...] = contract.OUTPUT_NAMES):
    """Run the v1 graph. Accepts one sample ([6, ...]) or a batch ([B, 6, ...]); returns the requested outputs
    (default occupancy uint8 [(B,) 200, 200, 16], density float32 [(B,) 200, 200, 16]) at the same rank."""
    single = images.ndim == 4
    if single:
        images, intrinsics, cam2ego = images[None], intrinsics[None], cam2ego[None]
    results = session.run(list(outputs), contract.make_feeds(images, intrinsics, cam2ego))
    return tuple(r[0] for r in results) if single else tuple(results)


# ----------------------------------------------------------------------------------------------- outputs
def save_grid(path: str | Path, occupancy: np.ndarray, density: np.ndarray) -> Path:
    """Write ``occupancy`` uint8 [200, 200, 16] and ``density`` float32 [200, 200, 16] to an .npz file."""
    path = Path(path)
    if occupancy.shape != GRID.shape or density.shape != GRID.shape:
        raise ValueError(f"expected grids of shape {GRID.shape}, got {occupancy.shape} and {density.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, occupancy=occupancy.astype(np.uint8), density=density.astype(np.float32))
    return path


def bev_image(occupancy: np.ndarray, scale: int = 2, mark_ego: bool = True) -> np.ndarray:
    """Top-down picture uint8 [200·scale, 200·scale, 3] RGB of an occupancy grid [200, 200, 16].

    Each column shows the class of its highest non-free voxel (``CLASS_COLORS``; empty columns white, the free
    colour). Orientation: up = +x (forward), left = +y (left), the ego vehicle at the centre.
    """
    occ = np.asarray(occupancy)
    if occ.shape != GRID.shape:
        raise ValueError(f"expected an occupancy grid of shape {GRID.shape}, got {occ.shape}")
    occupied = occ != FREE
    nz = occ.shape[2]
    top = nz - 1 - np.argmax(occupied[:, :, ::-1], axis=2)                  # highest occupied z per column
    labels = np.take_along_axis(occ, top[:, :, None], axis=2)[:, :, 0]
    labels = np.where(occupied.any(axis=2), labels, FREE)
    rgb = CLASS_COLORS[labels]                                                # [x, y, 3]
    rgb = rgb[::-1, ::-1]                                                     # row 0 = max x, column 0 = max y
    rgb = np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1)
    if mark_ego:
        c = rgb.shape[0] // 2
        half = max(1, 2 * scale)
        rgb[c - half:c + half, c - half // 2:c + half // 2] = 0
    return np.ascontiguousarray(rgb)


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image as PNG."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1])):
        raise OSError(f"could not write PNG {path}")
    return path


def class_counts(occupancy: np.ndarray) -> dict[int, int]:
    """{class index: voxel count} over classes 0..17."""
    counts = np.bincount(np.asarray(occupancy).reshape(-1), minlength=FREE + 1)
    return {int(i): int(n) for i, n in enumerate(counts)}
