"""Pictures of occupancy grids, numpy + OpenCV only (no torch): the top-down view, the class legend, PNG files.

One top-down rule for every picture the package draws (``predict --png``, the server's ``image/png``, the
synthetic world's preview, the side-by-side of ``quickstart``): each (x, y) column of a grid uint8 [X, Y, Z]
([x, y, z] of the ego frame, ``free_index`` = free) takes the colour of its highest non-free voxel. Orientation:
image up = +x (forward), image left = +y (left), the ego vehicle marked at the centre.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from occflownet.occ3d import CLASS_COLORS, CLASS_NAMES, FREE


def top_down(occupancy: np.ndarray, colors: np.ndarray = CLASS_COLORS, free_index: int = FREE, scale: int = 2,
             mask: np.ndarray | None = None, empty: Sequence[int] | None = None,
             ego: Sequence[int] | None = (0, 0, 0)) -> np.ndarray:
    """RGB uint8 [X·scale, Y·scale, 3] of ``occupancy`` [X, Y, Z] (see the module docstring).

    colors: uint8 [free_index + 1 or more, 3] per class. mask: optional bool/uint8 [X, Y, Z] (e.g. ``mask_camera``);
    a column whose top voxel lies outside it is dimmed to 40 %. empty: colour of columns with no occupied voxel
    (default ``colors[free_index]``). ego: colour of the ego mark (a 2·scale × 2·scale square), None = no mark.
    """
    occ = np.asarray(occupancy)
    if occ.ndim != 3:
        raise ValueError(f"expected an occupancy grid [X, Y, Z], got shape {occ.shape}")
    occupied = occ != free_index
    any_occupied = occupied.any(axis=2)
    top_z = occ.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)        # highest occupied z per column
    top = np.where(any_occupied, np.take_along_axis(occ, top_z[..., None], axis=2)[..., 0], free_index)
    rgb = np.asarray(colors, dtype=np.float32)[top]
    if empty is not None:
        rgb[~any_occupied] = empty
    if mask is not None:
        seen = np.take_along_axis(np.asarray(mask), top_z[..., None], axis=2)[..., 0] > 0
        rgb[any_occupied & ~seen] *= 0.4
    rgb = rgb[::-1, ::-1]                                                       # row 0 = max x, column 0 = max y
    rgb = np.repeat(np.repeat(rgb, scale, axis=0), scale, axis=1).astype(np.uint8)
    if ego is not None:
        cx, cy = rgb.shape[0] // 2, rgb.shape[1] // 2
        rgb[cx - scale:cx + scale, cy - scale:cy + scale] = ego
    return np.ascontiguousarray(rgb)


def class_legend(width: int, names: Sequence[str] = CLASS_NAMES, colors: np.ndarray = CLASS_COLORS,
                 count: int = FREE, columns: int = 6, background: int = 255) -> np.ndarray:
    """RGB uint8 [rows · 22 + 6, width, 3]: a swatch and the name of classes 0..count-1, ``columns`` per row; text
    black on a light background, white on a dark one."""
    import cv2

    row_h = 22
    rows = int(np.ceil(count / columns))
    out = np.full((rows * row_h + 6, width, 3), background, np.uint8)
    ink = (0, 0, 0) if background >= 128 else (230, 230, 230)
    cell = width // columns
    for c in range(count):
        x, y = (c % columns) * cell + 6, (c // columns) * row_h + 4
        out[y:y + 14, x:x + 14] = colors[c]
        cv2.putText(out, names[c], (x + 18, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.42, ink, 1, cv2.LINE_AA)
    return out


def encode_png(rgb: np.ndarray) -> bytes:
    """RGB uint8 [H, W, 3] → PNG bytes."""
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(np.asarray(rgb)[:, :, ::-1]))
    if not ok:  # pragma: no cover - imencode of a plain uint8 image does not fail
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 image [H, W, 3] as PNG (creating the folder); OSError naming the file if it cannot."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        path.write_bytes(encode_png(rgb))
    except OSError as exc:
        raise OSError(f"could not write PNG {path}: {exc}") from None
    return path
