"""The training data pipeline: keyframe → images, calibration, sampled rays, LiDAR depth points, 3D labels, flow.

Items are addressed by ``(i, step)`` keys from :class:`~occflownet.train.sampler.StepBatchSampler`; every random
choice of an item (which rays) comes from ``default_rng([seed, step, i])``, so a resumed run loads exactly what an
uninterrupted one would, whatever worker process builds it.

Frames: everything is in the *current ego frame* of the keyframe (ego pose at its LiDAR timestamp, the frame of
the Occ3D ground truth). The model's ``cam2ego`` input is camera → current ego through each camera's own ego pose.
With ``bev_flip`` that frame is mirrored in x and/or y at random, with ``bev_rotate`` turned by a multiple of 90°
about z, every geometric field with it (:mod:`occflownet.train.augment`); with ``image_aug`` each image is warped
and its intrinsics with it; with ``photometric_aug`` its brightness, contrast and saturation are jittered.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from occflownet.data.flow import flow_moves
from occflownet.data.index import SampleIndex
from occflownet.data.loaders import load_occupancy, load_sample_images
from occflownet.data.free_space import FreeSpaceConfig
from occflownet.data.rays import RayBuilder, RayConfig, sample_rays
from occflownet.geometry import invert, transform_points
from occflownet.occ3d import GRID
from occflownet.train.augment import BevFlip, BevRotation, ImageAug, Photometric
from occflownet.train.losses import loss_terms, step_data, voxel_targets
from occflownet.train.recipe import TrainConfig

MAX_DEPTH_POINTS = 40000  # LiDAR points per sample kept for the LSS depth loss
# Keyframes whose camera hits a data worker keeps (about 2 MB each for a nuScenes-size sweep, so 128 MB): a step
# reads its keyframe and 2O neighbours, and with samples drawn at random a cache of only 2O + 2 frames missed
# 5.4 of the 7 frames of a step on the quickstart's world (10 ms each; docs/results.md#training-speed).
RAY_CACHE_FRAMES = 64


def volume_frames(time_offsets: np.ndarray, flow: bool) -> list[int]:
    """The frames t that get their own volume copy, in volume order (volume 0 is always t = 0).

    With flow every present t ≠ 0 gets its own warped copy. Without flow all t ≠ 0 share one copy (the
    disoccluded volume, or the plain one when disocclusion is off), listed as frame 1."""
    present = sorted(set(int(t) for t in np.unique(time_offsets)) - {0})
    if flow:
        return [0] + present
    return [0, 1] if present else [0]


class TrainingSamples(Dataset):
    """Keyframes of one split as training items (see the module docstring)."""

    def __init__(self, dataroot, index: SampleIndex, positions: np.ndarray, cfg: TrainConfig,
                 flow_records: dict | None = None):
        self.dataroot = Path(dataroot)
        self.index = index
        self.positions = np.asarray(positions, dtype=np.int64)
        self.cfg = cfg
        self.flow_records = flow_records or {}
        self.data = step_data(loss_terms(cfg))   # what the run's loss terms read (losses.INPUT_DATA)
        # With occupancy flow, dynamic rays of temporal frames are kept and rendered through the warped volume.
        ray_cfg = RayConfig(horizon=cfg.horizon, dynamic_filter=cfg.dynamic_filter and not cfg.flow,
                            free_space=FreeSpaceConfig() if cfg.free_space else None,
                            beyond_grid=cfg.free_beyond_grid, box_line_of_sight=cfg.box_line_of_sight,
                            free_stretch=cfg.free_stretch)
        self.rays = RayBuilder(index, dataroot, ray_cfg, cache_size=max(RAY_CACHE_FRAMES, 2 * cfg.horizon + 2))

    def __len__(self) -> int:
        return len(self.positions)

    def __getitem__(self, key) -> dict:
        i, step = key
        position = int(self.positions[i])
        sample = self.index[position]
        rng = np.random.default_rng([self.cfg.seed, int(step), int(i)])
        item = {
            "token": sample.token,
            "images": torch.from_numpy(load_sample_images(self.dataroot, sample)),          # uint8 [6, H, W, 3]
            "intrinsics": torch.from_numpy(sample.intrinsics.astype(np.float32)),          # [6, 3, 3]
            "cam2ego": torch.from_numpy(sample.cam2current_ego().astype(np.float32)),      # [6, 4, 4]
        }
        if "rays" in self.data:
            rays = sample_rays(self.rays.rays(position), self.cfg.rays_per_step, rng, self.cfg.ray_sampling)
            free = self._free_rays(position, rng)
            offsets = rays.time_offsets if free is None else np.concatenate([rays.time_offsets, free.time_offsets])
            frames = volume_frames(offsets, self.cfg.flow)
            item.update({
                "ray_origins": torch.from_numpy(rays.origins), "ray_directions": torch.from_numpy(rays.directions),
                "ray_depths": torch.from_numpy(rays.depths), "ray_labels": torch.from_numpy(rays.labels.astype(np.int64)),
                "ray_free_ends": torch.from_numpy(rays.free_ends),
                "ray_volume": torch.from_numpy(self._volume_of(rays.time_offsets, frames)), "num_volumes": len(frames),
            })
            if free is not None:
                item.update({"free_origins": torch.from_numpy(free.origins),
                             "free_directions": torch.from_numpy(free.directions),
                             "free_volume": torch.from_numpy(self._volume_of(free.time_offsets, frames))})
                if self.cfg.free_stretch == "points":
                    item.update(self._near_points(position, free, frames))
            if self.cfg.flow:
                record = self.flow_records.get(sample.token)
                if record is None:
                    raise KeyError(f"no flow record for sample {sample.token}: the flow file is older than the "
                                   f"index; re-run `occflownet prepare --dataroot {self.dataroot}`")
                item["flow"] = flow_moves(record, frames)
        if "depth_points" in self.data:
            points, labels = self._depth_points(position, rng)
            item.update(depth_points=torch.from_numpy(points), depth_labels=torch.from_numpy(labels))
        if "voxel_labels" in self.data:
            occ = load_occupancy(self.dataroot, sample.occupancy_path)
            item["occ_semantics"] = torch.from_numpy(occ.semantics)                       # uint8 [200, 200, 16]
            item["occ_mask"] = torch.from_numpy(occ.mask_camera.astype(bool))
        if self.cfg.bev_flip:                       # drawn last: the other draws stay those of a run without it
            item = BevFlip.draw(rng).apply(item)
        if self.cfg.bev_rotate:                     # after the flip, for the same reason
            item = BevRotation.draw(rng).apply(item)
        if self.cfg.image_aug:                      # after the flip, for the same reason
            images = item["images"]
            item = ImageAug.draw(rng, images.shape[1], images.shape[2], images.shape[0]).apply(item)
        if self.cfg.photometric_aug:                # after the warp, for the same reason
            item = Photometric.draw(rng, item["images"].shape[0]).apply(item)
        if "voxel_labels" in self.data:
            item.update(voxel_targets(item["occ_semantics"], item["occ_mask"] if self.cfg.voxel_mask else None))
        return item

    def _volume_of(self, time_offsets: np.ndarray, frames: list[int]) -> np.ndarray:
        """int64 [R]: the volume (index into ``frames``' copies) that rays of frames ``time_offsets`` render."""
        t = time_offsets.astype(np.int64)
        if self.cfg.flow:  # frames = [0, sorted t ≠ 0]: the position of t in that list, for all rays at once
            keys = np.asarray(frames, dtype=np.int64)
            order = np.argsort(keys)
            return order[np.searchsorted(keys[order], t)]
        return (t != 0).astype(np.int64)

    def _free_rays(self, position: int, rng: np.random.Generator):
        """``free_rays_per_step`` free rays of the keyframe and its neighbours, or None (off / none found)."""
        if "free_rays" not in self.data:
            return None
        free = self.rays.free_rays(position)
        if len(free) == 0:
            return None
        return free.take(rng.choice(len(free), size=self.cfg.free_rays_per_step,
                                    replace=len(free) < self.cfg.free_rays_per_step))

    def _near_points(self, position: int, free, frames: list[int]) -> dict:
        """The voxels the free rays of each of their frames leave out (``free_stretch="points"``): "free_masks" bool
        [T, X, Y, Z] (``RayBuilder.near_points`` of the T frames the free rays come from, in order of t),
        "free_slot" long [F] (the mask of each free ray), "slot_volume" long [T] (the volume each mask applies to,
        as ``free_volume``)."""
        frame_of = dict(self.index.neighbours(position, self.cfg.horizon))
        offsets = sorted(set(int(t) for t in free.time_offsets))
        return {"free_masks": torch.from_numpy(np.stack([self.rays.near_points(position, frame_of[t])
                                                         for t in offsets])),
                "free_slot": torch.from_numpy(np.searchsorted(offsets, free.time_offsets.astype(np.int64))),
                "slot_volume": torch.from_numpy(self._volume_of(np.asarray(offsets, np.int8), frames))}

    def _depth_points(self, position: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The keyframe's LiDAR points (t = 0) that cameras see, for the LSS depth loss and the image semantics:
        (float32 [N, 3] in the current ego frame, uint8 [N] their classes)."""
        frame = self.rays.frame(position)
        _, first = np.unique(frame.point_index, return_index=True)    # a point seen by two cameras counts once
        points = transform_points(invert(self.index.arrays["lidar_ego2global"][position]), frame.points[first])
        inside = GRID.contains(points)
        points, labels = points[inside], frame.labels[first][inside]
        if len(points) > MAX_DEPTH_POINTS:
            pick = rng.choice(len(points), MAX_DEPTH_POINTS, replace=False)
            points, labels = points[pick], labels[pick]
        return points.astype(np.float32), labels.astype(np.uint8)


def collate(items: list[dict]) -> dict:
    """Stack per-sample tensors; concatenate rays with a global volume index (sample-major volume order)."""
    out = {"tokens": [it["token"] for it in items]}
    for key in ("images", "intrinsics", "cam2ego", "occ_semantics", "occ_mask"):
        if key in items[0]:
            out[key] = torch.stack([it[key] for it in items])
    for key in ("depth_points", "depth_labels"):                      # one tensor per sample
        if key in items[0]:
            out[key] = [it[key] for it in items]
    for key in ("voxel_rows", "occupied_rows"):      # rows of each sample's grid → rows of the batch's [B·X·Y·Z]
        if key in items[0]:
            out[key] = torch.cat([it[key] + b * GRID.num_voxels for b, it in enumerate(items)])
    for key in ("voxel_occupied", "voxel_classes", "occupied_labels"):
        if key in items[0]:
            out[key] = torch.cat([it[key] for it in items])
    if "ray_origins" in items[0]:
        offsets = np.cumsum([0] + [it["num_volumes"] for it in items[:-1]])
        for key in ("ray_origins", "ray_directions", "ray_depths", "ray_labels", "ray_free_ends"):
            out[key] = torch.cat([it[key] for it in items])
        out["ray_volume"] = torch.cat([it["ray_volume"] + int(o) for it, o in zip(items, offsets)])
        if any("free_origins" in it for it in items):
            with_free = [(it, o) for it, o in zip(items, offsets) if "free_origins" in it]
            out["free_origins"] = torch.cat([it["free_origins"] for it, _ in with_free])
            out["free_directions"] = torch.cat([it["free_directions"] for it, _ in with_free])
            out["free_volume"] = torch.cat([it["free_volume"] + int(o) for it, o in with_free])
            if "free_masks" in with_free[0][0]:             # (every item with free rays has them, or none)
                slots = np.cumsum([0] + [len(it["free_masks"]) for it, _ in with_free[:-1]])
                out["free_masks"] = torch.cat([it["free_masks"] for it, _ in with_free])
                out["free_slot"] = torch.cat([it["free_slot"] + int(s) for (it, _), s in zip(with_free, slots)])
                out["slot_volume"] = torch.cat([it["slot_volume"] + int(o) for it, o in with_free])
        out["volume_source"] = torch.cat([torch.full((it["num_volumes"],), b, dtype=torch.long)
                                          for b, it in enumerate(items)])
        out["volume_is_temporal"] = torch.cat([torch.arange(it["num_volumes"]) > 0 for it in items])
        if "flow" in items[0]:
            out["flow"] = [(it["flow"], int(o)) for it, o in zip(items, offsets)]
    return out
