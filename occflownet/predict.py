"""Prediction for one set of six camera images: the image folder, the frame as the inference paths decode it, outputs.

Inputs: a folder with one image per camera (``<CAMERA>.jpg``/``.jpeg``/``.png``) → uint8 [6, H, W, 3] RGB in
``CAMERAS`` order (:func:`load_frame`: JPEGs at reduced scale for the model's input size, images of another size
resized to the common one, as the server does), and with its calibration
→ the model's inputs (:meth:`Frame.inputs`, :func:`occflownet.runtime.frame_inputs`); the model is an
:class:`occflownet.runtime.Predictor` (ONNX or torch). Outputs: occupancy uint8 [200, 200, 16] ([x, y, z] of the ego
frame, 17 = free) and density float32 [200, 200, 16], written as one .npz, and per-class counts. Shipping wing: this
module imports numpy (OpenCV when it decodes an image), never torch.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract import common_size, decode_reduction, decode_rgb, image_header, reduced_size, resize_rgb
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
    order at one size (w, h); per camera, ``sizes`` the (w, h) of its file as stored and ``reductions`` the n it
    was decoded at, 1/n (the contract's reduced-scale JPEG rule, :func:`occflownet.contract.decode_reduction`;
    1 = whole). An image whose decoded size is not (w, h) was resized to it
    (:func:`occflownet.contract.resize_rgb`)."""

    images: np.ndarray
    sizes: tuple[tuple[int, int], ...]
    reductions: tuple[int, ...]

    @property
    def reduction(self) -> int:
        """The n every camera was decoded at (1/n); ValueError when they differ."""
        if len(set(self.reductions)) != 1:
            raise ValueError(f"the cameras were decoded at different scales {list(self.reductions)}")
        return self.reductions[0]

    def inputs(self, calib: dict) -> ModelInputs:
        """The model's inputs for this frame (a batch of one) with calibration JSON ``calib`` (for each camera's
        stored size or one of its aspect ratio): intrinsics rescaled from the stored size by 1/n and to (w, h) in
        one step (:func:`occflownet.runtime.frame_inputs`)."""
        return frame_inputs(self.images, calib, sizes=self.sizes, reductions=self.reductions)


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
    """Six camera images of ``folder`` as every inference path decodes them for a model whose network input is
    ``input_size`` [H, W]: each JPEG at its own reduced scale (:func:`occflownet.contract.decode_reduction`; PNGs
    and, with ``input_size=None``, every image whole), then any image whose decoded size differs from the one most
    of them have resized to it (:func:`occflownet.contract.common_size`, :func:`~occflownet.contract.resize_rgb`),
    as the server does; the six decode in parallel threads. ValueError naming the file that cannot be decoded."""
    blobs = [(p.read_bytes(), str(p)) for p in find_camera_images(folder).values()]
    headers = []
    for data, name in blobs:
        try:
            headers.append(image_header(data))
        except ValueError as exc:
            raise ValueError(f"{name}: not a decodable JPEG/PNG image ({exc})") from None
    reductions = [decode_reduction(hd, input_size) for hd in headers]
    decoded = [reduced_size(hd.width, hd.height, n) for hd, n in zip(headers, reductions)]
    w, h = common_size(decoded)
    images = np.empty((len(blobs), h, w, 3), np.uint8)

    def decode(i: int) -> None:                          # image i into images[i]
        (data, name), n, size = blobs[i], reductions[i], decoded[i]
        rgb = decode_image(data, name, n)
        if (rgb.shape[1], rgb.shape[0]) != size:
            raise ValueError(f"{name}: decoded size {rgb.shape[1]}x{rgb.shape[0]} disagrees with its header's "
                             f"{headers[i].width}x{headers[i].height} at 1/{n}")
        resize_rgb(rgb, (w, h), out=images[i])

    # one thread per image: the decoder (OpenCV) releases the GIL, so the images decode in parallel; the first
    # failing image in camera order raises
    with ThreadPoolExecutor(max_workers=len(blobs)) as pool:
        list(pool.map(decode, range(len(blobs))))
    return Frame(images, tuple((hd.width, hd.height) for hd in headers), tuple(reductions))


def load_image_folder(folder: str | Path) -> np.ndarray:
    """Six camera images of ``folder``, all of one size, → uint8 [6, H, W, 3] RGB in ``CAMERAS`` order, decoded
    whole (images of different sizes: :func:`load_frame`, whose intrinsics follow the resize). ValueError naming
    the sizes when they differ."""
    frame = load_frame(folder)
    if len(set(frame.sizes)) != 1:
        detail = ", ".join(f"{c}: {w}x{h}" for c, (w, h) in zip(CAMERAS, frame.sizes))
        raise ValueError(f"{folder}: camera images differ in size ({detail}); all six must match")
    return frame.images


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
