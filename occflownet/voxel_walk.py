"""Exact ray–voxel traversal (Amanatides & Woo 1987, "A fast voxel traversal algorithm"), vectorised over rays.

One walk for everyone who needs to know which voxels a ray passes: the synthetic world's visibility masks
(``occflownet.synth.frame``: ``mask_lidar``, ``mask_camera``), the fog metric's crossed voxels
(``occflownet.eval.fog``), RayIoU's first hits (``occflownet.eval.ray_iou``) and the LiDAR and camera visibility of
the label pipeline (``occflownet.labels``). It imports nothing else from the package but the grid's defaults, so
every stage can use it. Two engines compute the same walk: numpy (lock-step over all rays, always available) and
numba (``occflownet.voxel_walk_numba``, compiled and parallel, when numba is installed); ``engine="auto"`` picks
numba when it can.

- ``walk_rays(volume, origins, directions, ...)``: the walk. In the numpy engine all rays advance in lock-step, one
  voxel per numpy step, and the volume is padded with a one-voxel border of ``OUTSIDE`` so that no bounds checks
  are needed; the numba engine walks one ray per loop iteration with bounds checks.
- ``traverse(origins, dirs, occupied, t_max, lower, voxel_size)``: the voxels rays visit up to and including the
  first occupied one (the masks and the fog metric).

Tie-breaking (``ties``) decides which axis a ray steps along when it crosses two or three voxel faces at the same
parameter t (a ray through a voxel edge or corner): ``"first"`` steps x before y before z, ``"last"`` z before y
before x, which is what SparseOcc's ``dvr`` kernel does (``tMaxX < tMaxY`` false on a tie → y or z). Both walks
are exact; they differ only in which of the voxels that the ray touches in a single point (at the edge or corner)
it visits. ``traverse`` keeps ``"first"`` (the synthetic ground truth written so far was made with it, and
changing it would change the masks of a seed); RayIoU keeps ``"last"`` to reproduce the reference kernel bit for
bit (tests/test_eval_ray_iou.py).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from occflownet.occ3d import GRID

OUTSIDE = 254  # code of the border around the volume: a ray that reaches it has left the grid
TIES = ("first", "last")
ENGINES = ("auto", "numpy", "numba")


class VoxelWalk(NamedTuple):
    """Result of ``walk_rays``. code uint8 [R]: the value of the voxel the ray stopped in when it is not
    ``empty``, else ``empty`` (the ray ended, left the grid or never entered it); t float64 [R]: the ray parameter
    where the ray leaves that last voxel (inf for rays that never enter the grid); visited: bool [X, Y, Z] of all
    voxels visited (the stopping voxels included), or None when not asked for."""

    code: np.ndarray
    t: np.ndarray
    visited: np.ndarray | None


def walk_rays(volume: np.ndarray, origins: np.ndarray, directions: np.ndarray, *, empty: int = 0,
              lower=(0.0, 0.0, 0.0), voxel_size: float = 1.0, t_end: np.ndarray | None = None,
              ties: str = "first", visited: bool = False, engine: str = "auto") -> VoxelWalk:
    """Walk rays voxel by voxel through ``volume`` until each one stops.

    volume: integer or bool [X, Y, Z], values < ``OUTSIDE``; voxels equal to ``empty`` let rays through, any other
    value stops them. origins, directions: float [R, 3] in the grid's frame and units (voxel (i, j, k) spans
    ``lower + (i, j, k) * voxel_size`` to ``+ voxel_size``; the defaults are voxel units); directions of any
    non-zero length, components may be 0. A ray is ``origins + t * directions``, t >= 0; a ray starting outside the
    grid begins where it enters (t still measured from its origin).

    A ray stops in the first voxel that is not empty (code = its value, t = where it leaves it). Without ``t_end``
    it otherwise walks until it leaves the grid (code ``empty``, t = the last face it crossed); with ``t_end`` [R]
    it also stops in the voxel whose exit crossing lies at or beyond ``min(t_end, grid exit)`` (code ``empty``,
    t = that crossing), the grid exit being the slab test's exact value. ``ties``: ``"first"`` or ``"last"``, see
    the module docstring. ``visited``: also return the voxels visited.

    ``engine``: ``"numpy"`` (lock-step over all rays), ``"numba"`` (compiled, one ray per iteration, parallel;
    ``occflownet.voxel_walk_numba``) or ``"auto"`` (numba when it is installed). Both give identical results.
    """
    if ties not in TIES:
        raise ValueError(f"ties must be one of {TIES}, got {ties!r}")
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")
    volume = np.asarray(volume)
    shape = np.asarray(volume.shape, dtype=np.int64)
    if volume.ndim != 3:
        raise ValueError(f"volume must be [X, Y, Z], got shape {volume.shape}")
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if len(o) != len(d):
        raise ValueError(f"origins ({len(o)}) and directions ({len(d)}) must have one row per ray")
    lower = np.asarray(lower, dtype=np.float64)
    if volume.size and int(volume.max()) >= OUTSIDE:
        raise ValueError(f"volume values must be < {OUTSIDE}")
    if _use_numba(engine):
        return _walk_numba(volume, o, d, empty, lower, float(voxel_size), t_end, ties, visited)
    code = np.full(len(o), empty, dtype=np.uint8)
    t_exit = np.full(len(o), np.inf)
    padded = np.full(tuple(shape + 2), OUTSIDE, dtype=np.uint8)
    padded[1:-1, 1:-1, 1:-1] = volume
    codes = np.concatenate([padded.reshape(-1), np.array([empty], dtype=np.uint8)])  # + the parking cell
    seen = np.zeros(len(codes), dtype=bool) if visited else None
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # axis-parallel rays: x/0 = ±inf
        ids, t_stop, state = _enter(o, d, shape, lower, float(voxel_size), t_end)
        if len(ids):
            _advance(codes, empty, ids, t_stop, state, ties, code, t_exit, seen,
                     int(shape.sum()) + 8)
    if seen is not None:
        seen = seen[:-1].reshape(padded.shape)[1:-1, 1:-1, 1:-1].copy()
    return VoxelWalk(code, t_exit, seen)


def _use_numba(engine: str) -> bool:
    if engine == "numpy":
        return False
    try:
        import numba  # noqa: F401
    except ImportError:
        if engine == "numba":
            raise ImportError("walk_rays(engine='numba') needs numba (pip install numba, or the train/labels "
                              "extra)") from None
        return False
    return True


def _walk_numba(volume, o, d, empty, lower, voxel_size, t_end, ties, visited) -> VoxelWalk:
    from occflownet.voxel_walk_numba import keep_torch_threads, walk

    code = np.empty(len(o), dtype=np.uint8)
    t_exit = np.empty(len(o))
    seen = np.zeros(volume.shape if visited else (1, 1, 1), dtype=np.bool_)
    ends = np.zeros(len(o)) if t_end is None else np.ascontiguousarray(np.asarray(t_end, np.float64).reshape(-1))
    if len(ends) != len(o):
        raise ValueError(f"t_end must have one value per ray ({len(o)}), got {len(ends)}")
    with keep_torch_threads():
        walk(np.ascontiguousarray(volume, dtype=np.uint8), np.uint8(empty), np.ascontiguousarray(o),
             np.ascontiguousarray(d), lower, voxel_size, ends, t_end is not None, ties == "last", seen, visited,
             code, t_exit)
    return VoxelWalk(code, t_exit, seen if visited else None)


def _enter(o, d, shape, lower, voxel_size, t_end):
    """Slab test and the Amanatides–Woo start state of the rays that enter the grid: (ray ids, t_stop [n] or None,
    state: flat index into the padded volume, then per axis x, y, z the next crossing, its increment, the flat
    offset of one step). The operations are those of the reference kernel (``(boundary − o) / d``), so that in
    voxel units (lower 0, size 1) the crossings are its values bit for bit."""
    upper = lower + shape * voxel_size
    zero = d == 0
    any_zero = bool(zero.any())
    t1, t2 = (lower - o) / d, (upper - o) / d
    t_near, t_far = np.minimum(t1, t2), np.maximum(t1, t2)
    if any_zero:  # parallel to a slab: inside it for all t, or never
        inside = (o >= lower) & (o < upper)
        t_near = np.where(zero, np.where(inside, -np.inf, np.inf), t_near)
        t_far = np.where(zero, np.where(inside, np.inf, -np.inf), t_far)
    t_in = np.maximum(t_near.max(axis=1), 0.0)
    t_out = t_far.min(axis=1)
    if t_end is not None:
        t_out = np.minimum(t_out, np.asarray(t_end, dtype=np.float64).reshape(-1))
    enters = t_in < t_out
    ids = np.flatnonzero(enters)
    if len(ids) < len(o):
        o, d, zero, t_in, t_out = o[ids], d[ids], zero[ids], t_in[ids], t_out[ids]
    p = o + t_in[:, None] * d
    voxel = np.clip(np.floor((p - lower) / voxel_size), 0, shape - 1).astype(np.int64)
    step = np.where(d >= 0, 1, -1)
    t_next = (lower + (voxel + (step > 0)) * voxel_size - o) / d
    t_delta = voxel_size / np.abs(d)
    if any_zero:  # never crosses a face of that axis
        t_next[zero] = np.inf
        t_delta[zero] = np.inf
    _, Y, Z = shape + 2
    strides = np.array([Y * Z, Z, 1], dtype=np.int64)
    flat = (voxel + 1) @ strides
    move = step * strides
    per_axis = [np.ascontiguousarray(a[:, axis]) for axis in range(3) for a in (t_next, t_delta, move)]
    return ids, (None if t_end is None else t_out), [flat, *per_axis]


def _advance(codes, empty, ids, t_stop, state, ties, out_code, out_t, seen, max_steps):
    """The lock-step loop: look up each ray's voxel, record the rays that stop there, step the others along the
    axis of their nearest crossing. ``codes`` ends with one extra ``empty`` cell where stopped rays are parked
    (no moves, no end) until an eighth of the rays are parked and the arrays are compacted."""
    flat, tx, dx, mx, ty, dy, my, tz, dz, mz = state
    park = len(codes) - 1
    parked = 0
    buf = [np.empty(len(ids), dtype=bool) for _ in range(4)]  # reused masks
    for _ in range(max_steps):  # every step moves one voxel along one axis: bounded by the grid
        value = codes.take(flat, mode="clip")  # indices are always valid; 'clip' skips the checks
        if seen is not None:
            seen[flat] = True
        stop = value != empty
        if t_stop is not None:
            stop |= np.minimum(np.minimum(tx, ty), tz) >= t_stop
        done = np.flatnonzero(stop)
        if done.size:
            _record(done, value, ids, tx, dx, ty, dy, tz, dz, empty, out_code, out_t)
            parked += done.size
            if parked * 8 > len(ids):  # compact once an eighth of the rays are finished
                keep = ~stop
                keep &= flat != park
                ids, flat, tx, dx, mx, ty, dy, my, tz, dz, mz = (
                    a[keep] for a in (ids, flat, tx, dx, mx, ty, dy, my, tz, dz, mz))
                t_stop = None if t_stop is None else t_stop[keep]
                parked = 0
                if len(ids) == 0:
                    return
            else:
                flat[done] = park
                mx[done] = 0
                my[done] = 0
                mz[done] = 0
                if t_stop is not None:
                    t_stop[done] = np.inf
        n = len(ids)
        a, sx, sy, sz = (b[:n] for b in buf)
        if ties == "first":  # x if tx <= ty and tx <= tz; else y if ty <= tz; else z
            np.less_equal(tx, ty, out=a)
            np.less_equal(tx, tz, out=sx)
            sx &= a
            np.less_equal(ty, tz, out=sy)
        else:  # the kernel's: x if tx < ty and tx < tz; else y if ty < tz; else z
            np.less(tx, ty, out=a)
            np.less(tx, tz, out=sx)
            sx &= a
            np.less(ty, tz, out=sy)
        np.greater(sy, a, out=sy)  # ... and not (the comparison of tx with ty that picked x)
        np.logical_or(sx, sy, out=sz)
        np.logical_not(sz, out=sz)
        np.add(tx, dx, out=tx, where=sx)
        np.add(ty, dy, out=ty, where=sy)
        np.add(tz, dz, out=tz, where=sz)
        np.add(flat, mx, out=flat, where=sx)
        np.add(flat, my, out=flat, where=sy)
        np.add(flat, mz, out=flat, where=sz)
    raise RuntimeError("voxel traversal did not terminate; this is a bug")


def _record(done, value, ids, tx, dx, ty, dy, tz, dz, empty, out_code, out_t):
    """Code and exit parameter of the rays ``done`` (positions in the current arrays)."""
    v = value[done]
    left = v == OUTSIDE
    t_exit = np.minimum(np.minimum(tx[done], ty[done]), tz[done])
    # A ray in the border: the grid exit is the last face it crossed.
    t_last = np.fmax(np.fmax(tx[done] - dx[done], ty[done] - dy[done]), tz[done] - dz[done])
    out_code[ids[done]] = np.where(left, empty, v)
    out_t[ids[done]] = np.where(left, t_last, t_exit)


def traverse(origins: np.ndarray, dirs: np.ndarray, occupied: np.ndarray, t_max: np.ndarray | None = None,
             lower=GRID.lower, voxel_size: float = GRID.voxel_size) -> np.ndarray:
    """Voxels visited by rays up to and including the first occupied voxel (exact 3D DDA, all rays at once).

    ``origins`` [N, 3] and ``dirs`` [N, 3] (any length, not zero) in the grid's frame; ``occupied`` bool [X, Y, Z];
    ``t_max`` [N] optional end of each ray in units of ``dirs`` (a ray stops in the voxel where it ends if it met
    nothing before). Rays may start outside the grid. Returns bool [X, Y, Z]. Ties step x before y before z
    (``ties="first"``); direction components below 1e-12 in magnitude are taken as +1e-12.
    """
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    t_end = np.full(len(o), np.inf) if t_max is None else np.asarray(t_max, dtype=np.float64).reshape(-1)
    return walk_rays(np.asarray(occupied, dtype=bool), o, d, empty=0, lower=lower, voxel_size=voxel_size,
                     t_end=t_end, ties="first", visited=True).visited
