"""Prediction for one set of six camera images: the image folder, the frame as the inference paths decode it, outputs.

Inputs: a folder with one image per camera (``<CAMERA>.jpg``/``.jpeg``/``.png``) → uint8 [6, H, W, 3] RGB in
``CAMERAS`` order (:func:`load_frame`: JPEGs at reduced scale for the model's input size), and with its calibration
→ the model's inputs (:meth:`Frame.inputs`, :func:`occflownet.runtime.frame_inputs`); the model is an
:class:`occflownet.runtime.Predictor` (ONNX or torch). Outputs: occupancy uint8 [200, 200, 16] ([x, y, z] of the ego
frame, 17 = free) and density float32 [200, 200, 16], written as one .npz, and per-class counts. Shipping wing: this
module imports numpy (OpenCV when it decodes an image), never torch.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract import decode_reduction, decode_rgb, image_header
from occflownet.occ3d import CAMERAS, FREE, GRID
from occflownet.runtime import ModelInputs, frame_inputs

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

    def inputs(self, calib: dict) -> ModelInputs:
        """The model's inputs for this frame (a batch of one) with calibration JSON ``calib`` (for the stored size
        or one of its aspect ratio): the intrinsics for the decoded images, scaled by 1/``reduction`` exactly
        (:func:`occflownet.runtime.frame_inputs`)."""
        return frame_inputs(self.images, calib, sizes=[self.stored_size] * len(self.images),
                            reductions=[self.reduction] * len(self.images))


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
