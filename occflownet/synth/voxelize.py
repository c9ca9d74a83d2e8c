"""Occ3D ground truth from the world's geometry: semantics by voxelisation, visibility masks by ray traversal.

``semantics``: a voxel takes the class of the geometry whose *surface* lies in it (it overlaps a box but is not
wholly inside it, or the ground plane z = 0 passes through it): like Occ3D, whose labels come from LiDAR returns and
reconstructed surfaces, the inside of a building or a car is free (and outside ``mask_camera``, which stops at the
first occupied voxel). Where several overlap, ``materials.voxel_priority`` decides (objects win over
ground and facades). ``traverse``: exact voxel walk (Amanatides & Woo) of many rays at once, marking every voxel a
ray passes through up to and including the first occupied one. All arrays are indexed [x, y, z] in the ego frame
of one keyframe, like Occ3D.
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


def traverse(origins: np.ndarray, dirs: np.ndarray, occupied: np.ndarray, t_max: np.ndarray | None = None,
             lower=GRID.lower, voxel_size: float = GRID.voxel_size) -> np.ndarray:
    """Voxels visited by rays up to and including the first occupied voxel (exact 3D DDA, all rays at once).

    ``origins`` [N, 3] and ``dirs`` [N, 3] (any length, not zero) in the grid's frame; ``occupied`` bool [X, Y, Z];
    ``t_max`` [N] optional end of each ray in units of ``dirs`` (a ray stops in the voxel where it ends if it met
    nothing before). Rays may start outside the grid. Returns bool [X, Y, Z].
    """
    shape = np.asarray(occupied.shape)
    lower = np.asarray(lower, dtype=np.float64)
    upper = lower + shape * voxel_size
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    t_end = np.full(len(o), np.inf) if t_max is None else np.asarray(t_max, dtype=np.float64).reshape(-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t1, t2 = (lower - o) / d, (upper - o) / d
    t_in = np.maximum(np.minimum(t1, t2).max(axis=1), 0.0)
    t_out = np.minimum(np.maximum(t1, t2).min(axis=1), t_end)
    keep = t_in < t_out
    o, d, t_in, t_out = o[keep], d[keep], t_in[keep], t_out[keep]
    # Work on a grid padded by one voxel whose border counts as occupied: a ray leaving the grid stops there.
    X, Y, Z = shape + 2
    occ_pad = np.ones((X, Y, Z), bool)
    occ_pad[1:-1, 1:-1, 1:-1] = occupied
    occ_flat = occ_pad.reshape(-1)
    out = np.zeros(X * Y * Z, bool)
    p = o + t_in[:, None] * d
    idx = np.clip(np.floor((p - lower) / voxel_size).astype(np.int64), 0, shape - 1)
    step = np.where(d > 0, 1, -1)
    with np.errstate(divide="ignore", over="ignore"):
        t_delta = voxel_size / np.abs(d)
        t_next = (lower + (idx + (step > 0)) * voxel_size - o) / d  # next boundary crossing per axis
    strides = np.array([Y * Z, Z, 1], dtype=np.int64)
    flat = (idx + 1) @ strides  # index into the padded grid
    move = step * strides  # flat offset of one step along each axis
    tx, ty, tz = (np.ascontiguousarray(t_next[:, a]) for a in range(3))
    dx, dy, dz = (np.ascontiguousarray(t_delta[:, a]) for a in range(3))
    mvx, mvy, mvz = (np.ascontiguousarray(move[:, a]) for a in range(3))
    iteration = 0
    while len(flat):
        out[flat] = True
        mx = (tx <= ty) & (tx <= tz)
        my = (ty < tx) & (ty <= tz)
        mz = ~(mx | my)
        t_cross = np.where(mx, tx, np.where(my, ty, tz))
        alive = ~occ_flat[flat] & (t_cross < t_out)
        mx &= alive
        my &= alive
        mz &= alive
        np.add(flat, mvx, out=flat, where=mx)
        np.add(flat, mvy, out=flat, where=my)
        np.add(flat, mvz, out=flat, where=mz)
        np.add(tx, dx, out=tx, where=mx)
        np.add(ty, dy, out=ty, where=my)
        np.add(tz, dz, out=tz, where=mz)
        iteration += 1
        if iteration % 8 == 0 or alive.mean() < 0.75:
            flat, tx, ty, tz, dx, dy, dz, mvx, mvy, mvz, t_out = (
                a[alive] for a in (flat, tx, ty, tz, dx, dy, dz, mvx, mvy, mvz, t_out))
    return out.reshape(X, Y, Z)[1:-1, 1:-1, 1:-1].copy()
