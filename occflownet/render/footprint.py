"""The footprint of rays on the grid: the voxels that rendering along them can read.

Rendering (``volume_render``, both lookups) reads σ and the logits trilinearly between the 8 voxel centres around
each sample point: continuous index u = (p - lower) / voxel_size - 0.5 per axis, corners ⌊u⌋ and ⌊u⌋ + 1, corners
outside the grid read zero. A sample at t ∈ [0, t_end] on a ray therefore reads, with non-zero weight, only the 8
corners of the *interpolation cell* it lies in. The interpolation cells form a dual grid one cell larger per axis,
whose cell c spans the centres of voxels c - 1 and c (``lower - voxel_size / 2`` to ``+ (n + 1) · voxel_size``):
walking the segment through that grid (``voxel_walk.walk_rays``, exact) and marking the 8 corners of every cell it
crosses gives every voxel a sample on the segment can read.

What it is for: a volume that equals the prediction on the footprint and holds anything finite elsewhere renders
the same depths, semantics and weights, with the same gradients, so the model's heads need to run on the footprint
only (``occflownet.train.step.LossComputer.head_rows``: 37–47 % of the grid for the 4,096 rays of a 2d-base
sample, O = 3). The one difference is at a sample lying on a cell face to within rounding (1e-13 m): the kernel may
read the voxel beyond the face with a weight of that order, which the footprint may leave out.
"""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import GRID, Grid
from occflownet.voxel_walk import walk_rays


def ray_footprint(origins: np.ndarray, directions: np.ndarray, t_end: np.ndarray, grid: Grid = GRID) -> np.ndarray:
    """bool [X, Y, Z]: the voxels of ``grid`` that trilinear lookups at points ``origins + t · directions``,
    0 ≤ t ≤ ``t_end``, can read (module docstring). origins, directions: float [R, 3] in the grid's frame (metres;
    directions of any non-zero length, t in their units); t_end: float [R] (or a scalar for all rays)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    ends = np.broadcast_to(np.asarray(t_end, dtype=np.float64), (len(o),))
    shape = tuple(int(n) for n in grid.shape)
    if len(o) == 0:
        return np.zeros(shape, dtype=bool)
    cells = tuple(n + 1 for n in shape)
    lower = np.asarray(grid.lower, dtype=np.float64) - 0.5 * grid.voxel_size
    crossed = walk_rays(np.zeros(cells, dtype=np.uint8), o, d, lower=lower, voxel_size=grid.voxel_size,
                        t_end=np.ascontiguousarray(ends), visited=True).visited       # [X + 1, Y + 1, Z + 1]
    return corners_of_cells(crossed)


def corners_of_cells(cells: np.ndarray) -> np.ndarray:
    """bool [X + 1, Y + 1, Z + 1] interpolation cells (cell c spans voxel centres c - 1 and c per axis) → bool
    [X, Y, Z]: the voxels that are a corner of at least one of them."""
    x, y, z = (n - 1 for n in cells.shape)
    out = np.zeros((x, y, z), dtype=bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                out |= cells[dx:dx + x, dy:dy + y, dz:dz + z]
    return out
