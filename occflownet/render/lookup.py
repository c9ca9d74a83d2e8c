"""Trilinear lookup of voxel volumes at ray samples with ``F.grid_sample``: the reference the fast path
(``numba_render``) is checked and benchmarked against, and the path used on GPUs.

Frames and conventions: points are in the ego frame (metres) of the grid ``grid`` (``occflownet.occ3d.Grid``);
voxel (i, j, k) has its centre at ``grid.lower + (ijk + 0.5) * grid.voxel_size``. The *continuous index* of a
point is ``(p - lower) / voxel_size - 0.5``, so voxel centres sit at integers. Trilinear interpolation blends
the 8 voxel centres around a point; a corner outside the grid contributes zero (``grid_sample`` with
``padding_mode="zeros", align_corners=False``), so values fade to zero over the outer half voxel and are zero
beyond it.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from occflownet.occ3d import Grid


def grid_sample_lookup(volume: torch.Tensor, points: torch.Tensor, ray_volume: torch.Tensor,
                       grid: Grid) -> torch.Tensor:
    """Reference lookup with ``F.grid_sample``: volume [n, X, Y, Z, C], points [R, N, 3], ray_volume [R] → [R, N, C].

    Straightforward and differentiable through autograd; fast on a GPU, slow on a CPU.
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
