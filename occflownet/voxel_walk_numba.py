"""The compiled engine of ``occflownet.voxel_walk.walk_rays`` (numba): the same walk, one ray per loop iteration.

``walk_rays(..., engine="numba")`` calls :func:`walk`; the numpy engine and this one perform the same floating-point
operations in the same order (the slab test, the Amanatides–Woo start state, one ``t += Δt`` per step, the same tie
comparisons), so their codes, exit parameters and visited voxels are identical, bit for bit
(``tests/test_voxel_walk.py`` compares them on random rays under both tie rules). Rays run in parallel (``prange``);
the only shared write is ``visited[i, j, k] = True``, which every thread writes with the same value.

numba is optional for the package's core (it comes with the ``train`` and ``labels`` extras); this module is imported
only when the numba engine is asked for or chosen by ``engine="auto"``.
"""
from __future__ import annotations

import math
import sys
from contextlib import contextmanager

import numpy as np
from numba import njit, prange


@contextmanager
def keep_torch_threads():
    """Run numba's parallel kernels without changing torch's intra-op thread count. numba's OpenMP threading layer
    shares the OpenMP runtime with torch and, when it starts, raises torch's count to its own (e.g. from
    ``OMP_NUM_THREADS=1`` to the core count): a training run started in the same process after a labelling or
    rendering kernel would otherwise run with other threads than a fresh process (and, resumed, give other weights).
    Only when torch is already imported; this module does not import it."""
    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None   # first: asking numba starts its layer
    try:
        yield
    finally:
        if torch is not None and torch.get_num_threads() != before:
            torch.set_num_threads(before)


@njit(cache=True, inline="always")
def _fmax(a, b):
    """``np.fmax`` for scalars: the larger of a and b, ignoring a NaN."""
    if a != a:
        return b
    if b != b:
        return a
    return a if a >= b else b


@njit(cache=True, inline="always")
def _slab(o, d, lo, hi):
    """Entry and exit parameter of the ray's coordinate o + t·d in the slab [lo, hi) (±inf when parallel)."""
    if d == 0.0:
        if o >= lo and o < hi:
            return -np.inf, np.inf
        return np.inf, -np.inf
    t1 = (lo - o) / d
    t2 = (hi - o) / d
    return min(t1, t2), max(t1, t2)


@njit(cache=True, inline="always")
def _axis_start(o, d, t_in, lo, vs, n):
    """Start voxel index, next crossing, crossing increment and step of one axis (``voxel_walk._enter``)."""
    v = min(max(math.floor((o + t_in * d - lo) / vs), 0), n - 1)
    if d == 0.0:
        return v, np.inf, np.inf, 1
    step = 1 if d >= 0 else -1
    return v, (lo + (v + (1 if step > 0 else 0)) * vs - o) / d, vs / abs(d), step


@njit(cache=True, parallel=True)
def walk(volume, empty, origins, directions, lower, vs, t_end, has_t_end, last_ties, visited, want_visited,
         code, t_exit):
    """Walk every ray (see ``voxel_walk.walk_rays``). volume uint8 [X, Y, Z]; origins, directions float64 [R, 3];
    lower float64 [3]; t_end float64 [R] (used when ``has_t_end``); ``last_ties``: the "last" tie rule; writes
    code uint8 [R], t_exit float64 [R] (inf for rays that never enter) and, when ``want_visited``, visited bool
    [X, Y, Z]."""
    nx, ny, nz = volume.shape
    max_steps = nx + ny + nz + 8
    for r in prange(origins.shape[0]):
        code[r] = empty
        t_exit[r] = np.inf
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        ax, bx = _slab(ox, dx, lower[0], lower[0] + nx * vs)
        ay, by = _slab(oy, dy, lower[1], lower[1] + ny * vs)
        az, bz = _slab(oz, dz, lower[2], lower[2] + nz * vs)
        t_in = max(max(max(ax, ay), az), 0.0)
        t_stop = min(min(bx, by), bz)
        if has_t_end:
            t_stop = min(t_stop, t_end[r])
        if not t_in < t_stop:
            continue
        vx, tx, ex, sx = _axis_start(ox, dx, t_in, lower[0], vs, nx)
        vy, ty, ey, sy = _axis_start(oy, dy, t_in, lower[1], vs, ny)
        vz, tz, ez, sz = _axis_start(oz, dz, t_in, lower[2], vs, nz)
        for _ in range(max_steps):
            value = volume[vx, vy, vz]
            if want_visited:
                visited[vx, vy, vz] = True
            nearest = min(min(tx, ty), tz)
            if value != empty or (has_t_end and nearest >= t_stop):
                code[r] = value
                t_exit[r] = nearest
                break
            if last_ties:
                pick_x = (tx < ty) and (tx < tz)
                pick_y = (not tx < ty) and (ty < tz)
            else:
                pick_x = (tx <= ty) and (tx <= tz)
                pick_y = (not tx <= ty) and (ty <= tz)
            if pick_x:
                tx += ex
                vx += sx
                out = vx < 0 or vx >= nx
            elif pick_y:
                ty += ey
                vy += sy
                out = vy < 0 or vy >= ny
            else:
                tz += ez
                vz += sz
                out = vz < 0 or vz >= nz
            if out:  # left the grid: t is the last face crossed
                t_exit[r] = _fmax(_fmax(tx - ex, ty - ey), tz - ez)
                break
