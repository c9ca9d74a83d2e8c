"""The full occupancy network: uint8 images → preprocessing → ResNet → neck → LSS lift → 3D decoder → σ, logits.

Inputs (all batch-first, camera order ``occflownet.occ3d.CAMERAS``):
- images uint8 [B, 6, H, W, 3] RGB, any H×W;
- intrinsics float32 [B, 6, 3, 3] for that H×W (camera frame → pixels, OpenCV camera);
- cam2ego float32 [B, 6, 4, 4] (camera frame → ego frame of the current keyframe).
Outputs are in the ego frame, grid indexed [x, y, z] (``occflownet.occ3d.GRID``).
"""
from __future__ import annotations

import torch
from torch import nn

from occflownet.contract import NUM_CAMERAS
from occflownet.occ3d import FREE, GRID, NUM_CLASSES
from occflownet.model.backbone import ResNet
from occflownet.model.presets import FEATURE_STRIDE, ModelConfig
from occflownet.model.decoder import VoxelDecoder, block_rows, unblock
from occflownet.model.lift import DepthContextHead, LiftSplat
from occflownet.model.neck import Stride16Neck
from occflownet.model.preprocess import preprocess_images, scale_intrinsics_to_features


def fuse_occupancy(density: torch.Tensor, logits: torch.Tensor, threshold: float) -> torch.Tensor:
    """occupancy uint8 [...] = argmax(logits [..., 17]) where density [...] >= threshold, else 17 (free)."""
    labels = torch.argmax(logits, dim=-1)
    return torch.where(density >= threshold, labels, torch.full_like(labels, FREE)).to(torch.uint8)


class OccupancyModel(nn.Module):
    """OccFlowNet-style camera-only occupancy model (see the module docstring for inputs)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.backbone = ResNet(cfg.backbone_block, cfg.backbone_layers, cfg.backbone_width)
        self.neck = Stride16Neck(self.backbone.out_channels, cfg.neck_channels)
        fine = cfg.head_channels if cfg.uses_fine_skip else 0
        self.depth_head = DepthContextHead(cfg.neck_channels, cfg.num_depth_bins, cfg.context_channels, fine)
        self.lift = LiftSplat(cfg.depth_bin_centers(), cfg.decoder_stride)
        self.decoder = VoxelDecoder(cfg.context_channels, cfg.decoder_stride, cfg.decoder_channels,
                                    cfg.decoder_blocks, cfg.head_channels, cfg.sigma_hidden, cfg.semantic_hidden,
                                    cfg.head_init)
        # training only (an auxiliary loss reads it; inference() and the exported graph never run it)
        self.image_head = nn.Conv2d(cfg.neck_channels, NUM_CLASSES, 1) if cfg.image_semantics else None

    # ---------------------------------------------------------------- shared trunk
    def _check_inputs(self, images, intrinsics, cam2ego):
        if images.dtype != torch.uint8 or images.dim() != 5 or images.shape[1] != NUM_CAMERAS \
                or images.shape[4] != 3:
            raise ValueError(f"images must be uint8 [B, 6, H, W, 3], got {images.dtype} {tuple(images.shape)}")
        if intrinsics.dim() != 4 or tuple(intrinsics.shape[1:]) != (NUM_CAMERAS, 3, 3):
            raise ValueError(f"intrinsics must be [B, 6, 3, 3], got {tuple(intrinsics.shape)}")
        if cam2ego.dim() != 4 or tuple(cam2ego.shape[1:]) != (NUM_CAMERAS, 4, 4):
            raise ValueError(f"cam2ego must be [B, 6, 4, 4], got {tuple(cam2ego.shape)}")
        return intrinsics.to(torch.float32), cam2ego.to(torch.float32)

    def _lift(self, images, intrinsics, cam2ego):
        """→ (trunk grid, fine points, depth_prob [B, 6, D, h, w], feature_intrinsics [B, 6, 3, 3],
        features [B·6, neck, h, w])."""
        intrinsics, cam2ego = self._check_inputs(images, intrinsics, cam2ego)
        cfg = self.cfg
        b = images.shape[0]
        x, input_k = preprocess_images(images, intrinsics, cfg.input_size, cfg.image_mean, cfg.image_std,
                                       cfg.subsample_large_inputs)
        features = self.neck(*self.backbone(x))                                    # [B*6, N, h, w]
        h, w = features.shape[-2:]
        depth_logits, context, fine = self.depth_head(features)
        depth_prob = torch.softmax(depth_logits, dim=1).reshape(b, NUM_CAMERAS, -1, h, w)
        context = context.reshape(b, NUM_CAMERAS, -1, h, w).permute(0, 1, 3, 4, 2)  # [B, 6, h, w, C]
        if fine.shape[1] > 0:
            fine = fine.reshape(b, NUM_CAMERAS, -1, h, w).permute(0, 1, 3, 4, 2)
        else:
            fine = None
        feature_k = scale_intrinsics_to_features(input_k, FEATURE_STRIDE)
        trunk, fine_points = self.lift(depth_prob, context, fine, feature_k, cam2ego)
        return trunk, fine_points, depth_prob, feature_k, features

    # ---------------------------------------------------------------- public entry points
    def forward(self, images: torch.Tensor, intrinsics: torch.Tensor, cam2ego: torch.Tensor,
                density_at: torch.Tensor | None = None, logits_at: torch.Tensor | None = None) -> dict:
        """Training/analysis outputs:
        density float [B, 200, 200, 16] (σ ∈ [0, 1]) and density_logit (its logit: σ = sigmoid(density_logit));
        logits float [B, 200, 200, 16, 17];
        depth_prob float [B, 6, D, h, w] (softmax over D, z-depth bins ``cfg.depth_bin_centers()``);
        feature_intrinsics float [B, 6, 3, 3] (camera frame → feature-map pixel coordinates);
        with ``cfg.image_semantics`` also image_logits float [B, 6, 17, h, w] (the class of each feature cell);
        in eval mode also occupancy uint8 [B, 200, 200, 16] (fused with τ = cfg.threshold; a training step has no
        use for it).

        ``density_at`` / ``logits_at``: int64 [K] rows of the flattened grid [B·200·200·16] (row = ((b·200 + x)·200
        + y)·16 + z, ego frame): the head then runs on those voxels only and ``density`` is [K] / ``logits`` [K, 17]
        in the rows' order (a 3D-label loss needs σ and the classes only where it has labels: far fewer voxels
        than the grid). No occupancy is fused then."""
        trunk, fine_points, depth_prob, feature_k, features = self._lift(images, intrinsics, cam2ego)
        s = self.cfg.decoder_stride
        to_block = lambda rows: None if rows is None else block_rows(rows, GRID.shape, s)  # noqa: E731
        density_rows = to_block(density_at)
        logit_rows = density_rows if logits_at is density_at else to_block(logits_at)
        sigma_logits, semantic_logits = self.decoder(trunk, fine_points, density_rows, logit_rows)
        density_logit = sigma_logits if density_at is not None else unblock(sigma_logits, s)
        logits = semantic_logits if logits_at is not None else unblock(semantic_logits, s)
        out = {"density": torch.sigmoid(density_logit), "density_logit": density_logit, "logits": logits,
               "depth_prob": depth_prob, "feature_intrinsics": feature_k}
        if self.image_head is not None:
            out["image_logits"] = self.image_head(features).reshape(depth_prob.shape[:2] + (NUM_CLASSES,)
                                                                    + features.shape[-2:])
        if not self.training and density_at is None and logits_at is None:
            with torch.no_grad():
                out["occupancy"] = fuse_occupancy(out["density"], logits, self.cfg.threshold)
        return out

    def inference(self, images: torch.Tensor, intrinsics: torch.Tensor, cam2ego: torch.Tensor):
        """The exported path: → (occupancy uint8 [B, 200, 200, 16], density float32 [B, 200, 200, 16]).

        Same result as fusing :meth:`forward`'s outputs, computed as a CPU runs it fastest: the pooling by sorted
        segment sums, the per-voxel chain slab by slab, Φs only on voxels with σ ≥ τ
        (:meth:`~occflownet.model.decoder.VoxelDecoder.fused_occupancy`)."""
        trunk, fine_points, _, _, _ = self._lift(images, intrinsics, cam2ego)
        return self.decoder.fused_occupancy(trunk, fine_points, self.cfg.threshold)


class InferenceGraph(nn.Module):
    """Wrapper whose forward is :meth:`OccupancyModel.inference` (the module that is exported to ONNX)."""

    def __init__(self, model: OccupancyModel):
        super().__init__()
        self.model = model

    def forward(self, images, intrinsics, cam2ego):
        return self.model.inference(images, intrinsics, cam2ego)


def create_model(cfg: ModelConfig, seed: int | None = None) -> OccupancyModel:
    """Build a model; with ``seed`` torch's RNG is seeded first, so the same seed gives the same weights."""
    if seed is not None:
        torch.manual_seed(int(seed))
    return OccupancyModel(cfg)

