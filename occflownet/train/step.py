"""One training step's losses: the terms chosen once from the configuration (``losses.loss_terms``), and per step
only the inputs they need: volumes per frame (disocclusion / occupancy flow) → renderings, batch fields, outputs.

Inputs come from :func:`occflownet.train.dataset.collate`; everything is in the current ego frame of each sample.
Volume layout: per sample b, volume 0 is the prediction itself (t = 0); without flow, volume 1 serves every
t ≠ 0 (disoccluded when that is on); with flow, every present t ≠ 0 gets its own warped copy. ``ray_volume``
indexes the stacked [N, X, Y, Z] volumes.
"""
from __future__ import annotations

import torch

from occflownet.data.rays import FREE_BEFORE_MIN, free_segment_ends
from occflownet.model.presets import ModelConfig
from occflownet.render.disocclusion import disocclude
from occflownet.render.occupancy_flow import PackedMoves, warp_volumes
from occflownet.render.volume_render import RenderConfig, render_rays
from occflownet.train.losses import loss_terms
from occflownet.train.recipe import TrainConfig

# The renderings a term may need, in the order they are made: each draws its render jitter from the step's
# generator after the one before, so the order is part of what a step computes.
RENDERINGS = ("rendered", "free_opacity", "before_opacity")


class LossComputer:
    """Callable ``(model outputs, batch, device, generator) → {term name: scalar tensor, ..., "loss": their sum}``
    over the terms of ``loss_terms(cfg)`` (``self.terms``), each call computing only the inputs they name
    (``self.needs``)."""

    def __init__(self, cfg: TrainConfig, model_cfg: ModelConfig, class_weights: torch.Tensor | None,
                 render_cfg: RenderConfig | None = None):
        self.cfg = cfg
        self.render_cfg = render_cfg or RenderConfig(density_scale=cfg.density_scale, sigma_is=cfg.sigma_is)
        self.class_weights = class_weights
        self.depth_bins = torch.tensor(model_cfg.depth_bin_centers(), dtype=torch.float32)
        self.terms = loss_terms(cfg)
        self.needs = frozenset(name for term in self.terms for name in term.needs)

    def __call__(self, outputs: dict, batch: dict, device, generator: torch.Generator | None = None) -> dict:
        inputs = self.inputs(outputs, batch, device, generator)
        terms = {term.name: term(inputs) for term in self.terms}
        terms["loss"] = sum(terms.values())
        return terms

    def inputs(self, outputs: dict, batch: dict, device, generator: torch.Generator | None = None) -> dict:
        """The inputs the terms name (``self.needs``), each computed once (and a few cheap others):

        - model outputs as float32: "density" [B, X, Y, Z], "logits" [B, X, Y, Z, 17], "depth_prob" [B, N, D, h, w];
          "feature_intrinsics" [B, N, 3, 3];
        - renderings (:meth:`renderings`): "rendered", "free_opacity" [F], "before_opacity" [S];
        - constants: "class_weights" [17] or None, "depth_bins" [D];
        - every other name is a batch field, moved to ``device`` ("ray_depths" [R], "ray_labels" [R], "cam2ego"
          [B, N, 4, 4], "depth_points" B × [P_b, 3], "occ_semantics" [B, X, Y, Z], "occ_mask" [B, X, Y, Z]).
        """
        density, logits = outputs["density"].float(), outputs["logits"].float()
        found = {"density": density, "logits": logits, "depth_bins": self.depth_bins.to(device),
                 "class_weights": None if self.class_weights is None else self.class_weights.to(device)}
        if "depth_prob" in self.needs:
            found.update(depth_prob=outputs["depth_prob"].float(), feature_intrinsics=outputs["feature_intrinsics"])
        found.update(self.renderings(density, logits, batch, device, generator))
        missing = sorted(self.needs - found.keys() - batch.keys())
        if missing:
            users = [term.name for term in self.terms if set(term.needs) & set(missing)]
            raise ValueError(f"the loss terms {users} need the batch fields {missing}, which the batch lacks")
        for name in self.needs - found.keys():
            value = batch[name]
            found[name] = [v.to(device) for v in value] if isinstance(value, list) else value.to(device)
        return found

    def renderings(self, density: torch.Tensor, logits: torch.Tensor, batch: dict, device,
                   generator: torch.Generator | None = None) -> dict:
        """Those of :data:`RENDERINGS` the terms need, through the per-frame volumes (:meth:`volumes`), in that
        order: "rendered" (``RenderOutput`` of the batch's rays), "free_opacity" (:meth:`_free_opacity`),
        "before_opacity" (:meth:`_before_opacity`)."""
        wanted = [name for name in RENDERINGS if name in self.needs]
        if not wanted:
            return {}
        dens, logi = self.volumes(density, logits, batch, device)
        made = {}
        if "rendered" in wanted:
            made["rendered"] = render_rays(dens, logi, batch["ray_origins"].to(device),
                                           batch["ray_directions"].to(device), self.render_cfg, generator=generator,
                                           batch_index=batch["ray_volume"].to(device))
        if "free_opacity" in wanted:
            made["free_opacity"] = self._free_opacity(dens, logi, batch, device, generator)
        if "before_opacity" in wanted:
            made["before_opacity"] = self._before_opacity(dens, logi, batch, device, generator)
        return made

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

    def _free_opacity(self, dens, logi, batch: dict, device, generator) -> torch.Tensor:
        """Opacity [F] of the batch's free rays (free-space beams, camera rays beyond the grid) through their
        volumes; [0] when no sample of the batch found any (the dataset then leaves the free_* fields out)."""
        if "free_origins" not in batch:
            return torch.zeros(0, device=device)
        return render_rays(dens, logi, batch["free_origins"].to(device), batch["free_directions"].to(device),
                           self.render_cfg, generator=generator, batch_index=batch["free_volume"].to(device)).weight_sum

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
