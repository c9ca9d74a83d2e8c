"""Which voxels of the grid lie inside a (slightly enlarged) 3D box — numpy only, no torch.

Frames: the box and the grid are both given in the *ego frame of the current keyframe* (x forward, y left,
z up, metres). nuScenes box sizes are ``wlh``: width ``w`` along the box's own y axis, length ``l`` along its x
axis, height ``h`` along its z axis; the box centre is the centre of the cuboid.

Enlargement (the official OccFlowNet ``Boxes.corners(wlh_factor=1.15)`` with ``box_padding = 0.4``):
every full edge length becomes ``size * margin_scale + margin_add``, i.e. ``l' = 1.15 l + 0.4`` m, so each face
moves outward by ``0.075 l + 0.2`` m. A voxel belongs to the box when its *centre* lies inside the enlarged
cuboid, boundary included (``|local| <= half extent``, as the official ``points_in_boxes``).
"""
from __future__ import annotations

import numpy as np

from ..occ3d import GRID, Grid
from ..geometry import quaternion_to_matrix

MARGIN_SCALE = 1.15  # official wlh_factor
MARGIN_ADD = 0.4  # official box_padding (metres, added to each full edge length)


def box_rotation(rotation) -> np.ndarray:
    """A box orientation as a 3×3 rotation matrix (box frame → ego frame).

    ``rotation`` is a 3×3 matrix, a quaternion (w, x, y, z) [4], or a yaw angle in radians (scalar, about +z).
    """
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape == ():
        c, s = np.cos(float(r)), np.sin(float(r))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if r.shape == (4,):
        if not np.all(np.isfinite(r)) or np.linalg.norm(r) < 1e-9:
            raise ValueError(f"box rotation quaternion must be finite and non-zero, got {r.tolist()}")
        return quaternion_to_matrix(r)
    if r.shape == (3, 3):
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-4):
            raise ValueError("box rotation matrix is not orthonormal")
        return r
    raise ValueError(f"box rotation must be a yaw scalar, a quaternion [4] or a 3x3 matrix, got shape {r.shape}")


def enlarged_extent(size_wlh, margin_scale: float = MARGIN_SCALE, margin_add: float = MARGIN_ADD) -> np.ndarray:
    """Full edge lengths of the enlarged box along the box's own (x, y, z) axes: ``[l', w', h']`` metres.

    ``size_wlh`` [3] is nuScenes (w, l, h); the result is reordered to the box axes (x: length, y: width, z: height)
    and enlarged as ``size * margin_scale + margin_add``.
    """
    w, l, h = np.asarray(size_wlh, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite([w, l, h])) or min(w, l, h) < 0:
        raise ValueError(f"box size_wlh must be finite and non-negative, got {[w, l, h]}")
    return np.array([l, w, h]) * margin_scale + margin_add


def voxels_in_box(center, size_wlh, rotation, margin_scale: float = MARGIN_SCALE,
                  margin_add: float = MARGIN_ADD, grid: Grid = GRID) -> np.ndarray:
    """Voxel indices (i, j, k) of ``grid`` whose centres lie inside the enlarged box → int64 [M, 3].

    center [3] (ego frame, metres), size_wlh [3] (nuScenes w, l, h), rotation: 3×3 / quaternion (w,x,y,z) / yaw
    (box frame → ego frame). Only the voxels in the box's axis-aligned bounding range are tested, so the cost is
    proportional to the box volume, not the grid. Voxels outside the grid are never returned; a box entirely
    outside the grid gives an empty [0, 3] array. Indices are sorted (lexicographic i, j, k).
    """
    c = np.asarray(center, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(c)):
        raise ValueError(f"box center must be finite, got {c.tolist()}")
    rot = box_rotation(rotation)
    half = enlarged_extent(size_wlh, margin_scale, margin_add) / 2.0
    # Axis-aligned half extent of the rotated box in the ego frame: |R| @ half.
    reach = np.abs(rot) @ half
    lower = np.asarray(grid.lower, dtype=np.float64)
    vs = float(grid.voxel_size)
    shape = np.asarray(grid.shape)
    # Voxel centre index range whose centres can lie within [c - reach, c + reach].
    lo = np.maximum(np.ceil((c - reach - lower) / vs - 0.5 - 1e-9).astype(np.int64), 0)
    hi = np.minimum(np.floor((c + reach - lower) / vs - 0.5 + 1e-9).astype(np.int64), shape - 1)
    if np.any(hi < lo):
        return np.empty((0, 3), dtype=np.int64)
    axes = [np.arange(lo[a], hi[a] + 1) for a in range(3)]
    # Box-frame coordinates of every candidate centre, built per axis and broadcast (no meshgrid of points).
    rel = [lower[a] + (axes[a] + 0.5) * vs - c[a] for a in range(3)]  # [n_a] each
    inside = np.ones((len(axes[0]), len(axes[1]), len(axes[2])), dtype=bool)
    tol = 1e-9
    for b in range(3):  # box axis b: local_b = sum_a rot[a, b] * rel_a
        local = (rot[0, b] * rel[0][:, None, None] + rot[1, b] * rel[1][None, :, None]
                 + rot[2, b] * rel[2][None, None, :])
        inside &= np.abs(local) <= half[b] + tol
    idx = np.nonzero(inside)
    return np.stack([axes[0][idx[0]], axes[1][idx[1]], axes[2][idx[2]]], axis=-1).astype(np.int64)


def voxel_centers(indices, grid: Grid = GRID) -> np.ndarray:
    """Voxel indices [..., 3] → centre coordinates [..., 3] (ego frame, metres, float64)."""
    return np.asarray(grid.lower, dtype=np.float64) + (np.asarray(indices) + 0.5) * grid.voxel_size
