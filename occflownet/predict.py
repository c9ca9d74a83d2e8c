"""Prediction for one set of six camera images: the inputs, the model (ONNX file or torch), the outputs.

Inputs: a folder with one image per camera (``<CAMERA>.jpg``/``.jpeg``/``.png``) → uint8 [6, H, W, 3] RGB in
``CAMERAS`` order; calibration and sessions are the contract's (:mod:`occflownet.contract`). Outputs: occupancy
uint8 [200, 200, 16] ([x, y, z] of the ego frame, 17 = free) and density float32 [200, 200, 16], written as one
.npz, and per-class counts. This module imports numpy at import time, OpenCV when it decodes an image and torch
only inside :func:`model_from_source` and :func:`predict_torch`, so the onnxruntime path runs without torch.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract import calibration_arrays, decode_reduction, decode_rgb, image_header
from occflownet.occ3d import CAMERAS, FREE, GRID

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


# ----------------------------------------------------------------------------------------------- inputs
def decode_image(data: bytes, name: str = "image", reduction: int = 1) -> np.ndarray:
    """JPEG/PNG bytes → uint8 RGB [H, W, 3] by the contract's rule (:func:`occflownet.contract.decode_rgb`: EXIF
    orientation ignored; a JPEG at 1/``reduction``); ValueError naming ``name`` if it cannot be decoded."""
    rgb = decode_rgb(data, reduction)
    if rgb is None:
        raise ValueError(f"{name}: not a decodable JPEG/PNG image")
    return rgb


@dataclass(frozen=True)
class Frame:
    """Six camera images as an inference path decodes them: ``images`` uint8 [6, h, w, 3] RGB in ``CAMERAS``
    order, decoded at 1/``reduction`` from files of ``stored_size`` (W, H) (the contract's reduced-scale JPEG
    rule, :func:`occflownet.contract.decode_reduction`; 1 = whole)."""

    images: np.ndarray
    stored_size: tuple[int, int]
    reduction: int

    def calibration_arrays(self, calib: dict) -> tuple[np.ndarray, np.ndarray]:
        """(intrinsics float32 [6, 3, 3] for the decoded images, cam2ego float32 [6, 4, 4]) from calibration JSON
        (for the stored size or one of its aspect ratio; scaled by 1/``reduction`` exactly)."""
        w, h = self.stored_size
        return calibration_arrays(calib, w, h, reduction=self.reduction)


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


def load_frame(folder: str | Path, input_size: tuple[int, int] | None = None) -> Frame:
    """Six camera images of ``folder`` (all the same size) as the inference paths decode them for a model whose
    network input is ``input_size`` [H, W] (JPEGs at reduced scale, :func:`occflownet.contract.decode_reduction`);
    ``input_size=None`` decodes every image whole."""
    blobs = [(p.read_bytes(), str(p)) for p in find_camera_images(folder).values()]
    headers = []
    for data, name in blobs:
        try:
            headers.append(image_header(data))
        except ValueError as exc:
            raise ValueError(f"{name}: not a decodable JPEG/PNG image ({exc})") from None
    reductions = [decode_reduction(hd, input_size) for hd in headers]
    sizes = {(hd.width, hd.height, n) for hd, n in zip(headers, reductions)}
    if len(sizes) != 1:
        detail = ", ".join(f"{c}: {hd.width}x{hd.height} {hd.format}" for c, hd in zip(CAMERAS, headers))
        raise ValueError(f"{folder}: camera images differ in size ({detail}); all six must match")
    images = [decode_image(data, name, n) for (data, name), n in zip(blobs, reductions)]
    if len({im.shape for im in images}) != 1:
        detail = ", ".join(f"{c}: {im.shape[1]}x{im.shape[0]}" for c, im in zip(CAMERAS, images))
        raise ValueError(f"{folder}: camera images differ in size ({detail}); all six must match")
    return Frame(np.stack(images), (headers[0].width, headers[0].height), reductions[0])


def load_image_folder(folder: str | Path) -> np.ndarray:
    """Six camera images of ``folder`` → uint8 [6, H, W, 3] RGB in ``CAMERAS`` order, decoded whole (all the same
    size)."""
    return load_frame(folder).images


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
