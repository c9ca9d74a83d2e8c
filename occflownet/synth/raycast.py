"""Ray casting against the world's geometry: yaw-oriented boxes (analytic slab test) and the ground plane z = 0.

Rays come as a 2D array of directions [A, B, 3] from one origin (an image's pixels, a LiDAR's beams × azimuths),
all in the *global frame*. Callers cull first: for every box they name the rectangle of the ray array that may
hit it (``Block``), so the cost is proportional to the screen area of the boxes, not rays × boxes.
Ray parameter ``t`` is in units of the direction's length (unit directions: metres; camera directions with
z_cam = 1: z-depth).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.synth.world import Boxes

T_EPS = 1e-6


@dataclass(frozen=True)
class Block:
    """Box ``box`` may be hit by rays [r0:r1, c0:c1] of the ray array."""

    box: int
    r0: int
    r1: int
    c0: int
    c1: int


def ray_box_t(origin_local: np.ndarray, dirs_local: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Entry distance of rays into one axis-aligned box centred at the local origin (slab test).

    ``origin_local`` [3] or [..., 3]; ``dirs_local`` [..., 3]; ``half`` [3]. Returns t [...] (float64), ``inf``
    where the ray misses or starts inside/behind the box.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(np.abs(dirs_local) < 1e-12, 1e-12, dirs_local)
        inv = 1.0 / d
        t1 = (-half - origin_local) * inv
        t2 = (half - origin_local) * inv
    t_near = np.minimum(t1, t2).max(axis=-1)
    t_far = np.maximum(t1, t2).min(axis=-1)
    hit = (t_near <= t_far) & (t_near > T_EPS)
    return np.where(hit, t_near, np.inf)


def to_local(boxes: Boxes, i: int, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Origin [3] and directions [..., 3] (global) in the frame of box ``i`` (centre at 0, axes along the box)."""
    c, s = np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])
    o = origin - boxes.center[i]
    o_l = np.array([c * o[0] + s * o[1], -s * o[0] + c * o[1], o[2]])
    d_l = np.empty_like(dirs)
    d_l[..., 0] = c * dirs[..., 0] + s * dirs[..., 1]
    d_l[..., 1] = -s * dirs[..., 0] + c * dirs[..., 1]
    d_l[..., 2] = dirs[..., 2]
    return o_l, d_l


def cast_blocks(origin: np.ndarray, dirs: np.ndarray, boxes: Boxes, blocks: list[Block],
                t_buf: np.ndarray, id_buf: np.ndarray, alone: np.ndarray | None = None) -> None:
    """Nearest-hit update of ``t_buf`` [A, B] and ``id_buf`` [A, B] (box index, -1 none) in place.

    ``alone`` (optional, int64 [N boxes]) accumulates how many rays hit each box ignoring occlusion.
    """
    for blk in blocks:
        d = dirs[blk.r0:blk.r1, blk.c0:blk.c1]
        o_l, d_l = to_local(boxes, blk.box, origin, d)
        t = ray_box_t(o_l, d_l, boxes.half[blk.box])
        tb = t_buf[blk.r0:blk.r1, blk.c0:blk.c1]
        better = t < tb
        tb[better] = t[better]
        id_buf[blk.r0:blk.r1, blk.c0:blk.c1][better] = blk.box
        if alone is not None:
            alone[blk.box] += int(np.isfinite(t).sum())


def ground_t(origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance along rays [..., 3] from ``origin`` [3] to the ground plane z = 0 (global); inf if never."""
    dz = dirs[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origin[2] / dz
    return np.where((dz < -1e-9) & (t > T_EPS), t, np.inf)


def box_faces(boxes: Boxes, ids: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which face of box ``ids`` [M] the global ``points`` [M, 3] lie on.

    Returns (normal [M, 3] global unit outward normal, local point [M, 3] in the box frame, axis [M] 0/1/2).
    """
    c, s = np.cos(boxes.yaw[ids]), np.sin(boxes.yaw[ids])
    o = points - boxes.center[ids]
    local = np.stack([c * o[:, 0] + s * o[:, 1], -s * o[:, 0] + c * o[:, 1], o[:, 2]], axis=1)
    rel = np.abs(local) / np.maximum(boxes.half[ids], 1e-9)
    axis = rel.argmax(axis=1)
    sign = np.sign(local[np.arange(len(ids)), axis])
    n_local = np.zeros_like(local)
    n_local[np.arange(len(ids)), axis] = sign
    normal = np.stack([c * n_local[:, 0] - s * n_local[:, 1], s * n_local[:, 0] + c * n_local[:, 1],
                       n_local[:, 2]], axis=1)
    return normal, local, axis


def boxes_in_range(boxes: Boxes, origin: np.ndarray, max_range: float) -> np.ndarray:
    """Indices of boxes whose bounding sphere comes within ``max_range`` of ``origin`` (global)."""
    radius = np.linalg.norm(boxes.half, axis=1)
    dist = np.linalg.norm(boxes.center - origin, axis=1)
    return np.nonzero(dist - radius < max_range)[0]
