"""LSS lifting: per-pixel depth distribution × context features, splatted into the ego-frame voxel grid.

Geometry is computed inside the graph from the runtime ``feature_intrinsics`` and ``cam2ego``:
feature cell (u, v) with depth bin centre d (camera-frame z-depth) is the camera point ``d · K_f⁻¹ [u, v, 1]``,
moved into the ego frame by ``cam2ego``, and falls into voxel ``GRID.index_of(p)``
(``floor((p - GRID.lower) / GRID.voxel_size)``).

Pooling sums the lifted features of the points that fall into a voxel. Training (:meth:`LiftSplat.forward` in train
mode) weights the points outside the grid 0 and scatter-adds every point (``index_add``, whose backward is a
gather). Eval mode — the exported path — keeps the points inside the grid only and sums them by sorted segment sums
(:meth:`LiftSplat._pool_sorted`): the points sorted by voxel, their features summed cumulatively, and the
difference of that sum across each run of equal voxels; its cost follows the points, and nothing is scattered
with a reduction.
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
    # the last two axes merged ([w·3], the origin repeated w times): onnxruntime broadcasts a trailing [3] vector
    # three numbers at a time; the sums are the same
    b, v = cam2ego.shape[:2]
    origin = cam2ego[:, :, :3, 3].repeat(1, 1, w).reshape(b, v, 1, 1, w * 3)        # [B, V, 1, 1, w·3]
    direction = torch.stack(direction, dim=-1).reshape(b, v, 1, h, w * 3)          # [B, V, 1, h, w·3]
    return (origin + depths[:, None, None] * direction).reshape(b, v, -1, h, w, 3)  # [B, V, D, h, w, 3]


def block_layout_rows(index: torch.Tensor, batch: torch.Tensor, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel indices int64 [..., 3] inside the grid and their sample ``batch`` (int64, broadcastable to [...]) →
    (coarse_rows, fine_rows) int64 [...]: rows of the flattened trunk grid [B·X/s·Y/s·Z/s] and of the flattened
    full-resolution grid in block layout [B·X/s·Y/s·Z/s·s³]."""
    cx, cy, cz = (n // stride for n in GRID.shape)
    coarse = torch.div(index, stride, rounding_mode="floor")                        # [..., 3] (>= 0)
    sub = index - coarse * stride
    coarse_rows = ((batch * cx + coarse[..., 0]) * cy + coarse[..., 1]) * cz + coarse[..., 2]
    fine_rows = ((coarse_rows * stride + sub[..., 0]) * stride + sub[..., 1]) * stride + sub[..., 2]
    return coarse_rows, fine_rows


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
    batch = torch.arange(points.shape[0], device=points.device).reshape((-1,) + (1,) * (points.dim() - 2))
    coarse_rows, fine_rows = block_layout_rows(index, batch, stride)
    return coarse_rows, fine_rows, valid.to(torch.float32)


def points_inside(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Ego points [B, ..., 3] → (keep int64 [K]: the flat indices of the points inside the grid, ascending;
    index int64 [K, 3]: their voxels). The voxel is ``GRID.index_of``'s (``GRID.cells_of``, in float32), and a
    point is inside when all three lie in [0, shape): the points :func:`voxel_rows` calls valid (a non-finite
    point fails the comparisons). Only the kept points are turned into integers."""
    cell = GRID.cells_of(points)                                                   # [B, ..., n, 3] float
    rows = cell.reshape(tuple(cell.shape[:-2]) + (-1,))    # [..., n·3]: no [3]-vector broadcast (GRID.cells_of)
    below = rows < rows.new_tensor(tuple(GRID.shape) * cell.shape[-2])
    inside = torch.all(((rows >= 0) & below).reshape(cell.shape), dim=-1)
    keep = torch.nonzero(inside.reshape(-1)).reshape(-1)                           # [K]
    return keep, torch.index_select(cell.reshape(-1, 3), 0, keep).to(torch.int64)


def run_ends(keys: torch.Tensor) -> torch.Tensor:
    """Sorted keys int64 [K] → int64 [U]: the position of the last element of each run of equal keys."""
    last = torch.cat([keys[1:] != keys[:-1], torch.ones_like(keys[:1], dtype=torch.bool)])
    return torch.nonzero(last).reshape(-1)


# Points per block of the sorted segment sums (:class:`BlockedPrefix`): cumulative sums restart at every block, in
# float32, so that their magnitude stays that of at most this many lifted features.
POOL_BLOCK = 16


class BlockedPrefix:
    """Prefix sums of sorted values float32 [K', C] (K' a multiple of POOL_BLOCK, the tail zero-padded) that stay
    accurate over hundreds of thousands of rows: float32 cumulative sums within each block of POOL_BLOCK rows
    (``local``), and the sums of all earlier blocks in float64 (``offsets``, one row per block: a cumulative sum of
    the block totals centred on their mean, so that even a runtime that keeps float64 as float32 sums small
    numbers, plus that mean times the number of earlier blocks). ``at(pos)`` is the sum of rows 0 .. pos, in
    float64."""

    def __init__(self, values: torch.Tensor):
        c = values.shape[-1]
        self.local = torch.cumsum(values.reshape(-1, POOL_BLOCK, c), 1)            # [K'/L, L, C] float32
        totals = self.local[:, -1].to(torch.float64)                               # [K'/L, C]
        mean = totals.mean(0)
        centred = totals - mean
        index = torch.arange(totals.shape[0], device=values.device)[:, None].to(torch.float64)
        # the sums of all earlier blocks: exclusive centred prefix + mean per block, per block (not per row)
        self.offsets = (torch.cumsum(centred, 0) - centred) + index * mean        # [K'/L, C] float64
        self.local = self.local.reshape(-1, c)

    def at(self, pos: torch.Tensor) -> torch.Tensor:
        """Inclusive prefix sums float64 [U, C] at positions int64 [U]."""
        block = pos // POOL_BLOCK              # integer ops in ONNX (a float floor division is lost in fp16)
        return torch.index_select(self.offsets, 0, block) + torch.index_select(self.local, 0, pos).to(torch.float64)

    def run_sums(self, ends: torch.Tensor) -> torch.Tensor:
        """The sums over runs of rows ending at ``ends`` int64 [U] (:func:`run_ends`) → float32 [U, C]: the
        difference of the prefix across each run, in float64, rounded to float32 once (and only then joined: a
        float64 concatenation of base's 134,000 × 32 trunk sums took 25–33 ms)."""
        at = self.at(ends)
        return torch.cat([at[:1].to(torch.float32), (at[1:] - at[:-1]).to(torch.float32)])


def scatter_pool(features: torch.Tensor, rows: torch.Tensor, num_rows) -> torch.Tensor:
    """Sum ``features`` [N, C] into a zero-initialised [num_rows, C] by ``rows`` int64 [N] (repeats add up)."""
    return torch.index_add(features.new_zeros((num_rows, features.shape[1])), 0, rows, features)


class LiftSplat(nn.Module):
    """Outer product of depth distribution and context, splatted into the voxel grid.

    forward(depth_prob [B, V, D, h, w], context [B, V, h, w, C], fine [B, V, h, w, F] or None,
            feature_intrinsics [B, V, 3, 3], cam2ego [B, V, 4, 4])
    → (trunk grid [B, X/s, Y/s, Z/s, C] (ego frame, summed features),
       fine points (rows int64 [N], features [N, F]) or None: the full-resolution lifted features (row =
       block-layout voxel, see :func:`voxel_rows`), which the decoder adds into its upsampled grid; in training
       every frustum point (N = B·V·D·h·w, weighted 0 outside the grid, rows repeat), in eval mode already pooled:
       one row per voxel that holds a point, ascending, with the sum of its points' features).
    """

    def __init__(self, depth_centers: list[float], stride: int):
        super().__init__()
        self.stride = stride
        self.register_buffer("depths", torch.tensor(depth_centers, dtype=torch.float32), persistent=False)

    def forward(self, depth_prob, context, fine, feature_intrinsics, cam2ego):
        b, _, _, h, w = depth_prob.shape
        points = frustum_points(feature_intrinsics, cam2ego, self.depths, h, w)
        if not self.training:
            return self._pool_sorted(depth_prob, context, fine, points)
        coarse_rows, fine_rows, valid = voxel_rows(points, self.stride)
        cx, cy, cz = (n // self.stride for n in GRID.shape)
        weight = (depth_prob * valid)[..., None]                                   # [B, V, D, h, w, 1]
        lifted = (weight * context[:, :, None]).reshape(-1, context.shape[-1])      # [N, C]
        trunk = scatter_pool(lifted, coarse_rows.reshape(-1), b * cx * cy * cz).reshape(b, cx, cy, cz, -1)
        if fine is None:
            return trunk, None
        return trunk, (fine_rows.reshape(-1), (weight * fine[:, :, None]).reshape(-1, fine.shape[-1]))

    def _pool_sorted(self, depth_prob, context, fine, points):
        """Eval mode (the exported path): the training path's sums over the points inside the grid (about half of
        the frustum on the real frame, docs/results.md#inference), as sorted segment sums: the points sorted by voxel
        (block-layout row; ``topk`` ascending → ONNX ``TopK``, whose ties keep their index order), their
        lifted context and fine features summed cumulatively (:class:`BlockedPrefix`), and each voxel's sum the
        difference of that sum across its run of points; the trunk's cells are runs of the same order. Nothing is
        scattered with a reduction: the trunk grid's rows are set once (ScatterND without a reduction). The sums
        equal ``index_add``'s up to float32 rounding (prefixes of at most POOL_BLOCK features in float32, the
        blocks before them in float64)."""
        b, v, d, h, w = depth_prob.shape
        cx, cy, cz = (n // self.stride for n in GRID.shape)
        keep, index = points_inside(points)                                        # [K], [K, 3]
        batch = torch.div(keep, v * d * h * w, rounding_mode="floor")
        coarse_rows, fine_rows = block_layout_rows(index, batch, self.stride)
        order = torch.topk(fine_rows, fine_rows.shape[0], largest=False, sorted=True).indices  # [K]
        key, point = torch.index_select(fine_rows, 0, order), torch.index_select(keep, 0, order)
        pad = torch.zeros_like(point[:(-point.shape[0]) % POOL_BLOCK])             # to whole blocks: weight 0
        weight = torch.cat([torch.index_select(depth_prob.reshape(-1), 0, point), pad.to(depth_prob.dtype)])
        point = torch.cat([point, pad])
        pixel = torch.div(point, d * h * w, rounding_mode="floor") * (h * w) + torch.remainder(point, h * w)

        def lifted(features):                                                      # [B, V, h, w, C] → [K', C]
            return weight[:, None] * torch.index_select(features.reshape(-1, features.shape[-1]), 0, pixel)

        ends = run_ends(key // self.stride ** 3)                                   # runs of trunk cells
        rows = torch.index_select(coarse_rows, 0, torch.index_select(order, 0, ends))
        trunk = torch.zeros((b * cx * cy * cz, context.shape[-1]), dtype=weight.dtype, device=weight.device)
        trunk = torch.index_put(trunk, (rows,), BlockedPrefix(lifted(context)).run_sums(ends))
        trunk = trunk.reshape(b, cx, cy, cz, -1)
        if fine is None:
            return trunk, None
        ends = run_ends(key)
        return trunk, (torch.index_select(key, 0, ends), BlockedPrefix(lifted(fine)).run_sums(ends))
