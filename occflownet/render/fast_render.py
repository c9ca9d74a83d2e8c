"""The fast rendering path: chunked coarse-to-fine rendering with a hand-written backward (CPU-friendly).

Same mathematics as ``volume_render`` (and its ``lookup="grid_sample"`` reference, which the tests compare
against, gradients included); this module only organises the work so that it is cheap on a CPU:

- rays are processed in chunks (``RenderConfig.chunk_rays``) so that temporaries stay small and cache-resident
  instead of allocating hundreds of MB per operation;
- the coarse pass needs σ only and no gradient: one 1-channel ``grid_sample`` (fast for a single channel);
- consecutive fine samples of a ray that fall in the same interpolation cell form a *run*; the 8 corner voxels
  are looked up once per run, not once per sample;
- the semantic mixture ``Σ_i w_i s_i`` is linear in the logits, so it is computed as ``Σ_v A_v · logits[v]``
  over the distinct voxels v a ray touches, ``A_v`` summing ``w_i c_ik`` over every (sample, corner) at v,
  by one fused ``embedding_bag`` per chunk; the per-sample interpolated logits are never materialised.
  Neighbouring runs of a ray share corners (a step to the next cell keeps 4 of 8), so corner entries are
  merged into the first entry of the same voxel along the ray (``_merge_shared_corners``), roughly halving
  the 17-channel work;
- the backward is written out (volume-rendering derivative below), scattering straight into one gradient
  table for σ and one for the logits, instead of autograd building a full-size gradient per operation.

Backward of the rendering: with e_i = ∂L/∂w_i = g_depth·m_i + g_wsum + g_sem·s_i and T_{i+1} = T_i - w_i,
  ∂L/∂τ_k = e_k T_{k+1} - Σ_{i>k} e_i w_i,   ∂L/∂σ_k = ∂L/∂τ_k · density_scale · δ_k,
  ∂L/∂logits[v] = Σ_rays g_sem · Σ_{runs, corners k at v} A_run,k.
"""
from __future__ import annotations

from contextlib import contextmanager

import torch
import torch.nn.functional as F

from occflownet.render.lookup import PaddedTables, corner_weights, grid_sample_lookup
from occflownet.render.sampling import importance_sample, intervals_from_samples


@contextmanager
def intra_op_threads(n: int):
    """Run the enclosed torch ops with ``n`` intra-op threads (n <= 0: leave the setting alone), then restore.

    The fast path issues ~100 medium-sized ops per chunk; with OpenMP on a machine whose cores are busy with other
    processes, every op can stall on a descheduled worker thread (measured: 60x slower on the shared 2-core box),
    so the renderer defaults to one thread (``RenderConfig.intra_op_threads``).
    """
    old = torch.get_num_threads()
    if n <= 0 or n == old:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def coarse_cdf(density, origins, directions, edges, ray_volume, cfg) -> torch.Tensor:
    """CDF [r, n_coarse + 1] = 1 - T at the coarse edges, from the σ volumes ``density`` [n, X, Y, Z] (no grad)."""
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
    points = origins[:, None, :] + mids[..., None] * directions[:, None, :]
    sigma = grid_sample_lookup(density.unsqueeze(-1), points, ray_volume, cfg.grid)[..., 0]
    return cdf_from_sigma(edges, sigma, cfg)


def cdf_from_sigma(edges: torch.Tensor, sigma: torch.Tensor, cfg) -> torch.Tensor:
    """Coarse σ [r, M] at bins with edges [r, M + 1] → CDF [r, M + 1] (``1 - T`` at the edges)."""
    tau = cfg.density_scale * sigma * (edges[:, 1:] - edges[:, :-1])
    cdf = 1.0 - torch.exp(-torch.cumsum(tau, dim=-1))
    cdf = torch.cat([cdf.new_zeros(cdf.shape[0], 1), cdf], dim=-1)
    if cfg.uniform_mix > 0:
        normalised = cdf / cdf[:, -1:].clamp(min=1e-12)
        uniform = (edges - cfg.near) / (cfg.far - cfg.near)
        cdf = (1.0 - cfg.uniform_mix) * normalised + cfg.uniform_mix * uniform
    return cdf


_CORNERS = torch.tensor([[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]])


def _shared_corner_table() -> torch.Tensor:
    """[28, 8] long: for a step ``delta`` ∈ {-1, 0, 1}³ between consecutive cells (code = 9(dx+1) + 3(dy+1) +
    (dz+1); code 27 = any larger step), the corner k' of the previous cell that equals corner k of the new cell,
    or -1 when corner k is new."""
    table = torch.full((28, 8), -1, dtype=torch.long)
    for code in range(27):
        delta = torch.tensor([code // 9 - 1, code // 3 % 3 - 1, code % 3 - 1])
        e = _CORNERS + delta
        ok = ((e >= 0) & (e <= 1)).all(-1)
        table[code] = torch.where(ok, e[:, 0] * 4 + e[:, 1] * 2 + e[:, 2], torch.full((8,), -1))
    return table


_SHARED = _shared_corner_table()


def _merge_shared_corners(run_cells: torch.Tensor, ray_of_run: torch.Tensor) -> torch.Tensor:
    """For every corner entry (run, k) → index [n_runs * 8] of the first entry of the same voxel along the ray.

    Runs of one ray visit cells in order along a line, so the runs having voxel v as a corner are consecutive;
    entry (r, k) is linked to (r - 1, k') when ``cell_r + d_k == cell_{r-1} + d_k'``, and links are followed to
    their start by pointer jumping.
    """
    n = run_cells.shape[0]
    entry = torch.arange(n * 8, device=run_cells.device)
    if n < 2:
        return entry
    delta = (run_cells[1:] - run_cells[:-1]).long()
    small = (delta.abs() <= 1).all(-1) & (ray_of_run[1:] == ray_of_run[:-1])
    code = torch.where(small, (delta[:, 0] + 1) * 9 + (delta[:, 1] + 1) * 3 + (delta[:, 2] + 1), 27)
    k_prev = _SHARED.to(run_cells.device).index_select(0, code)  # [n - 1, 8]
    prev = entry[:-8].view(n - 1, 8)[:, :1] + k_prev  # entry index (r - 1) * 8 + k'
    root = entry.clone()
    root[8:] = torch.where(k_prev >= 0, prev, entry[8:].view(n - 1, 8)).reshape(-1)
    while True:
        nxt = root.index_select(0, root)
        if torch.equal(nxt, root):
            return root
        root = nxt


def _runs(tables: PaddedTables, points: torch.Tensor, ray_volume: torch.Tensor):
    """Fine points [r, N, 3] of one chunk → run structure (see module docstring):
    run_of_sample [S], corner rows [n_runs, 8], corner weights [S, 8], and the merged voxel entries:
    entry_of_corner [n_runs * 8] (index into the entries; U for corners outside the grid), entry rows [U]
    (rows of the unpadded logits table), entry rays [U], bag offsets [r]."""
    r, n_samples, _ = points.shape
    cell, frac = tables.cells(points)
    new_run = torch.ones((r, n_samples), dtype=torch.bool, device=points.device)
    new_run[:, 1:] = (cell[:, 1:] != cell[:, :-1]).any(-1)
    new_run = new_run.reshape(-1)
    run_of_sample = torch.cumsum(new_run, 0) - 1
    starts = torch.nonzero(new_run).squeeze(1)
    ray_of_run = torch.div(starts, n_samples, rounding_mode="floor")
    run_cells = cell.reshape(-1, 3).index_select(0, starts)
    rows = tables.base_rows(run_cells, ray_volume.index_select(0, ray_of_run))[:, None] \
        + tables.corner_offsets(points.device)
    root = _merge_shared_corners(run_cells, ray_of_run)
    is_entry = root == torch.arange(root.shape[0], device=root.device)
    entries = torch.nonzero(is_entry).squeeze(1)
    entry_of_corner = (torch.cumsum(is_entry, 0) - 1).index_select(0, root)
    entry_rows = tables.logit_rows(rows.reshape(-1).index_select(0, entries))
    keep = torch.nonzero(entry_rows >= 0).squeeze(1)  # entries outside the grid read zeros: drop them
    renumber = torch.full_like(entries, keep.shape[0])  # dropped entries → one extra slot that stays zero
    renumber[keep] = torch.arange(keep.shape[0], device=keep.device)
    entry_of_corner = renumber.index_select(0, entry_of_corner)
    entries = entries.index_select(0, keep)
    entry_rows = entry_rows.index_select(0, keep)
    entry_rays = ray_of_run.index_select(0, entries >> 3)
    counts = torch.bincount(entry_rays, minlength=r)
    bag_offsets = torch.cumsum(counts, 0) - counts
    return (run_of_sample, rows, corner_weights(frac.reshape(-1, 3)), entry_of_corner, entry_rows, entry_rays,
            bag_offsets)


class FastRender(torch.autograd.Function):
    """Coarse-to-fine rendering of R rays; differentiable in the padded σ table ``sigma_flat``
    (``lookup.PaddedTables`` layout) and the logits table ``logits_flat`` [n * X * Y * Z, C];
    ``density`` [n, X, Y, Z] (detached) feeds the coarse pass.

    Outputs: depth [R], semantics [R, C], weight_sum [R] (differentiable), then weights, sigma, t_samples,
    t_starts, t_ends (all [R, N], not differentiable).
    """

    @staticmethod
    def forward(ctx, sigma_flat, logits_flat, density, origins, directions, edges, ray_volume, cfg, generator):
        with intra_op_threads(cfg.intra_op_threads):
            return FastRender._forward(ctx, sigma_flat, logits_flat, density, origins, directions, edges, ray_volume,
                                       cfg, generator)

    @staticmethod
    def _forward(ctx, sigma_flat, logits_flat, density, origins, directions, edges, ray_volume, cfg, generator):
        tables = PaddedTables(sigma_flat, cfg.grid)
        n_rays, n_fine, channels = origins.shape[0], cfg.n_fine, logits_flat.shape[1]
        new = origins.new_empty
        depth, semantics, weight_sum = new(n_rays), new(n_rays, channels), new(n_rays)
        weights, sigma_out, t_out, a_out, b_out = (new(n_rays, n_fine) for _ in range(5))
        chunks = []
        for r0 in range(0, n_rays, cfg.chunk_rays):
            sl = slice(r0, min(r0 + cfg.chunk_rays, n_rays))
            o, d, vol = origins[sl], directions[sl], ray_volume[sl]
            cdf = coarse_cdf(density, o, d, edges[sl], vol, cfg)
            t = importance_sample(edges[sl], cdf, n_fine, stratified=cfg.fine_stratified, generator=generator)
            a, b = intervals_from_samples(t, cfg.near, cfg.far)
            points = o[:, None, :] + t[..., None] * d[:, None, :]
            run_of_sample, rows, corner_w, entry_of_corner, entry_rows, entry_rays, bag_offsets = \
                _runs(tables, points, vol)
            corner_sigma = sigma_flat.index_select(0, rows.reshape(-1)).view(-1, 8)
            sig = (corner_w * corner_sigma.index_select(0, run_of_sample)).sum(-1).view_as(t)
            tau = cfg.density_scale * sig * (b - a)
            trans = torch.exp(-(torch.cumsum(tau, -1) - tau))
            w = trans * -torch.expm1(-tau)
            depth[sl] = (w * (0.5 * (a + b))).sum(-1)
            weight_sum[sl] = w.sum(-1)
            corner_coeff = corner_w.new_zeros(rows.shape).index_add_(0, run_of_sample, w.reshape(-1, 1) * corner_w)
            entry_coeff = corner_w.new_zeros(entry_rows.shape[0] + 1).index_add_(0, entry_of_corner,
                                                                                 corner_coeff.reshape(-1))[:-1]
            semantics[sl] = F.embedding_bag(entry_rows, logits_flat, bag_offsets, mode="sum",
                                            per_sample_weights=entry_coeff)
            weights[sl], sigma_out[sl], t_out[sl], a_out[sl], b_out[sl] = w, sig, t, a, b
            chunks.append((sl, run_of_sample, rows, corner_w, entry_of_corner, entry_rows, entry_rays, entry_coeff,
                           trans))
        ctx.chunks = chunks
        ctx.density_scale = cfg.density_scale
        ctx.threads = cfg.intra_op_threads
        ctx.save_for_backward(sigma_flat, logits_flat, weights, a_out, b_out)
        ctx.mark_non_differentiable(weights, sigma_out, t_out, a_out, b_out)
        return depth, semantics, weight_sum, weights, sigma_out, t_out, a_out, b_out

    @staticmethod
    def backward(ctx, g_depth, g_sem, g_wsum, *_unused):
        with intra_op_threads(ctx.threads):
            grads = FastRender._backward(ctx, g_depth, g_sem, g_wsum)
        return grads + (None,) * 7

    @staticmethod
    def _backward(ctx, g_depth, g_sem, g_wsum):
        sigma_flat, logits_flat, weights, a_all, b_all = ctx.saved_tensors
        need_sigma, need_logits = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_sigma = torch.zeros_like(sigma_flat) if need_sigma else None
        grad_logits = torch.zeros_like(logits_flat) if need_logits else None
        for sl, run_of_sample, rows, corner_w, entry_of_corner, entry_rows, entry_rays, entry_coeff, trans \
                in ctx.chunks:
            g_entry = g_sem[sl].index_select(0, entry_rays)  # [U, C]: each entry's ray's semantic gradient
            if need_logits:
                grad_logits.index_add_(0, entry_rows, entry_coeff.unsqueeze(-1) * g_entry)
            if not need_sigma:
                continue
            w, a, b = weights[sl], a_all[sl], b_all[sl]
            q_entry = (logits_flat.index_select(0, entry_rows) * g_entry).sum(-1)  # g_sem · logits[v]
            q = torch.cat([q_entry, q_entry.new_zeros(1)]).index_select(0, entry_of_corner).view(-1, 8)
            sem_dot = (corner_w * q.index_select(0, run_of_sample)).sum(-1).view_as(w)  # g_sem · s_i
            e = g_depth[sl, None] * (0.5 * (a + b)) + g_wsum[sl, None] + sem_dot
            ew = e * w
            later = ew.sum(-1, keepdim=True) - torch.cumsum(ew, -1)  # Σ_{i>k} e_i w_i
            d_tau = e * (trans - w) - later
            g_sig = (d_tau * (ctx.density_scale * (b - a))).reshape(-1, 1)
            g_corner = corner_w.new_zeros(rows.shape).index_add_(0, run_of_sample, g_sig * corner_w)
            grad_sigma.index_add_(0, rows.reshape(-1), g_corner.reshape(-1))
        return grad_sigma, grad_logits
