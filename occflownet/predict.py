"""Prediction for one set of six camera images: the inputs, the model (ONNX file or torch), the outputs.

Inputs: a folder with one image per camera (``<CAMERA>.jpg``/``.jpeg``/``.png``) → uint8 [6, H, W, 3] RGB in
``CAMERAS`` order; calibration and sessions are the contract's (:mod:`occflownet.contract`). Outputs: occupancy
uint8 [200, 200, 16] ([x, y, z] of the ego frame, 17 = free) and density float32 [200, 200, 16], written as one
.npz, and per-class counts. This module imports numpy at import time, OpenCV when it decodes an image and torch
only inside :func:`model_from_source` and :func:`predict_torch`, so the onnxruntime path runs without torch.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from occflownet.contract import decode_rgb
from occflownet.occ3d import CAMERAS, FREE, GRID

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


# ----------------------------------------------------------------------------------------------- inputs
def decode_image(data: bytes, name: str = "image") -> np.ndarray:
    """JPEG/PNG bytes → uint8 RGB [H, W, 3] by the contract's rule (:func:`occflownet.contract.decode_rgb`: EXIF
    orientation ignored); ValueError naming ``name`` if it cannot be decoded."""
    rgb = decode_rgb(data)
    if rgb is None:
        raise ValueError(f"{name}: not a decodable JPEG/PNG image")
    return rgb


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


# ----------------------------------------------------------------------------------------------- torch model
def model_from_source(checkpoint: str | Path | None = None, preset: str | None = None, seed: int | None = None):
    """An ``OccupancyModel`` in eval mode from a checkpoint, or a randomly initialised preset (seeded: same seed →
    same weights)."""
    from occflownet.model import create_model, get_preset, load_checkpoint

    if checkpoint is not None:
        model, _, _ = load_checkpoint(checkpoint)
        return model.eval()
    if preset is None:
        raise ValueError("need a checkpoint or a preset")
    return create_model(get_preset(preset), seed=0 if seed is None else seed).eval()


def predict_torch(model, images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray):
    """One sample through the torch model: images uint8 [6, H, W, 3], intrinsics [6, 3, 3], cam2ego [6, 4, 4] →
    (occupancy uint8 [200, 200, 16], density float32 [200, 200, 16]); the same as the exported graph up to float
    rounding."""
    import torch

    with torch.no_grad():
        occ, dens = model.inference(torch.from_numpy(np.ascontiguousarray(images))[None],
                                    torch.from_numpy(np.asarray(intrinsics, dtype=np.float32))[None],
                                    torch.from_numpy(np.asarray(cam2ego, dtype=np.float32))[None])
    return occ[0].numpy(), dens[0].numpy()


# ----------------------------------------------------------------------------------------------- outputs
def save_grid(path: str | Path, occupancy: np.ndarray, density: np.ndarray) -> Path:
    """Write ``occupancy`` uint8 [200, 200, 16] and ``density`` float32 [200, 200, 16] to an .npz file."""
    path = Path(path)
    if occupancy.shape != GRID.shape or density.shape != GRID.shape:
        raise ValueError(f"expected grids of shape {GRID.shape}, got {occupancy.shape} and {density.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, occupancy=occupancy.astype(np.uint8), density=density.astype(np.float32))
    return path


def class_counts(occupancy: np.ndarray) -> dict[int, int]:
    """{class index: voxel count} over classes 0..17."""
    counts = np.bincount(np.asarray(occupancy).reshape(-1), minlength=FREE + 1)
    return {int(i): int(n) for i, n in enumerate(counts)}
