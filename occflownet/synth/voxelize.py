"""Occ3D semantics from the world's geometry by voxelisation (the visibility masks: ``frame``).

``semantics``: a voxel takes the class of the geometry whose *surface* lies in it (it overlaps a box but is not
wholly inside it, or the ground plane z = 0 passes through it): like Occ3D, whose labels come from LiDAR returns and
reconstructed surfaces, the inside of a building or a car is free (and outside ``mask_camera``, which stops at the
first occupied voxel). Where several overlap, ``materials.voxel_priority`` decides (objects win over
ground and facades). The visibility masks walk rays through the result with ``occflownet.voxel_walk.traverse``
(``frame.lidar_mask``, ``frame.camera_mask``). All arrays are indexed [x, y, z] in the ego frame of one keyframe,
like Occ3D.
"""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import FREE, GRID, Grid
from occflownet.geometry import invert, transform_points
from occflownet.synth.materials import voxel_priority
from occflownet.synth.world import Boxes, World


def voxelize(world: World, boxes: Boxes, ego2global: np.ndarray, grid: Grid = GRID) -> np.ndarray:
    """Semantics uint8 [X, Y, Z] (17 = free) of ``boxes`` (global frame) and the ground, in the ego frame."""
    sem = np.full(grid.shape, FREE, np.uint8)
    vs = grid.voxel_size
    lower = np.asarray(grid.lower)
    xc, yc = grid.centers(0), grid.centers(1)
    # ground: the layer through which the plane z_global = 0 passes (ego frame z of the ground)
    z_ground = -ego2global[2, 3]
    k = int(np.floor((z_ground - lower[2]) / vs))
    if 0 <= k < grid.shape[2]:
        X, Y = np.meshgrid(xc, yc, indexing="ij")
        pts = transform_points(ego2global, np.stack([X, Y, np.full_like(X, z_ground)], -1))
        sem[:, :, k] = world.ground_lookup_global(pts[..., :2])[0]
    local = boxes.transformed(invert(ego2global))
    order = np.argsort(voxel_priority(local.occ), kind="stable")
    occ = local.occ
    for i in order:
        cx, cy, cz = local.center[i]
        hx, hy, hz = local.half[i]
        c, s = np.cos(local.yaw[i]), np.sin(local.yaw[i])
        ex, ey = abs(c) * hx + abs(s) * hy, abs(s) * hx + abs(c) * hy  # half extents of the xy bounding box
        i0, i1 = _span(cx - ex, cx + ex, lower[0], vs, grid.shape[0])
        j0, j1 = _span(cy - ey, cy + ey, lower[1], vs, grid.shape[1])
        k0, k1 = _span(cz - hz, cz + hz, lower[2], vs, grid.shape[2])
        if i0 >= i1 or j0 >= j1 or k0 >= k1:
            continue
        dx = xc[i0:i1, None] - cx
        dy = yc[None, j0:j1] - cy
        h = vs / 2
        # separating axis test of each voxel column's square against the rotated rectangle (strict overlap)
        u, v = np.abs(c * dx + s * dy), np.abs(-s * dx + c * dy)
        reach = h * (abs(c) + abs(s))
        cols = (u < hx + reach) & (v < hy + reach)
        # Occ3D labels surfaces, not solids: a voxel wholly inside the box (its column inside the rectangle and
        # its z extent inside the box's) is left free, like the inside of a real building or car
        inner_cols = (u + reach < hx) & (v + reach < hy)       # strict: a voxel on a face holds that face
        z_lo = lower[2] + np.arange(k0, k1) * vs
        inner_z = (z_lo > cz - hz) & (z_lo + vs < cz + hz)
        shell = cols[:, :, None] & ~(inner_cols[:, :, None] & inner_z[None, None, :])
        block = sem[i0:i1, j0:j1, k0:k1]
        block[shell] = occ[i]
    return sem


def _span(lo: float, hi: float, origin: float, vs: float, n: int) -> tuple[int, int]:
    """Index range [a, b) of voxels [origin + i*vs, origin + (i+1)*vs) that overlap the open interval (lo, hi)."""
    a = int(np.floor((lo - origin) / vs))
    b = int(np.ceil((hi - origin) / vs))
    return max(a, 0), min(b, n)
