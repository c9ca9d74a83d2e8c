"""Occupancy flow (paper §3.4): move the predicted voxels of dynamic objects into per-time-step copies of the volume.

For a keyframe with prediction (σ [X, Y, Z], logits [X, Y, Z, C]) and a temporal frame t ≠ 0, every dynamic box
matched at t brings (voxels of its enlarged box at time 0, rigid transform ego→ego, class). In the copy for frame t:

1. *selection*: the box's voxels whose predicted class ``argmax(logits)`` equals the box class. A voxel inside
   several enlarged boxes that all select it moves with one box only: the one whose voxel centroid is nearest;
2. *clearing*: every selected source voxel is set to σ = 0 and logits = 0 (all channels). σ = 0 is what matters
   for rendering (the voxel no longer stops rays); zero logits are the neutral value (uniform softmax), so
   trilinear lookups next to a vacated voxel are not pulled towards the object's class, and no gradient reaches
   the source through the vacated place;
3. *moving*: each selected voxel centre x_v goes to x = T x_v (ego frame of the current keyframe) and its values
   (σ(v), s(v)) are written back onto the grid by a *mover*:
   - ``"idw"`` (paper, default): the 8 voxel centres x_i around x get w_i = 1/|x − x_i| (Euclidean), α_i =
     w_i / Σ_p w_p; if x is within 1e-4 m of a centre that centre gets α = 1 and the others 0. For one arrival the
     paper's update is s(v_i) ← α_i s(v) + (1 − α_i) s(v_i). Many arrivals at one target are combined order-free:
     with A_i = Σ_k α_ik (coverage) and m_i = Σ_k α_ik s(v_k) / A_i (weighted mean of the arrivals),
     s(v_i) ← β_i m_i + (1 − β_i) s_base(v_i), β_i = min(A_i, 1). One arrival gives exactly the paper's rule; a
     fully covered target (A ≥ 1, e.g. the interior of a translated object) takes the weighted mean of what
     arrived, so a uniform object stays uniform and σ stays in [0, 1] (the official code instead adds
     the per-arrival updates, which is unbounded for many arrivals). s_base is the copy after clearing.
   - ``"nearest"`` (official default): the voxel containing x receives the mean of its arrivals (β = 1).
   Neighbours outside the grid are dropped (their share is lost; the official code clamps them onto the border).

Everything is vectorised over all boxes and frames at once (one ``unique`` and a few ``index_add``), and
differentiable with respect to σ and logits: gradients flow from the warped copies to the original volume
(selection itself, an argmax, is not differentiable).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import numpy as np
import torch

from ..choices import FLOW_MOVERS
from ..occ3d import GRID, Grid

Mover = str  # one of MOVERS
MOVERS = FLOW_MOVERS
SNAP_DISTANCE = 1e-4  # metres: an IDW target this close to a voxel centre goes wholly to that centre

# Offsets of the 8 neighbouring voxel centres around a point, relative to the floor corner.
_CORNERS = torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], dtype=torch.long)


def _tensor(x, dtype) -> torch.Tensor:
    """numpy array, list or tensor → tensor of ``dtype`` (a tensor keeps its device)."""
    return x.to(dtype) if torch.is_tensor(x) else torch.as_tensor(np.asarray(x), dtype=dtype)


@dataclass
class PackedMoves:
    """All box moves of a batch, concatenated (build with ``PackedMoves.from_arrays``).

    voxels long [M, 3] (voxel indices), box long [M] (row of each voxel's move), transforms float [K, 4, 4]
    (ego→ego of the current keyframe), classes long [K], volume long [K] (which output volume each move writes).
    """

    voxels: torch.Tensor
    box: torch.Tensor
    transforms: torch.Tensor
    classes: torch.Tensor
    volume: torch.Tensor

    @staticmethod
    def from_arrays(voxels, box, transforms, classes, volume) -> "PackedMoves":
        """From numpy arrays or tensors (e.g. the dict of ``occflownet.data.flow.flow_moves``); validates shapes."""
        moves = PackedMoves(_tensor(voxels, torch.long).reshape(-1, 3), _tensor(box, torch.long).reshape(-1),
                            _tensor(transforms, torch.float64).reshape(-1, 4, 4),
                            _tensor(classes, torch.long).reshape(-1), _tensor(volume, torch.long).reshape(-1))
        moves.validate()
        return moves

    def validate(self) -> None:
        k = self.transforms.shape[0]
        if self.classes.shape != (k,) or self.volume.shape != (k,):
            raise ValueError(f"PackedMoves: classes {tuple(self.classes.shape)} and volume "
                             f"{tuple(self.volume.shape)} must both be [{k}] (one per transform)")
        if self.box.shape[0] != self.voxels.shape[0]:
            raise ValueError(f"PackedMoves: box has {self.box.shape[0]} rows, voxels {self.voxels.shape[0]}")
        if self.box.numel() and (int(self.box.min()) < 0 or int(self.box.max()) >= k):
            raise ValueError(f"PackedMoves: box indices must lie in [0, {k})")

    @property
    def num_moves(self) -> int:
        return int(self.transforms.shape[0])

    def to(self, device) -> "PackedMoves":
        return PackedMoves(*(t.to(device) for t in (self.voxels, self.box, self.transforms, self.classes,
                                                     self.volume)))

    @staticmethod
    def concat(parts: Sequence["PackedMoves"], volume_offsets: Sequence[int]) -> "PackedMoves":
        """Join per-sample moves; part p's volume indices are shifted by ``volume_offsets[p]``."""
        if len(parts) != len(volume_offsets):
            raise ValueError("PackedMoves.concat: one volume offset per part")
        if not parts:
            return PackedMoves.from_arrays(*(np.zeros(shape) for shape in ((0, 3), 0, (0, 4, 4), 0, 0)))
        box_offsets = np.cumsum([0] + [p.num_moves for p in parts[:-1]])
        return PackedMoves(torch.cat([p.voxels for p in parts]),
                           torch.cat([p.box + int(o) for p, o in zip(parts, box_offsets)]),
                           torch.cat([p.transforms for p in parts]),
                           torch.cat([p.classes for p in parts]),
                           torch.cat([p.volume + int(o) for p, o in zip(parts, volume_offsets)]))


def idw_neighbours(points: torch.Tensor, grid: Grid = GRID) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse-distance weights of the 8 voxel centres around each point.

    points float [P, 3] (ego frame, metres) → (indices long [P, 8, 3] (may lie outside the grid),
    weights [P, 8] (same dtype as points), non-negative, each row summing to 1). A point within SNAP_DISTANCE of
    a centre gives weight 1 to that centre.
    """
    lower = torch.tensor(grid.lower, dtype=points.dtype, device=points.device)
    vs = float(grid.voxel_size)
    base = torch.floor((points - lower) / vs - 0.5).long()  # index of the centre just below, per axis
    idx = base[:, None, :] + _CORNERS.to(points.device)[None]  # [P, 8, 3]
    centres = lower + (idx.to(points.dtype) + 0.5) * vs
    dist = torch.linalg.vector_norm(points[:, None, :] - centres, dim=-1)  # [P, 8]
    snap = dist < SNAP_DISTANCE
    weights = torch.where(snap.any(-1, keepdim=True), snap.to(points.dtype),
                          1.0 / dist.clamp_min(SNAP_DISTANCE))
    # Two snapped centres are impossible (centres are 0.4 m apart), so rows stay normalisable either way.
    return idx, weights / weights.sum(-1, keepdim=True)


def selected_sources(logits: torch.Tensor, source: torch.Tensor, moves: PackedMoves, grid: Grid = GRID):
    """Rows of ``moves.voxels`` that move (logits [B, V, C], detached): the predicted class (argmax, evaluated at
    the listed voxels only) equals the box class; a voxel selected by several boxes of one volume keeps one."""
    X, Y, Z = grid.shape
    vox, box = moves.voxels, moves.box
    vol = moves.volume[box]  # [M] output volume of each voxel
    flat = (vox[:, 0] * Y + vox[:, 1]) * Z + vox[:, 2]
    keep = logits[source[vol], flat].argmax(-1) == moves.classes[box]
    rows = torch.nonzero(keep).squeeze(1)
    if rows.numel() == 0:
        return rows
    # One box per (volume, voxel): the box whose voxel centroid is nearest (ties: the earlier move).
    key = vol[rows] * (X * Y * Z) + flat[rows]
    if torch.unique(key).numel() == key.numel():
        return rows
    pos = vox.to(torch.float64)
    centroid = torch.zeros(moves.num_moves, 3, dtype=torch.float64, device=vox.device).index_add_(0, box, pos)
    centroid /= torch.bincount(box, minlength=moves.num_moves).clamp_min(1)[:, None].to(torch.float64)
    d2 = ((pos[rows] - centroid[box[rows]]) ** 2).sum(-1)
    order = torch.argsort(box[rows], stable=True)  # sort by (key, d2, box): last sort key first
    order = order[torch.argsort(d2[order], stable=True)]
    order = order[torch.argsort(key[order], stable=True)]
    sorted_key = key[order]
    first = torch.ones_like(sorted_key, dtype=torch.bool)
    first[1:] = sorted_key[1:] != sorted_key[:-1]
    return rows[order[first]].sort().values


def warp_volumes(density: torch.Tensor, logits: torch.Tensor, source: torch.Tensor, moves: PackedMoves,
                 mover: Mover = "idw", grid: Grid = GRID) -> tuple[torch.Tensor, torch.Tensor]:
    """Warped copies of B predicted volumes, one per output volume (sample × frame).

    density [B, X, Y, Z] (σ in [0, 1]); logits [B, X, Y, Z, C]; source long [N]: the sample each output volume
    copies (e.g. ``arange(B).repeat_interleave(T)`` for T frames per sample); moves: PackedMoves whose
    ``volume`` indexes the N outputs. Returns (density [N, X, Y, Z], logits [N, X, Y, Z, C]), all in the ego
    frame of each sample's current keyframe; an output volume with no moves is a plain copy. This is the stacked
    volume the renderer takes together with a per-ray volume index.
    """
    source, moves = _checked_warp_inputs(density, logits, source, moves, mover, grid)
    B, X, Y, Z = density.shape
    C, V, N = logits.shape[-1], X * Y * Z, source.numel()
    flat_d, flat_l = density.reshape(B, V), logits.reshape(B, V, C)
    # Fresh copies [N, V] and [N, V, C] (not views), edited by ONE in-place index_put_ each at the end: the
    # backward then costs one full-size pass per tensor. Moved and background values are read from the
    # originals, so their gradients go straight to the B input volumes.
    out_d = torch.index_select(flat_d, 0, source)
    out_l = torch.index_select(flat_l, 0, source)
    if moves.voxels.shape[0] == 0:
        return out_d.reshape(N, X, Y, Z), out_l.reshape(N, X, Y, Z, C)
    with torch.no_grad():
        rows = selected_sources(flat_l.detach(), source, moves, grid)
    if rows.numel() == 0:
        return out_d.reshape(N, X, Y, Z), out_l.reshape(N, X, Y, Z, C)
    with torch.no_grad():
        plan = _warp_plan(rows, source, moves, mover, grid)
    out_d.index_put_((plan.write_n, plan.write_v), _moved_values(flat_d, 0, plan))
    out_l.index_put_((plan.write_n, plan.write_v), _moved_values(flat_l, C, plan))
    return out_d.reshape(N, X, Y, Z), out_l.reshape(N, X, Y, Z, C)


def _checked_warp_inputs(density, logits, source, moves: PackedMoves, mover, grid: Grid):
    """Validate ``warp_volumes``' inputs; returns (source long [N] on density's device, moves on that device)."""
    if mover not in MOVERS:
        raise ValueError(f"mover must be one of {MOVERS}, got {mover!r}")
    if density.ndim != 4 or tuple(density.shape[1:]) != tuple(grid.shape):
        raise ValueError(f"density must be [B, {', '.join(map(str, grid.shape))}], got {tuple(density.shape)}")
    if logits.ndim != 5 or logits.shape[:4] != density.shape:
        raise ValueError(f"logits must be [B, X, Y, Z, C] matching density, got {tuple(logits.shape)}")
    B = density.shape[0]
    device = density.device
    source = torch.as_tensor(source, dtype=torch.long, device=device).reshape(-1)
    if source.numel() and (int(source.min()) < 0 or int(source.max()) >= B):
        raise ValueError(f"source indices must lie in [0, {B})")
    N = source.numel()
    moves.validate()
    moves = moves.to(device)
    if moves.num_moves and (int(moves.volume.min()) < 0 or int(moves.volume.max()) >= N):
        raise ValueError(f"moves.volume must lie in [0, {N}) (the number of output volumes)")
    vox = moves.voxels
    if vox.numel() and ((vox < 0).any() or (vox >= torch.tensor(grid.shape, device=device)).any()):
        raise ValueError("moves.voxels must be voxel indices inside the grid")
    return source, moves


class _WarpPlan(NamedTuple):
    """Where the moved voxels go (all index work, no gradients). S moved sources, U targets; keys index [N·V].

    read_b, read_v [S + U]: input volume and voxel to read (the sources, then the targets' backgrounds);
    arrival [A]: source row of each (source, neighbour) arrival, inverse [A]: its target; share [A]: its weight
    normalised by the target's coverage; beta [U] = min(coverage, 1); keep_base [U]: background weight (0 where
    the target is itself a moved source); write_n, write_v [U + K]: output volume and voxel of the targets, then of
    the K vacated sources that nothing refills (written as zeros)."""

    read_b: torch.Tensor
    read_v: torch.Tensor
    arrival: torch.Tensor
    inverse: torch.Tensor
    share: torch.Tensor
    beta: torch.Tensor
    keep_base: torch.Tensor
    write_n: torch.Tensor
    write_v: torch.Tensor
    num_sources: int
    num_targets: int
    num_cleared: int


def _warp_plan(rows: torch.Tensor, source: torch.Tensor, moves: PackedMoves, mover, grid: Grid) -> _WarpPlan:
    """Targets and weights of the selected source voxels ``rows`` (``selected_sources``) under ``mover``."""
    X, Y, Z = grid.shape
    V = X * Y * Z
    device = source.device
    box = moves.box[rows]
    vol = moves.volume[box]  # [S] output volume of each moved voxel
    src_vox = moves.voxels[rows]
    src_key = vol * V + (src_vox[:, 0] * Y + src_vox[:, 1]) * Z + src_vox[:, 2]  # [S], unique, into [N*V]
    lower = torch.tensor(grid.lower, dtype=torch.float64, device=device)
    centres = lower + (src_vox.to(torch.float64) + 0.5) * grid.voxel_size
    T = moves.transforms[box]
    moved = (T[:, :3, :3] @ centres[:, :, None])[:, :, 0] + T[:, :3, 3]  # [S, 3] ego frame
    if mover == "nearest":
        tgt = grid.index_of(moved)[:, None, :]  # [S, 1, 3]
        weight = torch.ones(tgt.shape[:2], dtype=torch.float64, device=device)
    else:
        tgt, weight = idw_neighbours(moved, grid)  # [S, 8, 3], [S, 8]
    shape = torch.tensor(grid.shape, device=device)
    valid = ((tgt >= 0) & (tgt < shape)).all(-1) & (weight > 0)  # [S, P]
    arrival, corner = torch.nonzero(valid, as_tuple=True)  # entries: source row, neighbour
    t_vox = tgt[arrival, corner]
    tgt_key = vol[arrival] * V + (t_vox[:, 0] * Y + t_vox[:, 1]) * Z + t_vox[:, 2]
    alpha = weight[arrival, corner]
    targets, inverse = torch.unique(tgt_key, return_inverse=True)  # [U] keys into [N*V]
    coverage = torch.zeros(targets.numel(), dtype=torch.float64, device=device).index_add_(0, inverse, alpha)
    beta = coverage.clamp(max=1.0)
    share = alpha / coverage[inverse]  # normalised weight of each arrival
    # background at a target: the copy after clearing → 0 where the target is itself a moved source
    keep_base = (~torch.isin(targets, src_key)).to(torch.float64) * (1.0 - beta)
    cleared = src_key[~torch.isin(src_key, targets)]  # vacated and not refilled → plain zeros
    # rows of the B inputs to read: the moved sources, then the targets' backgrounds
    read_key = torch.cat([src_key, targets])
    read_n = read_key // V
    read_b, read_v = source[read_n], read_key % V
    write_key = torch.cat([targets, cleared])
    write_n, write_v = write_key // V, write_key % V
    return _WarpPlan(read_b, read_v, arrival, inverse, share, beta, keep_base, write_n, write_v, src_key.numel(),
                     targets.numel(), cleared.numel())


def _moved_values(flat: torch.Tensor, channels: int, plan: _WarpPlan) -> torch.Tensor:
    """New values at the targets: β · (weighted mean of arrivals) + (1 − β) · background (per channel), then zeros
    for the vacated voxels; ``flat`` [B, V] (channels 0) or [B, V, C]."""
    S, U, device = plan.num_sources, plan.num_targets, flat.device
    read = flat[plan.read_b, plan.read_v]  # [S + U] or [S + U, C]
    src, base = read[:S], read[S:]
    w = plan.share.to(flat.dtype)
    if channels:
        w, bg = w[:, None], plan.keep_base.to(flat.dtype)[:, None]
        scaled = torch.zeros(U, channels, dtype=flat.dtype, device=device)
    else:
        bg = plan.keep_base.to(flat.dtype)
        scaled = torch.zeros(U, dtype=flat.dtype, device=device)
    mean = scaled.index_add(0, plan.inverse, w * src[plan.arrival])
    b = plan.beta.to(flat.dtype)[:, None] if channels else plan.beta.to(flat.dtype)
    new = b * mean + bg * base
    zeros = torch.zeros((plan.num_cleared,) + new.shape[1:], dtype=flat.dtype, device=device)
    return torch.cat([new, zeros])
