"""3D decoder: a residual Conv3d trunk on the (possibly coarsened) grid and the per-voxel MLP heads Φσ, Φs.

forward(trunk grid [B, Xc, Yc, Zc, C], fine points (rows int64 [N], features [N, head_channels]) or None)
→ (density logits [B, Xc, Yc, Zc, s³], semantic logits [B, Xc, Yc, Zc, s³, 17]) in *block layout*;
:func:`unblock` turns block layout into the grid's [B, X, Y, Z, ...] layout (X = Xc·s, ...).

With stride s > 1 the trunk output is upsampled by a learned depth-to-space projection (one linear map per
sub-voxel, i.e. a transposed Conv3d with kernel = stride = s); the full-resolution lifted features (skip) are
scatter-added straight into that upsampled grid (pooling then projecting equals projecting then pooling, so the
depth head predicts the skip features in head width and no dense intermediate grid is built); the heads then run
on every full-resolution voxel. With s = 1 the heads run on the trunk output.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from occflownet.occ3d import FREE, NUM_CLASSES

# Initial bias of Φσ's output: σ starts near sigmoid(-2.2) ≈ 0.1 (most of space is free), so freshly initialised
# models render rays that travel into the scene instead of stopping in the first voxels.
SIGMA_PRIOR_LOGIT = -2.2
# In eval mode a trunk at most this many voxels high runs as 2-D convolutions with z folded into the channels
# (:func:`fold_conv`): the same map, computed by the runtimes' fast 2-D kernels. onnxruntime 1.32 on this CPU runs
# tiny's 3x3x3 Conv on [1, 32, 50, 50, 4] 2.6x slower than the folded Conv2d on [1, 128, 50, 50] (4/3 of the
# FLOPs); at base's height 8 (8/3 of the FLOPs) the two cost the same, so base keeps Conv3d (docs/results.md#inference).
FOLD_Z_MAX = 4


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


def fold_conv(conv: nn.Conv3d, bn: nn.BatchNorm3d, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A bias-free Conv3d (kernel k³, padding k // 2) followed by an eval-mode BatchNorm3d, on [B, C, X, Y, Z] with
    Z = ``height``, as one Conv2d on [B, Z·C, X, Y] (channel z·C + c = channel c at height z): → (weight
    [Z·O, Z·C, k, k], bias [Z·O]). Output height z reads input heights z + dz − k // 2 (zero padding: the
    blocks outside the grid are zero); the BatchNorm is folded in (scale into the weight, shift into the bias)."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)                         # [O]
    w = conv.weight * scale[:, None, None, None, None]                               # [O, C, k, k, k]
    bias = bn.bias - bn.running_mean * scale
    r = w.shape[-1] // 2
    zero = torch.zeros_like(w[..., 0])
    rows = [torch.cat([w[..., zi - zo + r] if abs(zi - zo) <= r else zero for zi in range(height)], dim=1)
            for zo in range(height)]
    return torch.cat(rows, dim=0), bias.repeat(height)


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
    z = torch.remainder(grid_rows, z_n)
    y = torch.remainder(torch.div(grid_rows, z_n, rounding_mode="floor"), y_n)
    x = torch.remainder(torch.div(grid_rows, z_n * y_n, rounding_mode="floor"), x_n)
    b = torch.div(grid_rows, x_n * y_n * z_n, rounding_mode="floor")
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
        (b, xc, yc, zc) order). Training (and any grid higher than FOLD_Z_MAX) runs the Conv3d modules; eval mode runs the same
        map as 2-D convolutions with z folded into the channels (:func:`fold_conv`, BatchNorm folded in)."""
        b, xc, yc, zc, _ = trunk.shape
        if self.training or zc > FOLD_Z_MAX:
            x = self.blocks(self.stem(trunk.permute(0, 4, 1, 2, 3)))              # [B, Ct, Xc, Yc, Zc]
            return x.permute(0, 2, 3, 4, 1).reshape(-1, x.shape[1])
        x = trunk.permute(0, 3, 4, 1, 2).reshape(b, -1, xc, yc)                    # [B, Zc·C, Xc, Yc]
        x = torch.relu(F.conv2d(x, *fold_conv(self.stem[0], self.stem[1], zc)))
        for block in self.blocks:
            out = torch.relu(F.conv2d(x, *fold_conv(block.conv1, block.bn1, zc), padding=1))
            x = torch.relu(F.conv2d(out, *fold_conv(block.conv2, block.bn2, zc), padding=1) + x)
        ct = x.shape[1] // zc
        return x.reshape(b, zc, ct, xc, yc).permute(0, 3, 4, 1, 2).reshape(-1, ct)  # [M, Ct]

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

    def fused_occupancy(self, trunk: torch.Tensor, fine_points, threshold: float):
        """Inference: (occupancy uint8, density) [B, Xc, Yc, Zc, s³], Φs evaluated only where σ ≥ threshold.

        Equals fusing :meth:`forward`'s outputs (argmax where σ ≥ τ else free) but skips the semantic MLP on free
        voxels (the gather/scatter export as NonZero/Gather/ScatterND; occupied voxels are unique, no reduction).
        """
        b, xc, yc, zc, _ = trunk.shape
        x = self.voxel_features(trunk, fine_points)
        density = torch.sigmoid(self.sigma_head(x)).reshape(-1)                    # [B·Xc·Yc·Zc·s³]
        occupied = torch.nonzero(density >= threshold).reshape(-1)
        labels = torch.argmax(self.semantic_head(torch.index_select(x, 0, occupied)), dim=-1).to(torch.uint8)
        occupancy = torch.full(density.shape, FREE, dtype=torch.uint8, device=x.device)
        occupancy = occupancy.index_put((occupied,), labels)
        shape = (b, xc, yc, zc, self.stride ** 3)
        return occupancy.reshape(shape), density.reshape(shape)
