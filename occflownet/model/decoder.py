"""3D decoder: a residual Conv3d trunk on the (possibly coarsened) grid and the per-voxel MLP heads Φσ, Φs.

forward(trunk grid [B, Xc, Yc, Zc, C], fine points (rows int64 [N], features [N, head_channels]) or None)
→ (density logits [B, Xc, Yc, Zc, s³], semantic logits [B, Xc, Yc, Zc, s³, 17]) in *block layout*;
:func:`unblock` turns block layout into the grid's [B, X, Y, Z, ...] layout (X = Xc·s, ...).

With stride s > 1 the trunk output is upsampled by a learned depth-to-space projection (one linear map per
sub-voxel, i.e. a transposed Conv3d with kernel = stride = s); the full-resolution lifted features (skip) are
added straight into that upsampled grid (pooling then projecting equals projecting then pooling, so the depth
head predicts the skip features in head width and no dense intermediate grid is built); the heads then run on
every full-resolution voxel. With s = 1 the heads run on the trunk output.

Inference (:meth:`VoxelDecoder.fused_occupancy`, the exported path) computes the same map in the order a CPU runs
fastest: the trunk's 3x3x3 convolutions as three 2-D convolutions over the z-shifted grid (:func:`conv_z`), and
the per-voxel chain (projection, skip features, ReLU, Φσ) over slabs of the grid whose intermediates fit in the
cache (:func:`slab_width`), Φs only on the voxels with σ ≥ τ.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from occflownet.occ3d import FREE, NUM_CLASSES

# Initial bias of Φσ's output: σ starts near sigmoid(-2.2) ≈ 0.1 (most of space is free), so freshly initialised
# models render rays that travel into the scene instead of stopping in the first voxels.
SIGMA_PRIOR_LOGIT = -2.2
# Bytes of one slab's widest per-voxel tensor in the inference chain (:meth:`VoxelDecoder.fused_occupancy`): the
# projection, Φσ and their intermediates run on slabs of whole x-planes whose widest layer takes at most this many
# bytes, near a core's L2 cache (tiny: 5 planes of 12,800 voxels, Φσ's hidden layer 16 wide; base: 2 planes of
# 6,400 voxels, 64 wide),
# instead of 640,000-row tensors written to memory and read back between layers (docs/results.md#inference).
SLAB_BYTES = 4 * 1024 * 1024


class ResBlock3d(nn.Module):
    """conv3x3x3-BN-ReLU-conv3x3x3-BN + identity, ReLU. [B, C, X, Y, Z] → same."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv3d(channels, channels, kernel_size=3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm3d(channels)
        self.conv2 = nn.Conv3d(channels, channels, kernel_size=3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm3d(channels)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        return self.relu(self.bn2(self.conv2(out)) + x)


def z_slices(conv: nn.Conv3d, bn: nn.BatchNorm3d) -> tuple[list[torch.Tensor], torch.Tensor]:
    """A bias-free Conv3d (kernel k³, padding k // 2) followed by an eval-mode BatchNorm3d → (k weights
    [O, C, k, k], one per z offset dz = 0 .. k − 1, bias [O]), the BatchNorm folded in (scale into the weights,
    shift into the bias): the Conv3d is the sum over dz of Conv2d(weight[dz]) on the input heights z + dz − k // 2
    (:func:`conv_z`)."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)                         # [O]
    w = conv.weight * scale[:, None, None, None, None]                               # [O, C, k, k, k]
    return [w[..., dz] for dz in range(w.shape[-1])], bn.bias - bn.running_mean * scale


def conv_z(x: torch.Tensor, weights: list[torch.Tensor], bias: torch.Tensor) -> torch.Tensor:
    """A Conv3d on z-major grids: x [B, Z, C, X, Y] → [B, Z, O, X, Y], out[z] = bias + sum over dz of
    conv2d(x[z + dz − r], weights[dz]) (r = len(weights) // 2, zero outside 0 .. Z − 1; 2-D padding k // 2).
    Each 2-D convolution runs on the B·Z planes as a batch — the same FLOPs as the Conv3d, in the runtimes' fast
    2-D kernels, which onnxruntime runs faster than its Conv3d (docs/results.md#inference)."""
    b, z, c, h, w = x.shape
    r = len(weights) // 2
    out = None
    for dz, weight in enumerate(weights):
        shift = dz - r                                   # this term reads input height z + shift
        src = x
        if shift:
            pad = torch.zeros_like(x[:, :abs(shift)])
            src = torch.cat([x[:, shift:], pad], 1) if shift > 0 else torch.cat([pad, x[:, :shift]], 1)
        y = F.conv2d(src.reshape(b * z, c, h, w), weight, bias if shift == 0 else None,
                     padding=weight.shape[-1] // 2)
        out = y if out is None else out + y
    return out.reshape(b, z, -1, h, w)


def slab_width(planes: int, voxels_per_plane: int, widest: int) -> int:
    """x-planes per slab of the inference chain: as many as keep a slab's widest per-voxel tensor (``widest``
    float32 channels) within SLAB_BYTES, at least 1, at most ``planes``."""
    return max(1, min(planes, SLAB_BYTES // (4 * widest * voxels_per_plane)))


# Row blocks of RowLinear's weight gradient: the sum over N rows as one batched product of this many blocks.
WEIGHT_GRAD_BLOCKS = 64


class RowLinear(torch.autograd.Function):
    """``apply(x [N, in], weight [out, in], bias [out])`` = F.linear, with a backward for narrow layers over many
    rows (the per-voxel heads: N up to 640,000 per sample, in/out 8–64): the weight gradient as one batched product
    over WEIGHT_GRAD_BLOCKS row blocks summed, instead of one product whose inner dimension is all N rows, and the
    input gradient of a one-output layer as a broadcast product instead of an outer product through mm. Same
    gradients up to the order of summation; on this CPU (2 threads) Φσ's forward and backward over 640,000 rows took
    79–81 ms against 91–101 ms (docs/results.md#training-speed)."""

    @staticmethod
    def forward(ctx, x, weight, bias):
        ctx.save_for_backward(x, weight)
        return F.linear(x, weight, bias)

    @staticmethod
    def backward(ctx, grad):
        x, weight = ctx.saved_tensors
        grad_x = grad * weight if weight.shape[0] == 1 else grad @ weight          # [N, in]
        n = x.shape[0] - x.shape[0] % WEIGHT_GRAD_BLOCKS
        blocks = (WEIGHT_GRAD_BLOCKS, -1)
        grad_w = torch.bmm(grad[:n].reshape(*blocks, grad.shape[1]).transpose(1, 2),
                           x[:n].reshape(*blocks, x.shape[1])).sum(0)                # [out, in]
        if n < x.shape[0]:
            grad_w = grad_w + grad[n:].T @ x[n:]
        return grad_x, grad_w, grad.sum(0)


class FineRows(torch.autograd.Function):
    """``apply(x [M, in], weight [s³·C, in], bias [s³·C], rows int64 [K], values [K, C], C)`` =
    ``relu(index_add(linear(x, weight, bias).reshape(M·s³, C), 0, rows, values))``: the head input of every voxel
    while training, in one buffer. Autograd's in-place ops on the reshaped view made its backward copy the
    whole buffer twice (``CopySlices``: a clone of [M·s³, C] and a copy of [M, s³·C]); here the backward is
    the ops autograd runs for the out-of-place form (ReLU's mask on the output, ``index_select`` for the values,
    ``mm`` and ``sum`` for the layer), so values and gradients are those of the out-of-place ops up to the order
    a CPU's kernels sum in (bitwise on most CPUs; 4e-6 on gradients of ~30 on an AVX-512 AMD one; tested)."""

    @staticmethod
    def forward(ctx, x, weight, bias, rows, values, channels):
        y = torch.addmm(bias, x, weight.t()).view(-1, channels)                    # [M·s³, C]
        y.index_add_(0, rows, values).relu_()
        ctx.save_for_backward(x, weight, y, rows)
        return y

    @staticmethod
    def backward(ctx, grad):
        x, weight, y, rows = ctx.saved_tensors
        grad = torch.ops.aten.threshold_backward(grad, y, 0)                        # [M·s³, C]
        grad_values = grad.index_select(0, rows) if ctx.needs_input_grad[4] else None
        grad_up = grad.view(x.shape[0], -1)                                          # [M, s³·C]
        return grad_up.mm(weight), grad_up.t().mm(x), grad_up.sum(0), None, grad_values, None


class VoxelMLP(nn.Sequential):
    """Per-voxel MLP over the last dimension of [N, C] rows: Linear-ReLU per hidden layer, then a Linear output
    layer (an ``nn.Sequential``: the same parameters and state-dict keys). In training, without autocast, the
    Linear layers run as :class:`RowLinear` (a faster backward over many rows); in eval (and export) as the
    modules themselves."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or x.dim() != 2 or torch.is_autocast_enabled(x.device.type):
            return super().forward(x)
        for layer in self:
            x = RowLinear.apply(x, layer.weight, layer.bias) if isinstance(layer, nn.Linear) else layer(x)
        return x


def mlp(in_channels: int, hidden: tuple[int, ...], out_channels: int) -> VoxelMLP:
    """Per-voxel MLP over the last dimension: Linear-ReLU per hidden layer, then a Linear output layer."""
    layers, c = [], in_channels
    for n in hidden:
        layers += [nn.Linear(c, n), nn.ReLU(inplace=True)]
        c = n
    layers.append(nn.Linear(c, out_channels))
    return VoxelMLP(*layers)


def unblock(x: torch.Tensor, stride: int) -> torch.Tensor:
    """Block layout [B, Xc, Yc, Zc, s³, *rest] → grid layout [B, Xc·s, Yc·s, Zc·s, *rest]."""
    b, xc, yc, zc = x.shape[:4]
    rest = tuple(x.shape[5:])
    s = stride
    x = x.reshape((b, xc, yc, zc, s, s, s) + rest)
    x = x.permute((0, 1, 4, 2, 5, 3, 6) + tuple(range(7, 7 + len(rest))))
    return x.reshape((b, xc * s, yc * s, zc * s) + rest)


def block_rows(grid_rows: torch.Tensor, grid_shape: tuple[int, int, int], stride: int) -> torch.Tensor:
    """Rows int64 [K] of the flattened grid layout [B·X·Y·Z] (row = ((b·X + x)·Y + y)·Z + z) → the same voxels' rows
    of the flattened block layout [B·Xc·Yc·Zc·s³] (:func:`unblock`'s input, sub-voxel (sx, sy, sz) last)."""
    x_n, y_n, z_n = grid_shape
    s = stride
    # integer floor divisions (ONNX Div on int64); the exporter's float form of rounding_mode="floor" is rounded
    # by the fp16 variant
    z = torch.remainder(grid_rows, z_n)
    y = torch.remainder(grid_rows // z_n, y_n)
    x = torch.remainder(grid_rows // (z_n * y_n), x_n)
    b = grid_rows // (x_n * y_n * z_n)
    coarse = ((b * (x_n // s) + x // s) * (y_n // s) + y // s) * (z_n // s) + z // s
    return ((coarse * s + x % s) * s + y % s) * s + z % s


class VoxelDecoder(nn.Module):
    """Residual 3D trunk at stride ``stride`` + depth-to-space upsampling + per-voxel heads Φσ, Φs."""

    def __init__(self, in_channels: int, stride: int, channels: int, blocks: int,
                 head_channels: int, sigma_hidden: tuple[int, ...], semantic_hidden: tuple[int, ...],
                 head_init: str = "prior"):
        super().__init__()
        self.stride = stride
        self.stem = nn.Sequential(nn.Conv3d(in_channels, channels, kernel_size=1, bias=False),
                                  nn.BatchNorm3d(channels), nn.ReLU(inplace=True))
        self.blocks = nn.Sequential(*[ResBlock3d(channels) for _ in range(blocks)])
        if stride > 1:
            self.up = nn.Linear(channels, stride ** 3 * head_channels)
            head_in = head_channels
        else:
            self.up = None
            head_in = channels
        self.head_channels = head_in
        self.widest = max(head_in, *sigma_hidden)         # the widest per-voxel tensor of the density chain
        self.sigma_head = mlp(head_in, sigma_hidden, 1)
        self.semantic_head = mlp(head_in, semantic_hidden, NUM_CLASSES)
        if head_init == "official":  # the official decoder: Xavier-uniform weights and zero biases in both heads
            for layer in [m for m in (*self.sigma_head, *self.semantic_head) if isinstance(m, nn.Linear)]:
                nn.init.xavier_uniform_(layer.weight)
                nn.init.zeros_(layer.bias)
        else:  # "prior": torch's default init, Φσ's output bias SIGMA_PRIOR_LOGIT
            nn.init.constant_(self.sigma_head[-1].bias, SIGMA_PRIOR_LOGIT)

    def trunk_rows(self, trunk: torch.Tensor) -> torch.Tensor:
        """Trunk grid [B, Xc, Yc, Zc, C] → stem and residual blocks → [M, Ct] (M = B·Xc·Yc·Zc, rows in
        (b, xc, yc, zc) order). Training runs the Conv3d modules; eval mode the same map on the z-major grid, each
        3x3x3 convolution as three 2-D ones (:func:`conv_z`, BatchNorm folded in, :func:`z_slices`)."""
        b, xc, yc, zc, _ = trunk.shape
        if self.training:
            x = self.blocks(self.stem(trunk.permute(0, 4, 1, 2, 3)))              # [B, Ct, Xc, Yc, Zc]
            return x.permute(0, 2, 3, 4, 1).reshape(-1, x.shape[1])
        x = trunk.permute(0, 3, 4, 1, 2)                                           # [B, Zc, C, Xc, Yc]
        x = torch.relu(conv_z(x, *z_slices(self.stem[0], self.stem[1])))
        for block in self.blocks:
            out = torch.relu(conv_z(x, *z_slices(block.conv1, block.bn1)))
            x = torch.relu(conv_z(out, *z_slices(block.conv2, block.bn2)) + x)
        return x.permute(0, 3, 4, 1, 2).reshape(-1, x.shape[2])                    # [M, Ct]

    def voxel_features(self, trunk: torch.Tensor, fine_points: tuple[torch.Tensor, torch.Tensor] | None):
        """Head input features [B·Xc·Yc·Zc·s³, head_channels], rows in block layout order."""
        x = self.trunk_rows(trunk)                                                 # [M, Ct], M = B·Xc·Yc·Zc
        # the per-voxel layers run on 2-D [rows, channels] tensors: onnxruntime then fuses bias and ReLU (Gemm)
        if self.up is None:
            return x
        if self.training and fine_points is not None and not torch.is_autocast_enabled(x.device.type):
            # one buffer for all M·s³ rows, no copies (FineRows); eval and export keep the out-of-place ops below,
            # which the exported graph was checked with
            return FineRows.apply(x, self.up.weight, self.up.bias, fine_points[0], fine_points[1].float(),
                                  self.head_channels)
        x = self.up(x).reshape(-1, self.head_channels)                             # [M·s³, Ch]
        if fine_points is not None:      # summed in float32 (under bf16 autocast the upsampling gives bf16)
            x = torch.index_add(x.float(), 0, fine_points[0], fine_points[1].float())
        return torch.relu(x)

    def forward(self, trunk: torch.Tensor, fine_points: tuple[torch.Tensor, torch.Tensor] | None,
                density_rows: torch.Tensor | None = None, logit_rows: torch.Tensor | None = None):
        """→ (density logits, semantic logits) in block layout: [B, Xc, Yc, Zc, s³] and [B, Xc, Yc, Zc, s³, 17]
        over every voxel, or [K] / [K, 17] at ``density_rows`` / ``logit_rows`` (int64 [K], rows of the flattened
        block layout, :func:`block_rows`) when given: a head then runs on those voxels only."""
        b, xc, yc, zc, _ = trunk.shape
        s3 = self.stride ** 3
        x = self.voxel_features(trunk, fine_points)
        at_density = None if density_rows is None else torch.index_select(x, 0, density_rows)
        if density_rows is None:
            sigma = self.sigma_head(x).reshape(b, xc, yc, zc, s3)
        else:
            sigma = self.sigma_head(at_density).reshape(-1)
        if logit_rows is None:
            semantic = self.semantic_head(x).reshape(b, xc, yc, zc, s3, NUM_CLASSES)
        else:       # one gather when both heads run on the same rows (the rays' footprint)
            semantic = self.semantic_head(at_density if logit_rows is density_rows
                                          else torch.index_select(x, 0, logit_rows))
        return sigma, semantic

    def head_input(self, rows: torch.Tensor, skip: tuple[torch.Tensor, torch.Tensor] | None) -> torch.Tensor:
        """Eval: trunk rows [m, Ct] and, with skip features, ``skip`` = (rows int64 [k] of the m·s³ voxels, block
        layout, unique; their summed skip features [k, Ch]) → the heads' input [m·s³, Ch]: relu(projection +
        skip), the skip features added to the k rows they belong to (the order of the training path's
        ``index_add``); the trunk rows themselves when s = 1."""
        if self.up is None:
            return rows
        y = self.up(rows).reshape(-1, self.head_channels)                          # [m·s³, Ch]
        if skip is not None:
            y = torch.index_put(y, (skip[0],), torch.index_select(y, 0, skip[0]) + skip[1])
        return torch.relu(y)

    def density_logits(self, x: torch.Tensor) -> torch.Tensor:
        """Φσ on head inputs [N, Ch] → logits [N]; its one-output layer as the product of its weight row with the
        hidden layer's transpose ([1, H] × [H, N], ONNX Gemm with transB): onnxruntime runs Φσ on 64,000 rows so in
        0.83 ms against 0.99 ms as [N, H] × [H, 1] (docs/results.md#inference)."""
        *hidden, out = self.sigma_head
        for layer in hidden:
            x = layer(x)
        return torch.addmm(out.bias, out.weight, x.t()).reshape(-1)

    def fused_occupancy(self, trunk: torch.Tensor, fine_points, threshold: float):
        """Inference: (occupancy uint8, density float32) [B, X, Y, Z] (grid layout), from the trunk grid
        [B, Xc, Yc, Zc, C] and the pooled skip features (unique block-layout rows int64 [U], sums [U, Ch], as
        :class:`~occflownet.model.lift.LiftSplat` gives them in eval mode) or None.

        Equals fusing :meth:`forward`'s outputs (argmax where σ ≥ τ else free). The whole per-voxel chain —
        projection, skip features, ReLU, Φσ, sigmoid, and Φs on the slab's voxels with σ ≥ τ — runs slab by slab
        (:func:`slab_width` x-planes of every sample, static shapes), in block layout, so its 640,000-row
        intermediates are never written out whole and no voxel index changes layout: a slab reads its skip
        features as the rows of its planes (:class:`SlabRows`), picks its occupied rows where its σ
        lies (``torch.nonzero``, exported as Compress; Gather; Φs; ScatterND of unique rows, no reduction), and
        turns σ and its classes into grid layout once, as a transpose of the slab."""
        b, xc, yc, zc, _ = trunk.shape
        s = self.stride
        per = yc * zc * s ** 3                                                     # voxels per x-plane and sample
        rows = self.trunk_rows(trunk).reshape(b, xc, yc * zc, -1)                  # [B, Xc, Yc·Zc, Ct]
        width = slab_width(xc, per, self.widest)
        skip = None if fine_points is None or self.up is None else SlabRows(*fine_points, xc, per, width)
        density, occupancy = [], []
        for x0 in range(0, xc, width):
            n = min(width, xc - x0)
            picked = None if skip is None else skip.within(x0)
            x = self.head_input(rows[:, x0:x0 + n].reshape(-1, rows.shape[-1]), picked)   # [B·n·per, Ch]
            sigma = torch.sigmoid(self.density_logits(x))                         # [B·n·per], block layout
            occupied = torch.nonzero(sigma >= threshold).reshape(-1)               # rows of this slab
            labels = torch.argmax(self.semantic_head(torch.index_select(x, 0, occupied)), dim=-1)
            classes = torch.full_like(sigma, FREE, dtype=torch.uint8).index_put((occupied,), labels.to(torch.uint8))
            density.append(unblock(sigma.reshape(b, n, yc, zc, s ** 3), s))        # [B, n·s, Y, Z]
            occupancy.append(unblock(classes.reshape(b, n, yc, zc, s ** 3), s))
        # occupancy's Concat last in the graph: onnxruntime orders a graph by a depth-first walk back from its last
        # output node, so each slab's Φs then runs right after its σ, while the slab's head input is still in the
        # cache (density's Concat last ran every slab's σ first, then every slab's Φs: 1.06x slower on tiny)
        density = torch.cat(density, 1)
        return torch.cat(occupancy, 1), density


class SlabRows:
    """Rows int64 [U] of a flattened block-layout grid [B·Xc·per] (``per`` voxels per x-plane and sample;
    unique, any order) and their values [U, ...], split by the slabs of ``width`` x-planes that
    :meth:`VoxelDecoder.fused_occupancy` runs: :meth:`within` gives the rows of slab x0 .. x0 + n − 1 (n = width,
    or fewer for the last) as rows of that slab's own flattened grid [B·n·per], with their values. Each row's
    slab and slab row are computed once, for all rows."""

    def __init__(self, rows: torch.Tensor, values: torch.Tensor, planes: int, per: int, width: int):
        self.values, self.width = values, width
        plane = rows // per                                                        # b·Xc + x
        b = plane // planes
        x = plane - b * planes
        self.slab = x // width
        x0 = self.slab * width
        n = torch.clamp(planes - x0, max=width)                                    # planes of the row's slab
        self.local = (b * n + x - x0) * per + (rows - plane * per)                 # row of the slab's grid

    def within(self, x0: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(rows int64 [k] of the grid of the slab starting at plane ``x0``, values [k, ...] of those rows)."""
        keep = torch.nonzero(self.slab == x0 // self.width).reshape(-1)
        return torch.index_select(self.local, 0, keep), torch.index_select(self.values, 0, keep)
