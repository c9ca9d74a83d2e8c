"""Load the data files of a sample: camera images, LiDAR sweeps, lidarseg labels, Occ3D occupancy.

Each loader takes the dataroot and a path relative to it (as stored in the index) and raises
``DatasetError`` naming the file when it is missing or malformed; nothing is skipped silently.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract import decode_rgb
from occflownet.occ3d import FREE, GRID
from occflownet.data.tables import DatasetError

LIDAR_FIELDS = 5  # x, y, z, intensity, ring (float32) per point in nuScenes .pcd.bin


def _existing(dataroot, rel_path: str, what: str) -> Path:
    if rel_path is None:
        raise DatasetError(f"no {what} file recorded for this sample")
    path = Path(dataroot) / rel_path
    if not path.is_file():
        raise DatasetError(f"{path}: {what} file is missing")
    return path


def load_image(dataroot, rel_path: str, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """An image file → uint8 [H, W, 3] RGB (the contract's rule: EXIF orientation ignored). ``expected_size``
    (width, height): error if the file differs."""
    path = _existing(dataroot, rel_path, "image")
    rgb = decode_rgb(path.read_bytes())
    if rgb is None:
        raise DatasetError(f"{path}: cannot decode image")
    if expected_size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(expected_size):
        raise DatasetError(f"{path}: image is {rgb.shape[1]}x{rgb.shape[0]}, the tables say "
                           f"{expected_size[0]}x{expected_size[1]}")
    return rgb


def load_sample_images(dataroot, sample) -> np.ndarray:
    """The six camera images of a SampleRecord → uint8 [6, H, W, 3] RGB in camera order (sizes must agree)."""
    images = [load_image(dataroot, c.path, (c.width, c.height)) for c in sample.cameras]
    if len({im.shape for im in images}) != 1:
        raise DatasetError(f"sample {sample.token}: camera images differ in size "
                           f"({', '.join(f'{c.name} {im.shape[1]}x{im.shape[0]}' for c, im in zip(sample.cameras, images))})")
    return np.stack(images)


def load_lidar(dataroot, rel_path: str) -> np.ndarray:
    """A nuScenes ``.pcd.bin`` → float32 [N, 5] (x, y, z, intensity, ring), LiDAR frame."""
    path = _existing(dataroot, rel_path, "LiDAR")
    raw = np.fromfile(path, dtype=np.float32)
    if raw.size % LIDAR_FIELDS:
        raise DatasetError(f"{path}: {raw.size} float32 values is not a multiple of {LIDAR_FIELDS} (x,y,z,i,ring)")
    points = raw.reshape(-1, LIDAR_FIELDS)
    if not np.isfinite(points[:, :3]).all():
        raise DatasetError(f"{path}: LiDAR coordinates contain NaN or inf")
    return points


def load_lidarseg(dataroot, rel_path: str, num_points: int) -> np.ndarray:
    """A nuScenes-lidarseg ``.bin`` → raw category indices uint8 [N]; must hold exactly ``num_points`` labels."""
    path = _existing(dataroot, rel_path, "lidarseg")
    labels = np.fromfile(path, dtype=np.uint8)
    if labels.size != num_points:
        raise DatasetError(f"{path}: {labels.size} labels for a sweep of {num_points} points")
    return labels


@dataclass(frozen=True)
class Occupancy:
    """Occ3D ground truth, each uint8 [200, 200, 16] indexed [x, y, z] in the current ego frame."""

    semantics: np.ndarray    # classes 0..16, 17 = free
    mask_lidar: np.ndarray   # 0/1
    mask_camera: np.ndarray  # 0/1 (the evaluation mask)


def load_occupancy(dataroot, rel_path: str) -> Occupancy:
    """An Occ3D ``labels.npz`` → :class:`Occupancy`, with keys, dtypes, shapes and value ranges checked."""
    path = _existing(dataroot, rel_path, "Occ3D labels")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {}
            for key in ("semantics", "mask_lidar", "mask_camera"):
                if key not in z.files:
                    raise DatasetError(f"{path}: lacks array '{key}' (has {', '.join(z.files)})")
                arrays[key] = z[key]
    except (OSError, ValueError) as e:
        if isinstance(e, DatasetError):
            raise
        raise DatasetError(f"{path}: cannot read as .npz ({e})") from e
    for key, a in arrays.items():
        if a.shape != GRID.shape:
            raise DatasetError(f"{path}: '{key}' has shape {a.shape}, expected {GRID.shape}")
        if a.dtype != np.uint8:
            raise DatasetError(f"{path}: '{key}' has dtype {a.dtype}, expected uint8")
    if arrays["semantics"].max() > FREE:
        raise DatasetError(f"{path}: 'semantics' holds class {arrays['semantics'].max()} > {FREE}")
    for key in ("mask_lidar", "mask_camera"):
        if arrays[key].max() > 1:
            raise DatasetError(f"{path}: '{key}' must be 0/1, holds {arrays[key].max()}")
    return Occupancy(**arrays)
