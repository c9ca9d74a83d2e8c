"""One training step's losses: the terms chosen once from the configuration (``losses.loss_terms``), and per step
only the inputs they need: volumes per frame (disocclusion / occupancy flow) → renderings, batch fields, outputs.

Inputs come from :func:`occflownet.train.dataset.collate`; everything is in the current ego frame of each sample.
Volume layout: per sample b, volume 0 is the prediction itself (t = 0); without flow, volume 1 serves every
t ≠ 0 (disoccluded when that is on); with flow, every present t ≠ 0 gets its own warped copy. ``ray_volume``
indexes the stacked [N, X, Y, Z] volumes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from occflownet.data.free_stretch import FREE_BEFORE_MIN
from occflownet.model.presets import ModelConfig
from occflownet.render.disocclusion import disocclude
from occflownet.render.footprint import ray_footprint
from occflownet.render.occupancy_flow import PackedMoves, warp_volumes
from occflownet.render.volume_render import RenderConfig, render_rays, table_rows
from occflownet.train.losses import loss_terms, step_data
from occflownet.train.recipe import TrainConfig

# The renderings a term may need, in the order they are made: each draws its render jitter from the step's
# generator after the one before, so the order is part of what a step computes.
RENDERINGS = ("rendered", "free_opacity", "before_opacity")
POINT_INPUTS = ("point_logits", "point_labels", "point_sigma")   # at the voxels holding the rays' points


class LossComputer:
    """Callable ``(model outputs, batch, device, generator) → {term name: scalar tensor, ..., "loss": their sum}``
    over the terms of ``loss_terms(cfg)`` (``self.terms``), each call computing only the inputs they name
    (``self.needs``)."""

    def __init__(self, cfg: TrainConfig, model_cfg: ModelConfig, class_weights: torch.Tensor | None,
                 render_cfg: RenderConfig | None = None, footprint: bool = True):
        self.cfg = cfg
        self.footprint = footprint         # False: never run the heads on the footprint only (tests compare)
        self.render_cfg = render_cfg or RenderConfig()
        self.class_weights = class_weights
        self.depth_bins = torch.tensor(model_cfg.depth_bin_centers(), dtype=torch.float32)
        self.terms = loss_terms(cfg)
        self.needs = frozenset(name for term in self.terms for name in term.needs)
        self.data = step_data(self.terms)   # what the batch carries (losses.INPUT_DATA)

    @property
    def heads_at_rows(self) -> bool:
        """Whether the model's heads need to run only on the supervised voxels: every term reads the grid there
        (3D labels alone; no rendering and no free prior, which read every voxel)."""
        return not self.needs & {"density", "logits", *RENDERINGS, *POINT_INPUTS}

    @property
    def heads_on_footprint(self) -> bool:
        """Whether the semantic head (and σ's, unless a term reads every σ) needs to run only on the rays'
        footprint (:meth:`footprint_rows`, with the labelled voxels the 3D terms read): the terms read the logits
        through renderings, the rays' points and the voxel labels only. Exact: a step computes the same loss and
        gradients either way (tests/test_train_losses.py)."""
        return self.footprint and bool(self.needs & {*RENDERINGS, *POINT_INPUTS}) and "logits" not in self.needs

    @property
    def _logits_key(self) -> str:
        """The batch's rows the semantic head runs at when :attr:`heads_at_rows`: the kept voxels when the affinity
        terms read their logits, else the occupied ones."""
        return "voxel_rows" if "kept_logits" in self.needs else "occupied_rows"

    def _sigma_everywhere(self, batch: dict) -> bool:
        """Whether a term reads σ of every voxel: the free prior, or the 3D density term without a voxel mask."""
        return "density" in self.needs or ("voxel_sigma" in self.needs and batch.get("voxel_rows") is None)

    def head_rows(self, batch: dict, device) -> dict:
        """Keyword arguments of the model's forward for this batch: ``density_at`` / ``logits_at`` (the rows of
        :func:`~occflownet.train.losses.voxel_targets`) when :attr:`heads_at_rows`; the rows of
        :meth:`footprint_rows` when :attr:`heads_on_footprint`, for σ too unless a term reads every σ (also stored
        as the batch's "footprint_rows", from which :meth:`inputs` puts σ back on the grids and the renderer reads
        the logits); else none (the whole grid)."""
        if self.heads_at_rows:
            rows, logits_rows = batch.get("voxel_rows"), batch.get(self._logits_key)
            return {"density_at": None if rows is None else rows.to(device),
                    "logits_at": None if logits_rows is None else logits_rows.to(device)}
        if self.heads_on_footprint:
            rows = self.footprint_rows(batch).to(device)
            batch["footprint_rows"] = rows
            return {"density_at": None if self._sigma_everywhere(batch) else rows, "logits_at": rows}
        return {}

    def footprint_rows(self, batch: dict) -> torch.Tensor:
        """int64 [K], ascending rows of the batch's flattened grids [B·X·Y·Z]: every voxel that this step's terms
        can read — the footprint (:func:`~occflownet.render.footprint.ray_footprint`) of the batch's rays up to
        the rendering's far end (or their free stretch's end, if beyond) and of its free rays, in the grid of the
        sample each ray's volume belongs to, the voxels holding the rays' points, with 3D labels the voxels their
        terms read (the labelled occupied ones; the kept ones too where σ is not computed everywhere or the
        affinity terms read their logits) and, with
        flow, the voxels of the boxes whose predicted voxels move (the warp reads them there; what it writes
        elsewhere it reads only at the voxel it writes)."""
        grid, far = self.render_cfg.grid, self.render_cfg.far
        samples = int(batch["images"].shape[0])
        source = batch["volume_source"].numpy()
        ends = np.maximum(far, batch["ray_free_ends"].numpy()) if "before_opacity" in self.needs else far
        rays = [(batch["ray_origins"].numpy(), batch["ray_directions"].numpy(), ends,
                 source[batch["ray_volume"].numpy()])]
        if "free_origins" in batch:
            rays.append((batch["free_origins"].numpy(), batch["free_directions"].numpy(), far,
                         source[batch["free_volume"].numpy()]))
        mask = np.zeros((samples, *grid.shape), dtype=bool)
        for origins, directions, t_end, sample in rays:
            t_end = np.broadcast_to(np.asarray(t_end, dtype=np.float64), (len(origins),))
            for b in range(samples):
                mine = sample == b
                if mine.any():
                    mask[b] |= ray_footprint(origins[mine], directions[mine], t_end[mine], grid)
        if self.needs & set(POINT_INPUTS):      # the voxels point_values reads, by the same arithmetic
            inside, ijk = (t.numpy() for t in self.point_voxels(batch, torch.device("cpu")))
            b = source[batch["ray_volume"].numpy()]
            mask[(b[inside], *ijk[inside].T)] = True
        for b, (moves, _) in enumerate(batch.get("flow", [])):          # one entry per sample, in batch order
            mask[(b, *np.asarray(moves["voxels"]).reshape(-1, 3).T)] = True
        flat = mask.reshape(-1)
        if "occupied_logits" in self.needs:
            flat[batch["occupied_rows"].numpy()] = True
        if "voxel_sigma" in self.needs and not self._sigma_everywhere(batch):
            flat[batch["voxel_rows"].numpy()] = True
        if "kept_logits" in self.needs:                    # every kept voxel: all of them without a mask
            rows = batch.get("voxel_rows")
            flat[slice(None) if rows is None else rows.numpy()] = True
        return torch.from_numpy(np.flatnonzero(flat).astype(np.int64))

    def __call__(self, outputs: dict, batch: dict, device, generator: torch.Generator | None = None,
                 step: int | None = None) -> dict:
        """The terms at optimisation step ``step`` (their ramps; None: full weight)."""
        inputs = self.inputs(outputs, batch, device, generator)
        terms = {term.name: term(inputs, step) for term in self.terms}
        terms["loss"] = sum(terms.values())
        return terms

    def inputs(self, outputs: dict, batch: dict, device, generator: torch.Generator | None = None) -> dict:
        """The inputs the terms name (``self.needs``), each computed once (and a few cheap others):

        - model outputs as float32: "density" [B, X, Y, Z], "logits" [B, X, Y, Z, 17] (with the heads on the
          footprint [K, 17] at the batch's "footprint_rows", σ zero off them), "depth_prob" [B, N, D, h, w];
          "feature_intrinsics" [B, N, 3, 3]; "image_logits" [B, N, 17, h, w]; "voxel_sigma" [K] and
          "occupied_logits" [K', 17], σ and the logits at the batch's "voxel_rows" (every voxel without) and
          "occupied_rows" (the model gave them at those rows when :meth:`head_rows` asked it to, else they are
          picked from the grid);
        - renderings (:meth:`renderings`): "rendered", "free_opacity" [F], "before_opacity" [S]; at the rays'
          points (:meth:`point_values`) "point_logits" [P, 17], "point_labels" [P], "point_sigma" [P];
        - constants: "class_weights" [17] or None, "depth_bins" [D];
        - every other name is a batch field, moved to ``device`` ("ray_depths" [R], "ray_labels" [R], "cam2ego"
          [B, N, 4, 4], "depth_points" B × [P_b, 3], "depth_labels" B × [P_b], "occ_semantics" [B, X, Y, Z],
          "occ_mask" [B, X, Y, Z]).
        """
        density, logits = outputs["density"].float(), outputs["logits"].float()
        if density.dim() == 1 and "footprint_rows" in batch:  # heads on the footprint: σ back onto the grids; the
            density = self._on_grids(density, batch)          # logits stay a table [K, 17] (FrameVolumes)
        found = {"density": density, "logits": logits, "depth_bins": self.depth_bins.to(device),
                 "class_weights": None if self.class_weights is None else self.class_weights.to(device)}
        if "voxel_sigma" in self.needs:
            found["voxel_sigma"] = self._at_rows(density.reshape(-1), batch.get("voxel_rows"), density.dim() == 1,
                                                 device)
        if "occupied_logits" in self.needs:
            found["occupied_logits"] = self._logits_at(logits, batch, "occupied_rows", device)
        if "kept_logits" in self.needs:
            found["kept_logits"] = self._logits_at(logits, batch, "voxel_rows", device)
        if "depth_prob" in self.needs:
            found["depth_prob"] = outputs["depth_prob"].float()
        if "feature_intrinsics" in self.needs:
            found["feature_intrinsics"] = outputs["feature_intrinsics"]
        if "image_logits" in self.needs:
            if "image_logits" not in outputs:
                raise ValueError("the image_semantics term needs the model's image head (ModelConfig.image_semantics)")
            found["image_logits"] = outputs["image_logits"].float()
        if self.needs & {*RENDERINGS, *POINT_INPUTS}:
            volumes = self.volumes(density, logits, batch, device)
            found.update(self.renderings(volumes, batch, device, generator))
            if self.needs & set(POINT_INPUTS):
                found.update(self.point_values(volumes, batch, device))
        missing = sorted(self.needs - found.keys() - batch.keys())
        if missing:
            users = [term.name for term in self.terms if set(term.needs) & set(missing)]
            raise ValueError(f"the loss terms {users} need the batch fields {missing}, which the batch lacks")
        for name in self.needs - found.keys():
            value = batch[name]
            found[name] = [v.to(device) for v in value] if isinstance(value, list) else value.to(device)
        return found

    def _on_grids(self, values: torch.Tensor, batch: dict) -> torch.Tensor:
        """values [K, ...] at the batch's "footprint_rows" [K] → [B, X, Y, Z, ...], zero off the footprint (read
        there, if at all, with weight 0: ``occflownet.render.footprint``); the gradient flows to ``values``."""
        shape = (int(batch["images"].shape[0]), *self.render_cfg.grid.shape)
        grid = values.new_zeros((int(np.prod(shape)), *values.shape[1:]))
        return grid.index_copy(0, batch["footprint_rows"], values).reshape(*shape, *values.shape[1:])

    def _logits_at(self, logits: torch.Tensor, batch: dict, key: str, device) -> torch.Tensor:
        """The logits [K, 17] at the batch's rows ``key`` ("occupied_rows", or "voxel_rows": every voxel when the
        batch has none): from the footprint's table [K', 17] (at the batch's ascending "footprint_rows", which hold
        them), from the table the model gave at the kept voxels (with the affinity terms), as the model gave them
        at exactly these rows, or picked from the grids [B, X, Y, Z, 17]."""
        rows = batch.get(key)
        if logits.dim() != 2:                    # the grids [B, X, Y, Z, 17]
            return self._at_rows(logits.reshape(-1, logits.shape[-1]), rows, False, device)
        table = batch.get("footprint_rows")
        if table is None:                        # the heads ran at the rows head_rows asked for
            table = None if key == self._logits_key else batch.get(self._logits_key)
        if table is None or rows is None:        # given at exactly these rows (or the footprint is every voxel)
            return logits
        return logits[torch.searchsorted(table.to(device), rows.to(device))]

    @staticmethod
    def _at_rows(values: torch.Tensor, rows: torch.Tensor | None, given: bool, device) -> torch.Tensor:
        """values [N, ...] flattened over the batch's grids → its rows ``rows`` [K] (None: all), unless the model
        ``given`` them at those rows already."""
        return values if given or rows is None else values[rows.to(device)]

    def renderings(self, volumes: "FrameVolumes", batch: dict, device,
                   generator: torch.Generator | None = None) -> dict:
        """Those of :data:`RENDERINGS` the terms need, through the per-frame volumes (:meth:`volumes`), in that
        order: "rendered" (``RenderOutput`` of the batch's rays), "free_opacity" (:meth:`_free_opacity`),
        "before_opacity" (:meth:`_before_opacity`)."""
        wanted = [name for name in RENDERINGS if name in self.needs]
        made = {}
        if "rendered" in wanted:
            made["rendered"] = render_rays(*volumes.grids, batch["ray_origins"].to(device),
                                           batch["ray_directions"].to(device), self.render_cfg, generator=generator,
                                           batch_index=batch["ray_volume"].to(device),
                                           logits_index=volumes.logits_index, logits_rows=volumes.logits_rows)
        if "free_opacity" in wanted:
            made["free_opacity"] = self._free_opacity(volumes, batch, device, generator)
        if "before_opacity" in wanted:
            made["before_opacity"] = self._before_opacity(volumes, batch, device, generator)
        return made

    def volumes(self, density: torch.Tensor, logits: torch.Tensor, batch: dict, device) -> "FrameVolumes":
        """The per-frame volumes of the batch's rays (:class:`FrameVolumes`)."""
        source = batch["volume_source"].to(device)
        temporal = batch["volume_is_temporal"].to(device)
        if self.cfg.flow:
            if logits.dim() == 2:          # heads on the footprint: the warp moves voxels of whole grids
                logits = self._on_grids(logits, batch)
            parts = [PackedMoves.from_arrays(**moves) for moves, _ in batch["flow"]]
            packed = PackedMoves.concat(parts, [offset for _, offset in batch["flow"]]).to(device)
            return FrameVolumes(*warp_volumes(density, logits, source, packed, mover=self.cfg.flow_mover))
        rows = batch.get("footprint_rows") if logits.dim() == 2 else None
        dens = density.index_select(0, source)   # (its backward is an index_add: 5x faster than indexing's here)
        if self.cfg.disocclusion and bool(temporal.any()):
            # disocclude each sample's volume once, then give its copy to the temporal volumes
            cleared = disocclude(density, logits, rows=rows).index_select(0, source)
            dens = torch.where(temporal[:, None, None, None], cleared, dens)
        if rows is None:
            return FrameVolumes(dens, logits, source)   # the frames of a sample read its logits: no copy of them
        table = torch.full((density.numel(),), -1, dtype=torch.long, device=device)
        table.index_copy_(0, rows, torch.arange(len(rows), device=device))
        return FrameVolumes(dens, logits, source, table)

    def point_values(self, volumes: "FrameVolumes", batch: dict, device) -> dict:
        """:data:`POINT_INPUTS` of the batch's rays whose LiDAR point (origin + depth · direction, current ego frame)
        lies inside the grid (P of them): "point_logits" [P, 17] and "point_sigma" [P], the logits and σ of the voxel
        holding the point in the ray's frame volume (with flow the moved one), and "point_labels" [P], the rays'
        labels."""
        inside, ijk = self.point_voxels(batch, device)
        volume = batch["ray_volume"].to(device)[inside]
        logits_volume = volume if volumes.logits_index is None else volumes.logits_index[volume]
        i, j, k = ijk[inside].unbind(1)
        return {"point_logits": volumes.logits_at(logits_volume, i, j, k),
                "point_sigma": volumes.density[volume, i, j, k],
                "point_labels": batch["ray_labels"].to(device)[inside]}

    def point_voxels(self, batch: dict, device) -> tuple[torch.Tensor, torch.Tensor]:
        """(inside bool [R], ijk long [R, 3]): the voxel holding each ray's LiDAR point (origin + depth · direction,
        current ego frame, float32 arithmetic on ``device``) and whether it lies in the grid."""
        grid = self.render_cfg.grid
        points = batch["ray_origins"].to(device) + batch["ray_depths"].to(device)[:, None] * \
            batch["ray_directions"].to(device)
        ijk = grid.index_of(points)
        return ((ijk >= 0) & (ijk < torch.tensor(grid.shape, device=device))).all(dim=1), ijk

    def _free_opacity(self, volumes: "FrameVolumes", batch: dict, device, generator) -> torch.Tensor:
        """Opacity [F] of the batch's free rays (free-space beams, camera rays beyond the grid) through their
        volumes; with "free_masks" in the batch (``free_stretch="points"``) through copies of them with the voxels
        near a LiDAR point of the ray's frame at σ = 0 ([T, X, Y, Z], one per frame, ``slot_volume`` the volume
        each copies). [0] when no sample of the batch found any (the dataset then leaves the free_* fields out)."""
        if "free_origins" not in batch:
            return torch.zeros(0, device=device)
        density, ray_volume, logits_index = volumes.density, batch["free_volume"].to(device), volumes.logits_index
        if "free_masks" in batch:
            slot_volume = batch["slot_volume"].to(device)
            density = density[slot_volume].masked_fill(batch["free_masks"].to(device), 0.0)
            ray_volume = batch["free_slot"].to(device)
            logits_index = slot_volume if logits_index is None else logits_index[slot_volume]
        return render_rays(density, volumes.logits, batch["free_origins"].to(device),
                           batch["free_directions"].to(device), self.render_cfg, generator=generator,
                           batch_index=ray_volume, logits_index=logits_index,
                           logits_rows=volumes.logits_rows).weight_sum

    def _before_opacity(self, volumes: "FrameVolumes", batch: dict, device, generator) -> torch.Tensor:
        """Opacity [S] of the free stretches in front of the points of ``free_rays_per_step`` rays per sample (every
        k-th ray of the batch: the rays are drawn at random and stored sample by sample), each through its ray's
        volume, up to the batch's "ray_free_ends" (``RayBatch.free_ends``, the rule of ``cfg.free_stretch``)."""
        total = len(batch["ray_depths"])
        n = self.cfg.free_rays_per_step * int(batch["images"].shape[0])
        pick = torch.arange(0, total, max(1, total // n))[:n]
        ends = batch["ray_free_ends"][pick]
        keep = pick[ends >= FREE_BEFORE_MIN]
        ends = ends[ends >= FREE_BEFORE_MIN]
        out = render_rays(*volumes.grids, batch["ray_origins"][keep].to(device),
                          batch["ray_directions"][keep].to(device), self.render_cfg, generator=generator,
                          batch_index=batch["ray_volume"][keep].to(device), far=ends.to(device),
                          logits_index=volumes.logits_index, logits_rows=volumes.logits_rows)
        return out.weight_sum


@dataclass(frozen=True)
class FrameVolumes:
    """What the batch's rays render through: density [N, X, Y, Z] per frame volume (``ray_volume`` indexes it) and
    logits [L, X, Y, Z, 17], volume n reading logits volume ``logits_index[n]`` (long [N]; None: L = N, one each).
    Without flow the frames of a sample share its predicted logits (L = B); with flow each frame has its own.
    With the heads on the footprint the logits are a table [K, 17] and ``logits_rows`` (long [L·X·Y·Z]) the row of
    each voxel, -1 off the footprint (``render_rays``' ``logits_rows``)."""

    density: torch.Tensor
    logits: torch.Tensor
    logits_index: torch.Tensor | None = None
    logits_rows: torch.Tensor | None = None

    def logits_at(self, volume: torch.Tensor, i: torch.Tensor, j: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """[P, 17]: the logits of voxels (i, j, k) [P] of logits volumes ``volume`` [P] (zero off the footprint)."""
        if self.logits_rows is None:
            return self.logits[volume, i, j, k]
        x, y, z = self.density.shape[1:]
        return table_rows(self.logits, self.logits_rows[((volume * x + i) * y + j) * z + k])

    @property
    def grids(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.density, self.logits
