"""Write an Occ3D ``labels.npz``: byte-reproducible and atomic (the file appears whole or not at all).

Arrays (uint8 [200, 200, 16], [x, y, z], ego frame): ``semantics`` (0..16, 17 free), ``mask_lidar``, ``mask_camera``
(0/1), the Occ3D layout that ``occflownet.data.loaders.load_occupancy`` reads; optional extra arrays (e.g.
``geometry_only``) are ignored by Occ3D readers.
"""
from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np

from occflownet.files import atomic_path


def write_labels_npz(path: Path, semantics: np.ndarray, mask_lidar: np.ndarray, mask_camera: np.ndarray,
                     **extra: np.ndarray) -> None:
    """Write an Occ3D ``labels.npz`` at ``path`` (see ``write_uint8_npz``)."""
    write_uint8_npz(path, semantics=semantics, mask_lidar=mask_lidar, mask_camera=mask_camera, **extra)


def write_uint8_npz(path: Path, **arrays: np.ndarray) -> None:
    """Write uint8 ``arrays`` to the .npz ``path`` atomically; identical arrays give identical bytes (fixed zip
    timestamps, unlike ``np.savez``)."""
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for key, arr in arrays.items():
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.ascontiguousarray(arr, dtype=np.uint8), allow_pickle=False)
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                zf.writestr(info, buf.getvalue())
