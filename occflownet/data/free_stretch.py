"""The free stretch in front of a ray's LiDAR point: where ``--free-before-point`` (beyond the paper, docs/training.md)
stops rendering a camera ray as free space. Distances in metres along the ray from its origin (the camera centre).

Two rules (``occflownet.choices.FREE_STRETCH_RULES``; ``RayConfig.free_stretch``):

- ``"fraction"`` (:func:`free_segment_ends`): up to ``(1 - FREE_BEFORE_FRACTION) · depth - FREE_BEFORE_MARGIN``.
  A fixed margin is not enough: a ray meeting the road (or a wall) at a shallow angle runs inside its 0.4 m voxel
  layer for metres before its point (55 % of the rays cross a labelled voxel before depth - 0.6 m on the fitting
  world, 4-5 % before this end). But on a surface seen head-on it leaves the last fifth of the ray unconstrained,
  and that is where a 2D-trained model puts its fog (docs/results.md).
- ``"points"`` (:func:`point_clearance_ends`): up to where the ray first enters a voxel within one voxel of a LiDAR
  point of its own frame (the 3 × 3 × 3 neighbourhood of a voxel holding a point: the trilinear lookup of a sample
  outside those voxels reads no voxel that holds a point). The points themselves say where surfaces are: head-on,
  the stretch runs to about a voxel before the point; grazing a road or a wall, it ends where the ray first comes
  near the surface's other points. On the fitting world (t = 0 rays of its 8 keyframes) 0.6 % of these stretches
  cross a labelled voxel, against 7.2 % of the fraction rule's, at about the same mean length (0.69 against 0.70
  of the depth). With it the free rays (``--free-beyond-grid``, ``--free-space``) leave out the voxels of
  :func:`near_point_voxels` (``RayBuilder.near_points``): 19 % of the beyond-grid rays of the fitting world cross
  a labelled voxel inside the grid (the tops of trees, trucks and buses they graze on the way up), 5 % outside those
  voxels.

Rays whose stretch is shorter than ``FREE_BEFORE_MIN`` are not rendered as free.
"""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import GRID, Grid
from occflownet.voxel_walk import walk_rays

FREE_BEFORE_FRACTION = 0.2
FREE_BEFORE_MARGIN = 0.6   # metres
FREE_BEFORE_MIN = 1.0      # metres: shorter stretches are not used


def free_segment_ends(depths):
    """The fraction rule: where the free stretch in front of each ray's point ends (numpy array or tensor [R] of
    depths along the ray → the same type, metres)."""
    return depths * (1.0 - FREE_BEFORE_FRACTION) - FREE_BEFORE_MARGIN


def near_point_voxels(points: np.ndarray, grid: Grid = GRID) -> np.ndarray:
    """bool [X, Y, Z]: the voxels of ``grid`` that hold one of ``points`` (float [P, 3], the grid's frame; those
    outside it are ignored) or touch such a voxel by a face, an edge or a corner."""
    near = np.zeros(tuple(n + 2 for n in grid.shape), dtype=bool)      # one voxel of border on each side
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    ijk = grid.index_of(points[grid.contains(points)]) + 1
    for dx in range(3):
        for dy in range(3):
            for dz in range(3):
                near[ijk[:, 0] + dx - 1, ijk[:, 1] + dy - 1, ijk[:, 2] + dz - 1] = True
    return near[1:-1, 1:-1, 1:-1]


def point_clearance_ends(origins: np.ndarray, directions: np.ndarray, depths: np.ndarray, near: np.ndarray,
                         grid: Grid = GRID) -> np.ndarray:
    """The points rule → float32 [R]: for rays ``origins + s · directions`` (float [R, 3], unit directions, the
    grid's frame), 0 ≤ s ≤ ``depths`` [R], the distance s where each ray enters the first voxel of ``near`` (bool
    [X, Y, Z]: :func:`near_point_voxels` of the LiDAR points of the rays' frame, same frame; 0 for a ray that starts
    in one); ``depths`` where the ray meets none of them before its point (a ray to a point beyond the grid that
    leaves it without coming near a point: its depth)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    depths = np.asarray(depths, dtype=np.float64).reshape(-1)
    lower = np.asarray(grid.lower, dtype=np.float64)
    walk = walk_rays(np.asarray(near, dtype=np.uint8), o, d, empty=0, lower=lower,
                     voxel_size=grid.voxel_size, t_end=depths)
    ends = depths.copy()
    stopped = np.flatnonzero(walk.code != 0)
    if len(stopped):
        # the walk gives where a ray leaves the voxel it stopped in; its entry is the box's slab entry
        os_, ds = o[stopped], d[stopped]
        inside = os_ + (walk.t[stopped] - 1e-6)[:, None] * ds
        lo = lower + np.floor((inside - lower) / grid.voxel_size) * grid.voxel_size
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - os_) / ds, (lo + grid.voxel_size - os_) / ds
        near_t = np.where(ds == 0, -np.inf, np.minimum(t1, t2))
        ends[stopped] = np.clip(near_t.max(axis=1), 0.0, depths[stopped])
    return ends.astype(np.float32)
