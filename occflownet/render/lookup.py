"""Trilinear lookup of voxel volumes at ray samples: flat-index gathers on zero-padded tables, and a
grid_sample reference.

Frames and conventions: points are in the ego frame (metres) of the grid ``grid`` (``occflownet.config.Grid``);
voxel (i, j, k) has its centre at ``grid.lower + (ijk + 0.5) * grid.voxel_size``. The *continuous index* of a
point is ``(p - lower) / voxel_size - 0.5``, so voxel centres sit at integers. Trilinear interpolation blends
the 8 voxel centres around a point; a corner outside the grid contributes zero (``grid_sample`` with
``padding_mode="zeros", align_corners=False``), so values fade to zero over the outer half voxel and are zero
beyond it.

Fast path: σ is copied into a *padded flat table* with one zero layer below and two above every axis
(``PaddedTables``); continuous indices are clamped to [-1, size] per axis, which leaves every point inside the
grid untouched and sends every point outside it onto zero padding. Corner rows are then ``base + offsets`` with
no bounds checks or validity masks. Row of padded voxel (v, i, j, k), i, j, k ∈ [-1, size + 1]:
``((v * PX + i + 1) * PY + j + 1) * PZ + k + 1`` with ``P* = size + 3``. The 17-channel logits are not copied
(that would cost a 50 MB copy per call): the few corner entries that survive deduplication are mapped back to
rows ``((v * X + i) * Y + j) * Z + k`` of the unpadded [n * X * Y * Z, C] table (``logit_rows``), and those
outside the grid dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from occflownet.config import Grid

PAD_LOW, PAD_HIGH = 1, 2


def continuous_index(points: torch.Tensor, grid: Grid) -> torch.Tensor:
    """Ego-frame points [..., 3] → continuous voxel index [..., 3] (voxel centres at integers)."""
    lower = torch.tensor(grid.lower, dtype=points.dtype, device=points.device)
    return (points - lower) / grid.voxel_size - 0.5


@dataclass
class PaddedTables:
    """σ of n volumes as a zero-padded flat table [n * PX * PY * PZ] (see module docstring), differentiable
    (the padding is ``F.pad``, whose backward crops the gradient back to the grid)."""

    sigma: torch.Tensor
    grid: Grid

    @classmethod
    def from_volumes(cls, density: torch.Tensor, grid: Grid) -> "PaddedTables":
        """density [n, X, Y, Z]."""
        return cls(F.pad(density, (PAD_LOW, PAD_HIGH) * 3).reshape(-1), grid)

    @property
    def padded_shape(self) -> tuple[int, int, int]:
        return tuple(s + PAD_LOW + PAD_HIGH for s in self.grid.shape)

    def corner_offsets(self, device) -> torch.Tensor:
        """Row offsets [8] of the corners (dx, dy, dz) in order 000, 001, 010, 011, 100, 101, 110, 111."""
        _, py, pz = self.padded_shape
        d = torch.tensor([[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]],
                         device=device)
        return d[:, 0] * (py * pz) + d[:, 1] * pz + d[:, 2]

    def cells(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points [..., 3] → (lower-corner cell [..., 3] as float, fraction in the cell [..., 3]), clamped."""
        u = continuous_index(points, self.grid)
        upper = torch.tensor(self.grid.shape, dtype=u.dtype, device=u.device)
        u = torch.maximum(torch.minimum(u, upper), torch.full_like(upper, -1.0))
        cell = torch.floor(u)
        return cell, u - cell

    def base_rows(self, cell: torch.Tensor, volume: torch.Tensor) -> torch.Tensor:
        """Float cells [K, 3] (from ``cells``) and volume ids [K] → row [K] (long) of the cell's corner 000."""
        px, py, pz = self.padded_shape
        c = cell.long() + PAD_LOW
        return ((volume * px + c[:, 0]) * py + c[:, 1]) * pz + c[:, 2]


    def logit_rows(self, padded_rows: torch.Tensor) -> torch.Tensor:
        """Padded rows [K] → rows [K] of the unpadded [n * X * Y * Z] table, -1 for padding voxels."""
        return _unpadded_index(self.grid, self.sigma.shape[0], padded_rows.device).index_select(0, padded_rows)


_UNPADDED_CACHE: dict = {}


def _unpadded_index(grid: Grid, padded_size: int, device) -> torch.Tensor:
    """Lookup table [n * PX * PY * PZ] (long): unpadded row of every padded voxel, -1 in the padding (cached)."""
    key = (grid, padded_size, str(device))
    table = _UNPADDED_CACHE.get(key)
    if table is None:
        nx, ny, nz = grid.shape
        n_vol = padded_size // ((nx + PAD_LOW + PAD_HIGH) * (ny + PAD_LOW + PAD_HIGH) * (nz + PAD_LOW + PAD_HIGH))
        rows = torch.arange(n_vol * nx * ny * nz, device=device).view(n_vol, nx, ny, nz)
        table = F.pad(rows, (PAD_LOW, PAD_HIGH) * 3, value=-1).reshape(-1)
        if len(_UNPADDED_CACHE) > 8:
            _UNPADDED_CACHE.clear()
        _UNPADDED_CACHE[key] = table
    return table


def corner_weights(frac: torch.Tensor) -> torch.Tensor:
    """Fractions [S, 3] within the cell → trilinear weights [S, 8] (corner order of ``corner_offsets``)."""
    fx, fy, fz = frac.unbind(-1)
    gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
    xy = (gx * gy, gx * fy, fx * gy, fx * fy)
    return torch.stack([w for p in xy for w in (p * gz, p * fz)], dim=1)


def sample_sigma_pointwise(tables: PaddedTables, points: torch.Tensor, point_volume: torch.Tensor) -> torch.Tensor:
    """σ at points [S, 3] (ego frame), each in volume ``point_volume`` [S] → [S]; 8 gathers per point.

    Used for the coarse pass (one channel, samples ~0.8 m apart so there is nothing to share between samples).
    """
    cell, frac = tables.cells(points)
    rows = tables.base_rows(cell, point_volume)[:, None] + tables.corner_offsets(points.device)
    return (tables.sigma.index_select(0, rows.reshape(-1)).view(-1, 8) * corner_weights(frac)).sum(-1)


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
