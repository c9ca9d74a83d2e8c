"""LSS lifting: per-pixel depth distribution × context features, splatted into the ego-frame voxel grid.

Geometry is computed inside the graph from the runtime ``feature_intrinsics`` and ``cam2ego``:
feature cell (u, v) with depth bin centre d (camera-frame z-depth) is the camera point ``d · K_f⁻¹ [u, v, 1]``,
moved into the ego frame by ``cam2ego``, and falls into voxel ``GRID.index_of(p)``
(``floor((p - GRID.lower) / GRID.voxel_size)``).
Points outside the grid contribute nothing (they are routed to a discarded dump row).

Pooling is a scatter-add (``index_add`` → ONNX ScatterND with ``reduction="add"``, correct for repeated indices).
The trunk grid is the full grid coarsened by ``stride``; the optional fine (skip) features keep full resolution
and are addressed in *block layout* [B, X/s, Y/s, Z/s, s, s, s] so the decoder can add them without transposes.
"""
from __future__ import annotations

import torch
from torch import nn

from occflownet.occ3d import GRID


class DepthContextHead(nn.Module):
    """Stride-16 features [N, C_in, h, w] → (depth logits [N, D, h, w], context [N, C, h, w], fine [N, F, h, w])."""

    def __init__(self, in_channels: int, num_bins: int, context_channels: int, fine_channels: int):
        super().__init__()
        self.splits = (num_bins, context_channels, fine_channels)
        self.body = nn.Sequential(
            nn.Conv2d(in_channels, in_channels, kernel_size=3, padding=1, bias=False),
            nn.BatchNorm2d(in_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(in_channels, sum(self.splits), kernel_size=1),
        )

    def forward(self, x: torch.Tensor):
        return torch.split(self.body(x), list(self.splits), dim=1)


def invert_3x3(m: torch.Tensor) -> torch.Tensor:
    """Inverse of [..., 3, 3] matrices by cofactors (elementwise ops only, so it exports to plain ONNX)."""
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    d, e, f = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    g, h, i = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    co = [e * i - f * h, c * h - b * i, b * f - c * e,
          f * g - d * i, a * i - c * g, c * d - a * f,
          d * h - e * g, b * g - a * h, a * e - b * d]
    det = a * co[0] + b * co[3] + c * co[6]
    inv = torch.stack(co, dim=-1) / det[..., None]
    return inv.reshape(m.shape)


def frustum_points(feature_intrinsics: torch.Tensor, cam2ego: torch.Tensor, depths: torch.Tensor,
                   h: int, w: int) -> torch.Tensor:
    """Ego-frame positions [B, V, D, h, w, 3] of the frustum points (feature cell centres × depth bins).

    feature_intrinsics [B, V, 3, 3] (camera frame → feature-map pixels); cam2ego [B, V, 4, 4];
    depths [D] z-depths in metres. Written with explicit products and sums (no MatMul) so that torch and
    onnxruntime compute bit-identical coordinates and therefore identical voxel indices.
    """
    k_inv = invert_3x3(feature_intrinsics)[:, :, None, None]                       # [B, V, 1, 1, 3, 3]
    u = torch.arange(w, dtype=torch.float32, device=depths.device)[None, :]        # [1, w]
    v = torch.arange(h, dtype=torch.float32, device=depths.device)[:, None]        # [h, 1]
    ray = [k_inv[..., r, 0] * u + k_inv[..., r, 1] * v + k_inv[..., r, 2] for r in range(3)]  # 3 × [B,V,h,w]
    rot = cam2ego[:, :, None, None, :3, :3]
    direction = [rot[..., r, 0] * ray[0] + rot[..., r, 1] * ray[1] + rot[..., r, 2] * ray[2] for r in range(3)]
    origin = cam2ego[:, :, None, None, None, :3, 3]                                 # [B, V, 1, 1, 1, 3]
    direction = torch.stack(direction, dim=-1)[:, :, None]                          # [B, V, 1, h, w, 3]
    return origin + depths[:, None, None, None] * direction                         # [B, V, D, h, w, 3]


def voxel_rows(points: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ego points [B, ..., 3] → (coarse_rows, fine_rows int64 [B, ...], valid float32 [B, ...]).

    coarse_rows index the flattened trunk grid [B·X/s·Y/s·Z/s]; fine_rows the flattened full-resolution grid in
    block layout [B·X/s·Y/s·Z/s·s³]. Points outside the grid (or not finite) get row 0 and valid = 0, so that
    multiplying their features by ``valid`` makes them contribute nothing.
    """
    finite = torch.all(torch.isfinite(points), dim=-1)
    points = torch.where(finite[..., None], points, torch.full_like(points, -1e4))
    index = GRID.index_of(points)                                                   # [B, ..., 3] int64
    shape = torch.tensor(GRID.shape, dtype=torch.int64, device=points.device)
    valid = torch.all((index >= 0) & (index < shape), dim=-1)                       # [B, ...]
    index = torch.where(valid[..., None], index, torch.zeros_like(index))
    cx, cy, cz = (n // stride for n in GRID.shape)
    coarse = torch.div(index, stride, rounding_mode="floor")                        # [B, ..., 3] (>= 0)
    sub = index - coarse * stride
    batch = torch.arange(points.shape[0], device=points.device).reshape((-1,) + (1,) * (points.dim() - 2))
    coarse_rows = ((batch * cx + coarse[..., 0]) * cy + coarse[..., 1]) * cz + coarse[..., 2]
    fine_rows = ((coarse_rows * stride + sub[..., 0]) * stride + sub[..., 1]) * stride + sub[..., 2]
    return coarse_rows, fine_rows, valid.to(torch.float32)


def scatter_pool(features: torch.Tensor, rows: torch.Tensor, num_rows) -> torch.Tensor:
    """Sum ``features`` [N, C] into a zero-initialised [num_rows, C] by ``rows`` int64 [N] (repeats add up)."""
    return torch.index_add(features.new_zeros((num_rows, features.shape[1])), 0, rows, features)


class LiftSplat(nn.Module):
    """Outer product of depth distribution and context, splatted into the voxel grid.

    forward(depth_prob [B, V, D, h, w], context [B, V, h, w, C], fine [B, V, h, w, F] or None,
            feature_intrinsics [B, V, 3, 3], cam2ego [B, V, 4, 4])
    → (trunk grid [B, X/s, Y/s, Z/s, C] (ego frame, summed features),
       fine points (rows int64 [N], features [N, F]) or None: the full-resolution lifted features, not yet pooled
       (row = block-layout voxel, see :func:`voxel_rows`); the decoder scatter-adds them into its upsampled grid;
       in eval mode only the N ≤ B·V·D·h·w points inside the grid, in training all of them, weighted 0 outside).
    """

    def __init__(self, depth_centers: list[float], stride: int):
        super().__init__()
        self.stride = stride
        self.register_buffer("depths", torch.tensor(depth_centers, dtype=torch.float32), persistent=False)

    def forward(self, depth_prob, context, fine, feature_intrinsics, cam2ego):
        b, _, _, h, w = depth_prob.shape
        points = frustum_points(feature_intrinsics, cam2ego, self.depths, h, w)
        coarse_rows, fine_rows, valid = voxel_rows(points, self.stride)
        cx, cy, cz = (n // self.stride for n in GRID.shape)
        if self.training:
            weight = (depth_prob * valid)[..., None]                               # [B, V, D, h, w, 1]
            lifted = (weight * context[:, :, None]).reshape(-1, context.shape[-1])  # [N, C]
            trunk = scatter_pool(lifted, coarse_rows.reshape(-1), b * cx * cy * cz).reshape(b, cx, cy, cz, -1)
            if fine is None:
                return trunk, None
            return trunk, (fine_rows.reshape(-1), (weight * fine[:, :, None]).reshape(-1, fine.shape[-1]))
        return self._pool_valid(depth_prob, context, fine, coarse_rows, fine_rows, valid)

    def _pool_valid(self, depth_prob, context, fine, coarse_rows, fine_rows, valid):
        """Eval mode (the exported path): the same sums with the points outside the grid left out before the
        outer product (about half of them on the real frame: tiny 53 %, base 46 %), so the scatter-add and the
        products see only the points that count. The kept points stay in their order (NonZero is ascending) and a
        dropped point only ever added 0 · feature = 0 to row 0, so the pooled sums are bit-identical to the
        training path's."""
        b, v, d, h, w = depth_prob.shape
        cx, cy, cz = (n // self.stride for n in GRID.shape)
        keep = torch.nonzero(valid.reshape(-1)).reshape(-1)                        # [K] point indices
        pixel = torch.div(keep, d * h * w, rounding_mode="floor") * (h * w) + torch.remainder(keep, h * w)
        pick = torch.index_select                                                  # ONNX Gather
        weight = pick(depth_prob.reshape(-1), 0, keep)[:, None]                    # [K, 1]
        lifted = weight * pick(context.reshape(-1, context.shape[-1]), 0, pixel)   # [K, C]
        trunk = scatter_pool(lifted, pick(coarse_rows.reshape(-1), 0, keep), b * cx * cy * cz)
        trunk = trunk.reshape(b, cx, cy, cz, -1)
        if fine is None:
            return trunk, None
        return trunk, (pick(fine_rows.reshape(-1), 0, keep), weight * pick(fine.reshape(-1, fine.shape[-1]), 0, pixel))
