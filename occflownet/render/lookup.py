"""Trilinear lookup of voxel volumes at ray samples: fast flat-index gathers, and a grid_sample reference.

Frames and conventions: points are in the ego frame (metres) of the grid ``grid`` (``occflownet.config.Grid``);
voxel (i, j, k) has its centre at ``grid.lower + (ijk + 0.5) * grid.voxel_size``. The *continuous index* of a
point is ``(p - lower) / voxel_size - 0.5``, so voxel centres sit at integers. Trilinear interpolation blends
the 8 voxel centres around a point; a corner outside the grid contributes zero (``grid_sample`` with
``padding_mode="zeros", align_corners=False``), so values fade to zero over the outer half voxel and are zero
beyond it.

Volumes are addressed as flat tables: ``sigma_flat`` [V] and ``logits_flat`` [V, C] with
``V = n_volumes * X * Y * Z`` and row ``v * XYZ + (i * Y + j) * Z + k`` (a contiguous [n, X, Y, Z(, C)] tensor
reshaped). ``ray_volume`` [R] (long) picks each ray's volume.

Speed (CPU): consecutive fine samples of one ray usually fall in the same interpolation cell, so the fine pass
groups them into *runs* and gathers the 8 corner rows once per run, not once per sample; the semantic
mixture ``Σ_i w_i s_i`` is linear in the logits, so it is accumulated per run (``Σ_{i in run} w_i c_ik``) and
never materialised per sample. The backward passes are ``index_add_`` scatters (PyTorch's backward of
``index_select``), which beat ``grid_sample``'s 3D backward on CPU by a wide margin (docs/render.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from occflownet.config import Grid


def continuous_index(points: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Ego-frame points [..., 3] → continuous voxel index [..., 3] (voxel centres at integers)."""
    lower = torch.tensor(grid.lower, dtype=points.dtype, device=points.device)
    return (points - lower) / grid.voxel_size - 0.5


def _axis_corners(u: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One axis: continuous index [S] → (lower-corner index [S] long, weights [S, 2], in-grid mask [S, 2])."""
    base = torch.floor(u)
    frac = u - base
    base = base.long()
    idx = torch.stack([base, base + 1], dim=-1)
    weights = torch.stack([1.0 - frac, frac], dim=-1)
    valid = (idx >= 0) & (idx < size)
    return base, weights, valid


def _corner_rows(cells: torch.Tensor, volume: torch.Tensor, grid: Grid) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower-corner cells [K, 3] (long) and volume ids [K] → (flat rows [K, 8] clamped into the grid, valid [K, 8]).

    Corner order is (dx, dy, dz) in row-major order: 000, 001, 010, 011, 100, 101, 110, 111.
    """
    nx, ny, nz = grid.shape
    offs = torch.tensor([0, 1], device=cells.device)
    ix, iy, iz = (cells[:, a:a + 1] + offs for a in range(3))  # [K, 2] each
    vx, vy, vz = (ix >= 0) & (ix < nx), (iy >= 0) & (iy < ny), (iz >= 0) & (iz < nz)
    ix, iy, iz = ix.clamp(0, nx - 1), iy.clamp(0, ny - 1), iz.clamp(0, nz - 1)
    rows = ((volume[:, None, None, None] * nx + ix[:, :, None, None]) * ny + iy[:, None, :, None]) * nz \
        + iz[:, None, None, :]
    valid = vx[:, :, None, None] & vy[:, None, :, None] & vz[:, None, None, :]
    return rows.reshape(-1, 8), valid.reshape(-1, 8)


def _corner_weights(frac: torch.Tensor) -> torch.Tensor:
    """Fractions [S, 3] within the cell → trilinear weights [S, 8] (same corner order as ``_corner_rows``)."""
    wx = torch.stack([1.0 - frac[:, 0], frac[:, 0]], dim=-1)
    wy = torch.stack([1.0 - frac[:, 1], frac[:, 1]], dim=-1)
    wz = torch.stack([1.0 - frac[:, 2], frac[:, 2]], dim=-1)
    return (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)


def sample_sigma_pointwise(sigma_flat: torch.Tensor, points: torch.Tensor, point_volume: torch.Tensor,
                           grid: Grid) -> torch.Tensor:
    """σ at points [S, 3] (ego frame), each in volume ``point_volume`` [S] → [S]; 8 gathers per point.

    Used for the coarse pass (one channel, samples 0.8 m apart so there is nothing to share between samples).
    Differentiable in ``sigma_flat`` (the renderer calls it under ``no_grad``).
    """
    u = continuous_index(points, grid)
    cells = torch.floor(u)
    frac = u - cells
    rows, valid = _corner_rows(cells.long(), point_volume, grid)
    w = _corner_weights(frac) * valid.to(frac.dtype)
    return (sigma_flat.index_select(0, rows.reshape(-1)).view(-1, 8) * w).sum(-1)


@dataclass
class SampleRuns:
    """Fine samples [R, N] grouped into runs of consecutive samples of one ray sharing an interpolation cell.

    run_of_sample: [R * N] long, run id of each sample (row-major over [R, N]); corner_rows: [n_runs, 8] long
    flat table rows (clamped); corner_valid: [n_runs, 8] float, 0 for corners outside the grid;
    ray_of_run: [n_runs] long; weights: [R * N, 8] trilinear weights of each sample in its cell.
    """

    run_of_sample: torch.Tensor
    corner_rows: torch.Tensor
    corner_valid: torch.Tensor
    ray_of_run: torch.Tensor
    weights: torch.Tensor
    n_rays: int
    n_samples: int

    @property
    def n_runs(self) -> int:
        return int(self.ray_of_run.shape[0])


def group_runs(points: torch.Tensor, ray_volume: torch.Tensor, grid: Grid) -> SampleRuns:
    """Points [R, N, 3] (ego frame, sorted along each ray) and ray volumes [R] → ``SampleRuns``."""
    n_rays, n_samples, _ = points.shape
    u = continuous_index(points, grid)
    cells = torch.floor(u)
    frac = (u - cells).reshape(-1, 3)
    cells = cells.long()
    new_run = torch.ones((n_rays, n_samples), dtype=torch.bool, device=points.device)
    if n_samples > 1:
        new_run[:, 1:] = (cells[:, 1:] != cells[:, :-1]).any(-1)
    new_run = new_run.reshape(-1)
    run_of_sample = torch.cumsum(new_run, 0) - 1
    starts = torch.nonzero(new_run).squeeze(1)
    ray_of_run = torch.div(starts, n_samples, rounding_mode="floor")
    rows, valid = _corner_rows(cells.reshape(-1, 3).index_select(0, starts), ray_volume.index_select(0, ray_of_run),
                               grid)
    return SampleRuns(run_of_sample, rows, valid.to(points.dtype), ray_of_run, _corner_weights(frac),
                      n_rays, n_samples)


def sample_sigma_runs(sigma_flat: torch.Tensor, runs: SampleRuns) -> torch.Tensor:
    """σ at every fine sample → [R, N]; differentiable in ``sigma_flat``; one 8-corner gather per run."""
    corner_sigma = sigma_flat.index_select(0, runs.corner_rows.reshape(-1)).view(-1, 8) * runs.corner_valid
    per_sample = (corner_sigma.index_select(0, runs.run_of_sample) * runs.weights).sum(-1)
    return per_sample.view(runs.n_rays, runs.n_samples)


def mix_logits_runs(logits_flat: torch.Tensor, runs: SampleRuns, sample_weights: torch.Tensor) -> torch.Tensor:
    """Σ_i w_i · logits(sample_i) per ray → [R, C]; differentiable in ``logits_flat`` and ``sample_weights`` [R, N].

    Equals gathering the interpolated logits of every sample and summing them with the rendering weights,
    but gathers each run's 8 corner rows once: ``Σ_runs Σ_k (Σ_{i in run} w_i c_ik) · row_k``.
    """
    per_corner = sample_weights.reshape(-1, 1) * runs.weights  # [R*N, 8]
    run_coeff = per_corner.new_zeros(runs.n_runs, 8).index_add(0, runs.run_of_sample, per_corner)
    run_coeff = run_coeff * runs.corner_valid
    rows = logits_flat.index_select(0, runs.corner_rows.reshape(-1))  # [n_runs*8, C]
    contrib = rows * run_coeff.reshape(-1, 1)
    target = runs.ray_of_run.repeat_interleave(8)
    return contrib.new_zeros(runs.n_rays, logits_flat.shape[1]).index_add(0, target, contrib)


def grid_sample_lookup(volume: torch.Tensor, points: torch.Tensor, ray_volume: torch.Tensor,
                       grid: Grid) -> torch.Tensor:
    """Reference lookup with ``F.grid_sample``: volume [n, X, Y, Z, C], points [R, N, 3], ray_volume [R] → [R, N, C].

    This is the straightforward (slow on CPU) implementation the fast path is checked and benchmarked against.
    """
    n_rays, n_samples, _ = points.shape
    channels = volume.shape[-1]
    lower = torch.tensor(grid.lower, dtype=points.dtype, device=points.device)
    extent = torch.tensor(grid.shape, dtype=points.dtype, device=points.device) * grid.voxel_size
    norm = (points - lower) / extent * 2.0 - 1.0  # grid_sample wants (x→W, y→H, z→D)
    out = points.new_zeros(n_rays, n_samples, channels)
    for v in torch.unique(ray_volume).tolist():
        sel = torch.nonzero(ray_volume == v).squeeze(1)
        vol = volume[v].permute(3, 2, 1, 0).unsqueeze(0)  # [1, C, Z, Y, X]
        g = norm.index_select(0, sel).reshape(1, 1, 1, -1, 3)
        vals = F.grid_sample(vol, g, mode="bilinear", padding_mode="zeros", align_corners=False)
        out = out.index_copy(0, sel, vals.reshape(channels, sel.numel(), n_samples).permute(1, 2, 0))
    return out
