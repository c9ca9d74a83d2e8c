"""The rays' footprint (occflownet/render/footprint.py): every voxel a trilinear lookup on a ray's segment can read,
and little more."""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import GRID, Grid
from occflownet.render.footprint import corners_of_cells, ray_footprint


def _read_by_samples(origins, directions, t_end, grid: Grid, step: float):
    """(voxels read with weight > 0, corners of the cells the samples lie in) by sampling each segment every
    ``step`` metres, with the renderer's rule (numba_kernels._cell: u = (p - lower) / voxel_size - 0.5)."""
    weighted = np.zeros(grid.shape, dtype=bool)
    cornered = np.zeros(grid.shape, dtype=bool)
    shape = np.asarray(grid.shape)
    for o, d, end in zip(origins, directions, t_end):
        t = np.arange(0.0, end, step)
        u = (o + t[:, None] * d - np.asarray(grid.lower)) / grid.voxel_size - 0.5
        u = np.clip(u, -1.0, shape.astype(float))
        base = np.floor(u).astype(np.int64)
        frac = u - base
        for corner in np.ndindex(2, 2, 2):
            ijk = base + np.asarray(corner)
            weight = np.prod(np.where(np.asarray(corner) == 1, frac, 1.0 - frac), axis=1)
            inside = ((ijk >= 0) & (ijk < shape)).all(axis=1)
            cornered[tuple(ijk[inside].T)] = True
            positive = inside & (weight > 0)
            weighted[tuple(ijk[positive].T)] = True
    return weighted, cornered


def test_a_ray_along_x_reads_a_two_by_two_column_of_voxels():
    # u_y = 100.3, u_z = 5.3 (between centres 100/101 and 5/6); x from u = 99.5 (x = 0) to 104.5 (t = 2 m)
    origin = np.array([[0.0, -40.0 + 100.8 * 0.4, -1.0 + 5.8 * 0.4]])
    footprint = ray_footprint(origin, np.array([[1.0, 0.0, 0.0]]), np.array([2.0]))
    expected = np.zeros(GRID.shape, dtype=bool)
    expected[99:106, 100:102, 5:7] = True
    # exact: booleans; the ray runs 0.3 voxel from the nearest centre plane, far from a tie
    assert np.array_equal(footprint, expected)


def test_the_footprint_holds_every_voxel_a_sample_on_the_segment_reads():
    """Random rays (starting inside and outside the grid, short and long, a few axis-parallel): every voxel that a
    lookup at a sample 4 mm apart reads with non-zero weight is in the footprint, and the footprint holds little
    beyond the corners of the cells such samples lie in (cells a ray only grazes between two samples)."""
    rng = np.random.default_rng(3)
    n = 24
    origins = np.concatenate([rng.uniform(-30, 30, (n, 2)), rng.uniform(0, 3, (n, 1))], axis=1)
    origins[:4, 0] = [-55.0, 52.0, 0.0, 10.0]                 # outside the grid, and on the grid's edge in x
    directions = rng.normal(size=(n, 3))
    directions[:, 2] *= 0.1
    directions[4:7] = [[1, 0, 0], [0, -1, 0], [0, 0, 1]]       # axis-parallel
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    t_end = rng.uniform(1.0, 60.0, n)
    footprint = ray_footprint(origins, directions, t_end)
    weighted, cornered = _read_by_samples(origins, directions, t_end, GRID, step=0.004)
    assert weighted.any() and not (weighted & ~footprint).any()
    assert (footprint & ~cornered).sum() <= 0.01 * footprint.sum()


def test_no_rays_no_footprint_and_cells_mark_their_eight_corners():
    assert not ray_footprint(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)).any()
    cells = np.zeros((5, 4, 3), dtype=bool)
    cells[2, 1, 1] = True                                         # spans voxel centres 1-2, 0-1, 0-1
    expected = np.zeros((4, 3, 2), dtype=bool)
    expected[1:3, 0:2, 0:2] = True
    assert np.array_equal(corners_of_cells(cells), expected)
    cells[:] = False
    cells[0, 0, 0] = True                                         # the corner cell: only voxel (0, 0, 0) is inside
    assert np.flatnonzero(corners_of_cells(cells)).tolist() == [0]
