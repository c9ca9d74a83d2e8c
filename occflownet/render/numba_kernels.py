"""Compiled CPU kernels for ray rendering (numba): the coarse pass, the fine draws and the rendering, and its
backward, one ray per loop iteration. Pure numpy in, numpy out; ``numba_render`` wraps them for autograd.

Same mathematics as ``volume_render`` (see its docstring; the tests compare values and gradients against the
``grid_sample`` reference path):

- grid: voxel (i, j, k) of volume v is element ``((v * X + i) * Y + j) * Z + k`` of the flat σ array, and of
  logits volume u (each ray names its own, ``ray_logits``: several σ volumes may share one) row
  ``((u * X + i) * Y + j) * Z + k`` of the logits table [m * X * Y * Z, C]; continuous index ``u = (p - lower) / voxel_size - 0.5`` (voxel centres at
  integers); trilinear between the 8 centres around u; corners outside the grid read zero;
- per ray: coarse σ at the midpoints of the jittered bins ``edges`` → CDF ``1 - T`` at the edges, 1 at the last
  (the official distribution; optionally
  mixed with a uniform CDF) → ``n_fine`` draws ``u_i = cdf_0 + (i + bias) / n · (cdf_M - cdf_0)`` inverted
  piecewise-linearly (nerfacc's ``importance_sampling``) → intervals half-way between samples → weights
  ``w_i = T_i (1 - exp(-τ_i))``, ``τ_i = scale · σ_i · δ_i``; depth ``Σ w_i (a_i + b_i) / 2``, semantics
  ``Σ w_i s_i``, weight sum ``Σ w_i``.

Work is organised around *runs*: consecutive fine samples of a ray that fall in the same interpolation cell share
their 8 corners, so the 17-channel logits are touched once per run (``Σ_k A_k · logits[v_k]`` with
``A_k = Σ_{i in run} w_i c_ik``), not once per sample. Arithmetic is float64 inside, whatever the input dtype.

Backward (with e_i = ∂L/∂w_i = g_depth · m_i + g_wsum + g_sem · s_i and T_{i+1} = T_i - w_i):
  ∂L/∂τ_k = e_k T_{k+1} - Σ_{i>k} e_i w_i,  ∂L/∂σ_k = ∂L/∂τ_k · scale · δ_k,
  ∂L/∂logits[v] = Σ_rays g_sem · Σ_{runs, corners k at v} A_k.
It runs in two kernels: ``sigma_sample_grads`` (rays in parallel, no shared writes) gives ∂L/∂σ_i per sample, and
``scatter_grads`` (voxel slabs split across threads, so no two threads write the same element) accumulates the
gradient tables. Every kernel takes ``order`` [R], the order in which rays are visited (neighbouring rays should
touch neighbouring voxels so that the logits rows stay in cache); no result depends on it or on the thread count.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_FLAT = 1e-10  # a CDF step below this is flat (nerfacc / sampling.importance_sample)


@njit(cache=True)
def _cell(px, py, pz, lower, inv_voxel, shape):
    """Point → (lower-corner cell i, j, k; fractions fx, fy, fz), the continuous index clamped to [-1, size]."""
    ux = min(max((px - lower[0]) * inv_voxel - 0.5, -1.0), float(shape[0]))
    uy = min(max((py - lower[1]) * inv_voxel - 0.5, -1.0), float(shape[1]))
    uz = min(max((pz - lower[2]) * inv_voxel - 0.5, -1.0), float(shape[2]))
    i, j, k = math.floor(ux), math.floor(uy), math.floor(uz)
    return int(i), int(j), int(k), ux - i, uy - j, uz - k


@njit(cache=True)
def _corners(vol, i, j, k, shape, rows):
    """Rows of the 8 corners (order 000, 001, 010, 011, 100, 101, 110, 111) into ``rows``; -1 outside the grid."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    for c in range(8):
        ci, cj, ck = i + (c >> 2), j + ((c >> 1) & 1), k + (c & 1)
        if 0 <= ci < nx and 0 <= cj < ny and 0 <= ck < nz:
            rows[c] = ((vol * nx + ci) * ny + cj) * nz + ck
        else:
            rows[c] = -1


@njit(cache=True)
def _corner_weights(fx, fy, fz, out):
    gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
    out[0] = gx * gy * gz
    out[1] = gx * gy * fz
    out[2] = gx * fy * gz
    out[3] = gx * fy * fz
    out[4] = fx * gy * gz
    out[5] = fx * gy * fz
    out[6] = fx * fy * gz
    out[7] = fx * fy * fz


@njit(cache=True)
def _sigma_at(sigma, vol, px, py, pz, lower, inv_voxel, shape, rows, cw):
    i, j, k, fx, fy, fz = _cell(px, py, pz, lower, inv_voxel, shape)
    _corners(vol, i, j, k, shape, rows)
    _corner_weights(fx, fy, fz, cw)
    s = 0.0
    for c in range(8):
        if rows[c] >= 0:
            s += cw[c] * sigma[rows[c]]
    return s


@njit(cache=True, inline="always")
def _logit_row(row, shift, logit_rows):
    """The logits table's row of the voxel at σ row ``row`` (``shift`` moves it to the ray's logits volume; through
    ``logit_rows`` when that table is given: -1 = the voxel has no row, it reads zero)."""
    if logit_rows.shape[0] == 0:
        return row + shift
    return logit_rows[row + shift]


@njit(cache=True)
def _add_cell_semantics(rows, acc, sem, logits, shift, logit_rows):
    """A ray leaves a cell: add Σ_k acc_k · logits[row of corner k] to the semantics ``sem`` [C] (corners outside:
    -1; :func:`_logit_row` finds the row)."""
    for c in range(8):
        if rows[c] >= 0 and acc[c] != 0.0:
            lr = _logit_row(rows[c], shift, logit_rows)
            if lr >= 0:
                for ch in range(sem.shape[0]):
                    sem[ch] += acc[c] * logits[lr, ch]


@njit(cache=True)
def _scatter_cell(rows, acc_w, acc_s, g, grad_sigma, grad_logits, shift, logit_rows):
    """A ray leaves a cell: add acc_s_k to grad_sigma[rows_k] and acc_w_k · g to grad_logits[logits row of corner k]
    (either table may be empty: not needed). Corners with row -1, and logits rows -1, are skipped."""
    for c in range(8):
        row = rows[c]
        if row >= 0:
            if grad_sigma.shape[0] > 0:
                grad_sigma[row] += acc_s[c]
            if grad_logits.shape[0] > 0 and acc_w[c] != 0.0:
                lr = _logit_row(row, shift, logit_rows)
                if lr >= 0:
                    for ch in range(g.shape[0]):
                        grad_logits[lr, ch] += acc_w[c] * g[ch]


@njit(parallel=True, cache=True)
def render_forward(sigma, logits, logit_rows, origins, directions, edges, ray_volume, ray_logits, order, bias, lower,
                   voxel_size, shape, near, far, scale, uniform_mix, depth, semantics, weight_sum, weights, sigma_out,
                   t_out, a_out, b_out):
    """Render every ray (see module docstring).

    In: sigma [n·X·Y·Z] (flat σ volumes), logits [m·X·Y·Z, C] (flat logits volumes) or, with ``logit_rows``
    int64 [m·X·Y·Z] (the row of each voxel, -1: none, reads zero; size 0: no table), [K, C]; origins/directions [R, 3]
    (ego frame of the grid, unit directions; float64), edges [R, M + 1] coarse bin edges (float64), ray_volume [R]
    int64 (the σ volume of each ray), ray_logits [R] int64 (its logits volume), order [R] int64,
    bias [R] fine-draw offsets (0.5 = mid-bin), lower [3], voxel_size, shape [3] int64, near (scalar), far [R]
    (each ray's far end, float64; the last coarse edge). Out (written): depth [R], semantics [R, C], weight_sum [R], weights/sigma_out/t_out/a_out/b_out [R, N].
    The draws and intervals are computed in float64; the fine pass then reads the *stored* t, a, b (the output
    dtype), exactly as the backward kernels will, so that forward and backward see the same samples.
    """
    n_rays, n_bins, n_fine, channels = origins.shape[0], edges.shape[1] - 1, t_out.shape[1], logits.shape[1]
    inv_voxel = 1.0 / voxel_size
    for n in prange(n_rays):
        r = order[n]
        rows = np.empty(8, np.int64)
        cw = np.empty(8)
        cdf = np.empty(n_bins + 1)
        ts = np.empty(n_fine)
        acc = np.zeros(8)
        sem = np.zeros(channels)
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        vol = ray_volume[r]
        shift = (ray_logits[r] - vol) * shape[0] * shape[1] * shape[2]
        # coarse pass: CDF = 1 - T at the first M edges and 1 at the last (the official distribution: the light
        # that passes through every bin is drawn in the last one; sampling.cdf_from_sigma)
        cdf[0] = 0.0
        optical = 0.0
        for m in range(n_bins - 1):
            e0, e1 = edges[r, m], edges[r, m + 1]
            mid = 0.5 * (e0 + e1)
            s = _sigma_at(sigma, vol, ox + mid * dx, oy + mid * dy, oz + mid * dz, lower, inv_voxel, shape, rows, cw)
            optical += scale * s * (e1 - e0)
            cdf[m + 1] = 1.0 - math.exp(-optical)
        cdf[n_bins] = 1.0
        if uniform_mix > 0.0:  # both CDFs end at 1: the mixture needs no normalisation
            for m in range(n_bins + 1):
                cdf[m] = (1.0 - uniform_mix) * cdf[m] + uniform_mix * (edges[r, m] - near) / (far[r] - near)
        # fine draws: invert the piecewise-linear CDF (searchsorted "right" over cdf[:-1], as nerfacc)
        lo, hi = cdf[0], cdf[n_bins]
        step = (hi - lo) / n_fine
        p = 0
        for i in range(n_fine):
            u = lo + (i + bias[r]) * step
            while p < n_bins and cdf[p] <= u:
                p += 1
            p0, p1 = max(p - 1, 0), min(p, n_bins)
            du = cdf[p1] - cdf[p0]
            frac = 0.5 if du < _FLAT else (u - cdf[p0]) / du
            ts[i] = edges[r, p0] + frac * (edges[r, p1] - edges[r, p0])
        # intervals half-way between samples, outer edges half a gap out, clamped to [near, far]
        for i in range(n_fine):
            t = ts[i]
            a_out[r, i] = max(t - 0.5 * (ts[1] - ts[0]), near) if i == 0 else 0.5 * (ts[i - 1] + t)
            b_out[r, i] = min(t + 0.5 * (t - ts[i - 1]), far[r]) if i == n_fine - 1 else 0.5 * (t + ts[i + 1])
            t_out[r, i] = t
        # fine pass, cell by cell (a run of samples in one cell shares its 8 corners)
        ci = cj = ck = -(1 << 30)
        rows[:] = -1
        optical = 0.0
        dep = 0.0
        wsum = 0.0
        for i in range(n_fine):
            t = t_out[r, i]
            i0, j0, k0, fx, fy, fz = _cell(ox + t * dx, oy + t * dy, oz + t * dz, lower, inv_voxel, shape)
            if not (i0 == ci and j0 == cj and k0 == ck):
                _add_cell_semantics(rows, acc, sem, logits, shift, logit_rows)
                ci, cj, ck = i0, j0, k0
                _corners(vol, ci, cj, ck, shape, rows)
                acc[:] = 0.0
            _corner_weights(fx, fy, fz, cw)
            s = 0.0
            for c in range(8):
                if rows[c] >= 0:
                    s += cw[c] * sigma[rows[c]]
            a, b = a_out[r, i], b_out[r, i]
            tau = scale * s * (b - a)
            w = math.exp(-optical) * -math.expm1(-tau)
            optical += tau
            for c in range(8):
                acc[c] += w * cw[c]
            dep += w * 0.5 * (a + b)
            wsum += w
            weights[r, i] = w
            sigma_out[r, i] = s
        _add_cell_semantics(rows, acc, sem, logits, shift, logit_rows)
        depth[r] = dep
        weight_sum[r] = wsum
        for ch in range(channels):
            semantics[r, ch] = sem[ch]


@njit(parallel=True, cache=True)
def sigma_sample_grads(logits, logit_rows, origins, directions, ray_volume, ray_logits, order, lower, voxel_size,
                       shape, scale, weights, sigma_s, t_s, a_s, b_s, g_depth, g_sem, g_wsum, g_sigma_s):
    """∂L/∂σ_i for every fine sample → g_sigma_s [R, N] (written). Rays in parallel (in ``order``); reads only.

    weights, sigma_s, t_s, a_s, b_s [R, N] from ``render_forward``; g_depth [R], g_sem [R, C] or [R, 0] (no loss
    reads the semantics: their term is skipped), g_wsum [R].
    """
    n_rays, n_fine, channels = origins.shape[0], t_s.shape[1], g_sem.shape[1]
    inv_voxel = 1.0 / voxel_size
    for n in prange(n_rays):
        r = order[n]
        rows = np.empty(8, np.int64)
        cw = np.empty(8)
        q = np.empty(8)
        e = np.empty(n_fine)
        ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
        dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
        vol = ray_volume[r]
        shift = (ray_logits[r] - vol) * shape[0] * shape[1] * shape[2]
        ci = cj = ck = -(1 << 30)
        total = 0.0
        for i in range(n_fine):
            t = t_s[r, i]
            i0, j0, k0, fx, fy, fz = _cell(ox + t * dx, oy + t * dy, oz + t * dz, lower, inv_voxel, shape)
            if not (i0 == ci and j0 == cj and k0 == ck):
                ci, cj, ck = i0, j0, k0
                _corners(vol, ci, cj, ck, shape, rows)
                for c in range(8):  # q_k = g_sem · logits[v_k]
                    acc = 0.0
                    lr = _logit_row(rows[c], shift, logit_rows) if rows[c] >= 0 else -1
                    if lr >= 0:
                        for ch in range(channels):
                            acc += g_sem[r, ch] * logits[lr, ch]
                    q[c] = acc
            _corner_weights(fx, fy, fz, cw)
            sem_dot = 0.0
            for c in range(8):
                sem_dot += cw[c] * q[c]
            e[i] = g_depth[r] * 0.5 * (a_s[r, i] + b_s[r, i]) + g_wsum[r] + sem_dot
            total += e[i] * weights[r, i]
        optical = 0.0
        done = 0.0
        for i in range(n_fine):
            w = weights[r, i]
            delta = b_s[r, i] - a_s[r, i]
            trans = math.exp(-optical)
            optical += scale * sigma_s[r, i] * delta
            done += e[i] * w
            d_tau = e[i] * (trans - w) - (total - done)
            g_sigma_s[r, i] = d_tau * scale * delta


@njit(parallel=True, cache=True)
def scatter_grads(origins, directions, ray_volume, ray_logits, order, lower, voxel_size, shape, weights, t_s,
                  g_sigma_s, g_sem, n_groups, grad_sigma, grad_logits, logit_rows):
    """Accumulate ∂L/∂σ into grad_sigma [n·X·Y·Z] and ∂L/∂logits into grad_logits [m·X·Y·Z, C], or [K, C] through
    ``logit_rows`` (as in ``render_forward``; each voxel has its own row) (both added to).

    Parallel over ``n_groups`` owners of voxel slabs: group g writes only voxels whose x index i has
    ``(i // 8) % n_groups == g``, so no two threads write the same element and the result does not depend on the
    number of groups; every group walks all rays but skips the cells it owns no corner of. Arrays as in
    ``sigma_sample_grads``; grad_sigma / grad_logits may be size 0 when not needed.
    """
    n_rays, n_fine = origins.shape[0], t_s.shape[1]
    inv_voxel = 1.0 / voxel_size
    for grp in prange(n_groups):
        rows = np.empty(8, np.int64)
        cw = np.empty(8)
        acc_w = np.zeros(8)
        acc_s = np.zeros(8)
        for n in range(n_rays):
            r = order[n]
            g = g_sem[r]
            ox, oy, oz = origins[r, 0], origins[r, 1], origins[r, 2]
            dx, dy, dz = directions[r, 0], directions[r, 1], directions[r, 2]
            vol = ray_volume[r]
            shift = (ray_logits[r] - vol) * shape[0] * shape[1] * shape[2]
            ci = cj = ck = -(1 << 30)
            rows[:] = -1
            owned = False
            for i in range(n_fine):
                t = t_s[r, i]
                i0, j0, k0, fx, fy, fz = _cell(ox + t * dx, oy + t * dy, oz + t * dz, lower, inv_voxel, shape)
                if not (i0 == ci and j0 == cj and k0 == ck):
                    if owned:
                        _scatter_cell(rows, acc_w, acc_s, g, grad_sigma, grad_logits, shift, logit_rows)
                    ci, cj, ck = i0, j0, k0
                    _corners(vol, ci, cj, ck, shape, rows)
                    owned = False
                    for c in range(8):
                        if rows[c] >= 0 and ((ci + (c >> 2)) >> 3) % n_groups != grp:
                            rows[c] = -1  # another group's voxel
                        owned = owned or rows[c] >= 0
                    acc_w[:] = 0.0
                    acc_s[:] = 0.0
                if owned:
                    _corner_weights(fx, fy, fz, cw)
                    w, gs = weights[r, i], g_sigma_s[r, i]
                    for c in range(8):
                        acc_w[c] += w * cw[c]
                        acc_s[c] += gs * cw[c]
            if owned:
                _scatter_cell(rows, acc_w, acc_s, g, grad_sigma, grad_logits, shift, logit_rows)
