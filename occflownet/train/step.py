"""One training step's losses: volumes per frame (disocclusion / occupancy flow) → rendering → loss terms.

Inputs come from :func:`occflownet.train.dataset.collate`; everything is in the current ego frame of each sample.
Volume layout: per sample b, volume 0 is the prediction itself (t = 0); without flow, volume 1 serves every
t ≠ 0 (disoccluded when that is on); with flow, every present t ≠ 0 gets its own warped copy. ``ray_volume``
indexes the stacked [N, X, Y, Z] volumes.
"""
from __future__ import annotations

from dataclasses import replace

import torch

from occflownet.data.rays import FREE_BEFORE_MIN, free_segment_ends
from occflownet.train import losses as L
from occflownet.model.presets import ModelConfig
from occflownet.render.disocclusion import disocclude
from occflownet.render.occupancy_flow import PackedMoves, warp_volumes
from occflownet.render.volume_render import RenderConfig, render_rays
from occflownet.train.recipe import TrainConfig


class LossComputer:
    """Callable ``(model outputs, batch, device, generator) → {name: scalar tensor, "loss": total}``."""

    def __init__(self, cfg: TrainConfig, model_cfg: ModelConfig, class_weights: torch.Tensor | None,
                 render_cfg: RenderConfig | None = None):
        self.cfg = cfg
        self.render_cfg = render_cfg or RenderConfig(density_scale=cfg.density_scale, sigma_is=cfg.sigma_is)
        self.class_weights = class_weights
        self.depth_bins = torch.tensor(model_cfg.depth_bin_centers(), dtype=torch.float32)
        self.loss_cfg = L.LossConfig(mode=cfg.supervision, free_space_weight=cfg.free_space_weight,
                                     depth_weight=cfg.render_depth_weight, render_semantics=cfg.render_semantics,
                                     free_prior_weight=cfg.free_prior_weight)
        if not cfg.depth_loss:  # "semantics only": no rendered-depth and no LiDAR-depth term
            self.loss_cfg = replace(self.loss_cfg, depth_weight=0.0, lidar_depth_weight=0.0)

    def volumes(self, density: torch.Tensor, logits: torch.Tensor, batch: dict, device):
        """Stacked per-frame volumes (density [N, X, Y, Z], logits [N, X, Y, Z, 17]) for the batch's rays."""
        source = batch["volume_source"].to(device)
        temporal = batch["volume_is_temporal"].to(device)
        if self.cfg.flow:
            parts = [PackedMoves.from_arrays(**moves) for moves, _ in batch["flow"]]
            packed = PackedMoves.concat(parts, [offset for _, offset in batch["flow"]]).to(device)
            return warp_volumes(density, logits, source, packed, mover=self.cfg.flow_mover)
        dens = density[source]
        if self.cfg.disocclusion and bool(temporal.any()):
            # disocclude each sample's volume once, then give its copy to the temporal volumes
            dens = torch.where(temporal[:, None, None, None], disocclude(density, logits)[source], dens)
        return dens, logits[source]

    def _before_opacity(self, dens, logi, batch: dict, device, generator) -> torch.Tensor:
        """Opacity [S] of the free stretches in front of the points of ``free_rays_per_step`` rays per sample (every
        k-th ray of the batch: the rays are drawn at random and stored sample by sample), each through its ray's
        volume (``free_segment_ends``)."""
        total = len(batch["ray_depths"])
        n = self.cfg.free_rays_per_step * int(batch["images"].shape[0])
        pick = torch.arange(0, total, max(1, total // n))[:n]
        ends = free_segment_ends(batch["ray_depths"][pick])
        keep = pick[ends >= FREE_BEFORE_MIN]
        ends = ends[ends >= FREE_BEFORE_MIN]
        out = render_rays(dens, logi, batch["ray_origins"][keep].to(device), batch["ray_directions"][keep].to(device),
                          self.render_cfg, generator=generator, batch_index=batch["ray_volume"][keep].to(device),
                          far=ends.to(device))
        return out.weight_sum

    def __call__(self, outputs: dict, batch: dict, device, generator: torch.Generator | None = None) -> dict:
        cfg = self.cfg
        density, logits = outputs["density"].float(), outputs["logits"].float()
        inputs: dict = {}
        if cfg.uses_2d:
            dens, logi = self.volumes(density, logits, batch, device)
            inputs.update(
                rendered=render_rays(dens, logi, batch["ray_origins"].to(device), batch["ray_directions"].to(device),
                                     self.render_cfg, generator=generator,
                                     batch_index=batch["ray_volume"].to(device)),
                depth_gt=batch["ray_depths"].to(device), labels_gt=batch["ray_labels"].to(device),
                class_weights=None if self.class_weights is None else self.class_weights.to(device))
            if "free_origins" in batch:  # free-space beams through the same per-frame volumes
                free = render_rays(dens, logi, batch["free_origins"].to(device), batch["free_directions"].to(device),
                                   self.render_cfg, generator=generator, batch_index=batch["free_volume"].to(device))
                inputs["free_opacity"] = free.weight_sum
            if cfg.free_before_point:
                inputs["before_opacity"] = self._before_opacity(dens, logi, batch, device, generator)
        if cfg.depth_loss:
            inputs.update(depth_prob=outputs["depth_prob"].float(), feature_intrinsics=outputs["feature_intrinsics"],
                          cam2ego=batch["cam2ego"].to(device), points_ego=[p.to(device) for p in batch["depth_points"]],
                          depth_bin_centers=self.depth_bins.to(device))
        if cfg.uses_3d:
            # every voxel by default, as the official 3D training (use_mask=False); mask_camera only when asked
            inputs.update(density=density, logits=logits, semantics_gt=batch["occ_semantics"].to(device),
                          voxel_mask=batch["occ_mask"].to(device) if cfg.voxel_mask else None)
        if self.loss_cfg.free_prior_weight > 0:
            inputs["prior_density"] = density
        terms = L.total_loss(self.loss_cfg, **inputs)
        terms["loss"] = terms.pop("total")
        return terms
