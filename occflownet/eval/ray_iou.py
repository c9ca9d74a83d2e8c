"""RayIoU (SparseOcc, Liu et al. 2024, "Fully Sparse 3D Occupancy Prediction") on the CPU, numpy only.

Reference: ``SparseOcc/loaders/ray_metrics.py`` + ``ego_pose_dataset.py`` + the ``dvr`` ray-casting kernel
(CUDA; a C++ copy ships in ``rayiou_metrics/lib/dvr_cpu``). What it does, and what this module reproduces:

1. Ray origins (``scene_ray_origins``): the LiDAR origin of every keyframe of the sample's scene, expressed in
   the current ego frame; origins with |x| >= 39 m or |y| >= 39 m are dropped; more than 8 → 8 picked evenly
   (``round(linspace(0, n - 1, 8))``).
2. Directions (``lidar_ray_directions``): a LiDAR-like pattern, 360 azimuths (1°) × 39 pitch angles
   (-45° … +12.5°), 14,040 rays per origin (the reference's comment says 15,840; its code makes 14,040).
3. For each ray, prediction and ground truth are reduced to occupied (class != 17) / free and traversed voxel by
   voxel (Amanatides–Woo, the kernel's tie-breaking); the first occupied voxel gives the ray's class and its
   distance = where the ray *leaves* that voxel (the kernel's ``d[i]``). No hit → class 17 (free).
4. Rays whose ground truth has no hit are dropped. On the rest, per class c and threshold θ ∈ {1, 2, 4} m:
   ``gt_c`` = rays with gt class c, ``pred_c`` = rays with predicted class c, ``TP`` = both c and
   |d_pred − d_gt| < θ; ``IoU = TP / (gt_c + pred_c − TP)`` (so a class-correct hit at the wrong distance is
   both a FP and a FN; a predicted hit on a ray whose gt has no hit is not counted at all).
   RayIoU@θ = nanmean over the 17 classes, RayIoU = nanmean over the 3 × 17 values.

The traversal is exact (a voxel walk, not sampling): same voxels, same exit distances as the kernel, computed in
float64 from the same float32-rounded voxel-unit endpoints (``RayIoUMetric`` reproduces the reference's
rounding; ``first_hits`` takes exact float64 geometry). Distances are compared in float32 like the reference.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Iterable

import numpy as np

from occflownet.occ3d import CLASS_NAMES, FREE, GRID, NUM_CLASSES, Grid
from occflownet.eval.metrics import check_labels, nanmean
from occflownet.geometry import invert
from occflownet.voxel_walk import walk_rays

THRESHOLDS_M: tuple[float, ...] = (1.0, 2.0, 4.0)
_MAX_ORIGINS = 8
_ORIGIN_XY_LIMIT_M = 39.0


@lru_cache(maxsize=1)
def _lidar_ray_directions() -> np.ndarray:
    pitch_angles = [-(math.pi / 2 - math.atan(k + 1)) for k in range(10)]
    while pitch_angles[-1] < 0.21:  # nuScenes LiDAR vertical field of view ends near +0.21 rad
        pitch_angles.append(pitch_angles[-1] + (pitch_angles[-1] - pitch_angles[-2]))
    rays = []
    for pitch in pitch_angles:
        for azimuth_deg in np.arange(0, 360, 1):
            azimuth = np.deg2rad(azimuth_deg)
            rays.append((np.cos(pitch) * np.cos(azimuth), np.cos(pitch) * np.sin(azimuth), np.sin(pitch)))
    out = np.array(rays, dtype=np.float32)
    out.flags.writeable = False
    return out


def lidar_ray_directions() -> np.ndarray:
    """The reference's ray pattern: unit directions float32 [14040, 3] in the ego frame (x forward, y left,
    z up), pitch-major: 39 pitches (-45°, -26.6°, … then steps of 0.63° up to +12.5°) × 360 azimuths (0°, 1°, …
    counter-clockwise from +x)."""
    return _lidar_ray_directions().copy()


def scene_ray_origins(lidar2ego, ego2global, current: int, max_origins: int = _MAX_ORIGINS,
                      xy_limit_m: float = _ORIGIN_XY_LIMIT_M) -> np.ndarray:
    """Ray origins of one sample, as in SparseOcc's ``EgoPoseDataset``: float64 [K, 3], current ego frame.

    lidar2ego, ego2global: [F, 4, 4] poses (child→parent) of the F keyframes of the sample's scene in time order
    (LiDAR calibration and the ego pose at the LiDAR timestamp); ``current``: index of the evaluated sample.
    Origin of frame f = inv(ego2global[current]) @ ego2global[f] @ lidar2ego[f] @ (0, 0, 0, 1). Origins with
    |x| or |y| >= ``xy_limit_m`` are dropped; of more than ``max_origins``, indices
    round(linspace(0, n - 1, max_origins)) are kept (time order preserved; the current frame may be dropped,
    as in the reference).
    """
    lidar2ego = np.asarray(lidar2ego, dtype=np.float64)
    ego2global = np.asarray(ego2global, dtype=np.float64)
    if lidar2ego.ndim != 3 or lidar2ego.shape[1:] != (4, 4) or ego2global.shape != lidar2ego.shape:
        raise ValueError(f"lidar2ego and ego2global must both be [F, 4, 4]; got {lidar2ego.shape} and "
                         f"{ego2global.shape}")
    if not 0 <= current < len(lidar2ego):
        raise ValueError(f"current={current} is not a frame index (scene has {len(lidar2ego)} frames)")
    ref_from_global = invert(ego2global[current])
    origins = np.stack([(ref_from_global @ ego2global[f] @ lidar2ego[f])[:3, 3] for f in range(len(lidar2ego))])
    origins = origins[(np.abs(origins[:, 0]) < xy_limit_m) & (np.abs(origins[:, 1]) < xy_limit_m)]
    if len(origins) > max_origins:
        origins = origins[np.round(np.linspace(0, len(origins) - 1, max_origins)).astype(np.int64)]
    return origins


# ----------------------------------------------------------------------------------------------------------
# Voxel traversal


def _cast(volume: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference kernel's walk: rays through a class volume uint8 [X, Y, Z] in voxel units.

    origin: float64 [R, 3] in voxel units (0 = the grid's lower corner); direction: float64 [R, 3], unit length
    in voxel units. Returns (class uint8 [R], t float64 [R]): the first voxel whose class is not FREE and the
    ray parameter (voxel units) where the ray leaves it; rays without a hit give (FREE, t where they leave the
    grid), rays that never enter the grid (FREE, inf). Ties go the kernel's way (``ties="last"``).
    """
    walk = walk_rays(volume, origin, direction, empty=FREE, ties="last")
    return walk.code, walk.t


def first_hits(volume, origins, directions, grid: Grid = GRID) -> tuple[np.ndarray, np.ndarray]:
    """First occupied voxel along each ray.

    volume: uint8 [X, Y, Z] class indices (17 = free, anything else occupied), ego frame, ``grid`` layout.
    origins: float [R, 3] or [3] (shared), ego frame, metres. directions: float [R, 3], any non-zero length.
    Returns (class uint8 [R], distance float64 [R] in metres from the origin to where the ray *leaves* the first
    occupied voxel — the reference's convention; a hit face-on at distance s through one voxel of 0.4 m gives
    s + 0.4). Rays without a hit give class 17 and the distance at which they leave the grid (inf if they never
    enter it). Exact voxel traversal: no sampling error, float64 round-off only.
    """
    volume = check_labels("volume", volume)
    if volume.shape != tuple(grid.shape):
        raise ValueError(f"volume: shape {volume.shape} != grid shape {tuple(grid.shape)}")
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions: expected [R, 3], got {directions.shape}")
    origins = np.asarray(origins, dtype=np.float64)
    if origins.shape not in ((3,), directions.shape):
        raise ValueError(f"origins: expected [3] or {list(directions.shape)} like directions, got {origins.shape}")
    origins = np.broadcast_to(origins, directions.shape)
    norm = np.linalg.norm(directions, axis=1, keepdims=True)
    if not np.all(norm > 0) or not np.all(np.isfinite(directions)) or not np.all(np.isfinite(origins)):
        raise ValueError("directions must be finite and non-zero, origins finite")
    origin_vox = (origins - np.asarray(grid.lower)) / grid.voxel_size
    cls, t = _cast(volume, origin_vox, directions / norm)
    return cls, t * grid.voxel_size


# ----------------------------------------------------------------------------------------------------------
# The metric


def _reference_rays(origins: np.ndarray, directions: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-unit ray origins and unit directions [K * M, 3] float64, rounded like the reference.

    The reference builds end points ``origin + direction`` (float64), converts origin and end point to voxel
    units ``(p - lower) / float32(voxel_size)`` and stores both as float32; the kernel then takes the direction
    (end − origin) / |end − origin| in double. Reproducing that rounding makes the traversal of grazing rays
    match the kernel's voxel for voxel.
    """
    lower = np.asarray(grid.lower, dtype=np.float32).astype(np.float64)
    scale = np.float64(np.float32(grid.voxel_size))
    o32 = ((origins - lower) / scale).astype(np.float32).astype(np.float64)  # [K, 3]
    e32 = ((directions[None, :, :] + origins[:, None, :] - lower) / scale).astype(np.float32).astype(np.float64)
    r = e32 - o32[:, None, :]  # [K, M, 3]
    norm = np.sqrt(r[..., 0] * r[..., 0] + r[..., 1] * r[..., 1] + r[..., 2] * r[..., 2])
    unit = r / norm[..., None]
    origin_vox = np.broadcast_to(o32[:, None, :], r.shape)
    return origin_vox.reshape(-1, 3), unit.reshape(-1, 3)


class RayIoUMetric:
    """RayIoU over a split: ``update`` once per sample (its prediction, ground truth and ray origins), then
    ``compute``. Counts are kept per class and threshold; the IoUs are formed at the end, like the reference.

    thresholds: distance tolerances in metres (default 1, 2, 4). directions: float [M, 3] ray directions in the
    ego frame (default ``lidar_ray_directions()``; custom ones are normalised). grid: the voxel grid.
    """

    def __init__(self, thresholds: Iterable[float] = THRESHOLDS_M, directions=None, grid: Grid = GRID):
        self.thresholds = tuple(float(t) for t in thresholds)
        if not self.thresholds or any(not t > 0 for t in self.thresholds):
            raise ValueError(f"thresholds must be positive distances in metres, got {self.thresholds}")
        if directions is None:
            self.directions = lidar_ray_directions().astype(np.float64)
        else:
            d = np.asarray(directions, dtype=np.float64)
            if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0:
                raise ValueError(f"directions: expected [M, 3], got {d.shape}")
            norm = np.linalg.norm(d, axis=1, keepdims=True)
            if not np.all(np.isfinite(d)) or not np.all(norm > 0):
                raise ValueError("directions must be finite and non-zero")
            self.directions = d / norm
        self.grid = grid
        self.gt_count = np.zeros(FREE + 1, dtype=np.int64)  # rays (with a gt hit) whose gt class is c
        self.pred_count = np.zeros(FREE + 1, dtype=np.int64)  # of those, rays whose predicted class is c
        self.tp_count = np.zeros((len(self.thresholds), FREE + 1), dtype=np.int64)
        self.samples = 0
        self.rays_cast = 0

    def update(self, pred, gt, origins) -> None:
        """Add one sample. pred, gt: uint8 [X, Y, Z] class indices 0..17 (17 free) in the sample's ego frame;
        origins: float [K, 3] ray origins in that ego frame, metres (``scene_ray_origins``; K >= 1)."""
        pred = check_labels("pred", pred)
        gt = check_labels("gt", gt)
        for name, vol in (("pred", pred), ("gt", gt)):
            if vol.shape != tuple(self.grid.shape):
                raise ValueError(f"{name}: shape {vol.shape} != grid shape {tuple(self.grid.shape)}")
        origins = np.asarray(origins, dtype=np.float64)
        if origins.ndim != 2 or origins.shape[1] != 3 or len(origins) == 0:
            raise ValueError(f"origins: expected [K, 3] with K >= 1, got {origins.shape}")
        if not np.all(np.isfinite(origins)):
            raise ValueError("origins: not finite")
        origin_vox, direction = _reference_rays(origins, self.directions, self.grid)
        gt_class, gt_t = _cast(gt, origin_vox, direction)
        keep = gt_class != FREE  # the reference evaluates only rays whose ground truth has a hit
        pred_class, pred_t = _cast(pred, origin_vox[keep], direction[keep])
        scale = np.float32(self.grid.voxel_size)  # the reference: float32 distance * float32 voxel size
        self.add_rays(pred_class, pred_t.astype(np.float32) * scale, gt_class[keep],
                      gt_t[keep].astype(np.float32) * scale)
        self.rays_cast += len(direction)
        self.samples += 1

    def add_rays(self, pred_class, pred_distance_m, gt_class, gt_distance_m) -> None:
        """Count rays already cast, all with a ground-truth hit: classes int [N] (pred may be 17 = no hit) and
        first-hit distances [N] in metres (compared in float32, like the reference). ``update`` calls this."""
        pred_class = np.asarray(pred_class).astype(np.int64)
        gt_class = np.asarray(gt_class).astype(np.int64)
        if pred_class.shape != gt_class.shape or pred_class.ndim != 1:
            raise ValueError(f"pred_class {pred_class.shape} and gt_class {gt_class.shape} must be equal [N]")
        if gt_class.size and (gt_class.min() < 0 or gt_class.max() >= FREE):
            raise ValueError("gt_class: every ray must have a ground-truth hit (class 0..16)")
        if pred_class.size and (pred_class.min() < 0 or pred_class.max() > FREE):
            raise ValueError("pred_class: classes must lie in 0..17")
        error = np.abs(np.asarray(pred_distance_m, dtype=np.float32) - np.asarray(gt_distance_m, dtype=np.float32))
        if error.shape != gt_class.shape:
            raise ValueError(f"distances must be [N] like the classes, got {error.shape}")
        n = FREE + 1
        self.gt_count += np.bincount(gt_class, minlength=n)
        self.pred_count += np.bincount(pred_class, minlength=n)
        same = pred_class == gt_class
        for j, threshold in enumerate(self.thresholds):
            self.tp_count[j] += np.bincount(gt_class[same & (error < threshold)], minlength=n)

    def merge(self, other: "RayIoUMetric") -> None:
        """Add another accumulator's counts (same thresholds), e.g. from another worker process."""
        if other.thresholds != self.thresholds:
            raise ValueError(f"cannot merge RayIoU with thresholds {other.thresholds} into {self.thresholds}")
        self.gt_count += other.gt_count
        self.pred_count += other.pred_count
        self.tp_count += other.tp_count
        self.samples += other.samples
        self.rays_cast += other.rays_cast

    def compute(self) -> dict:
        """``{"metric": "rayiou", "samples", "rays_cast", "rays_with_gt_hit", "thresholds_m": [1, 2, 4],
        "rayiou", "rayiou@1", "rayiou@2", "rayiou@4", "iou_per_class": {name: [IoU@1, IoU@2, IoU@4]},
        "gt_rays_per_class": {name: int}}``. IoUs are fractions in [0, 1]; NaN for a class that no kept ray hits in
        either ground truth or prediction (skipped by the means)."""
        if self.samples == 0:
            raise ValueError("RayIoUMetric.compute(): no samples were added")
        tp = self.tp_count.astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = (tp / (self.gt_count + self.pred_count - tp))[:, :NUM_CLASSES]  # [T, 17]
        result = {
            "metric": "rayiou",
            "samples": self.samples,
            "rays_cast": int(self.rays_cast),
            "rays_with_gt_hit": int(self.gt_count.sum()),
            "thresholds_m": list(self.thresholds),
            "rayiou": nanmean(iou),
        }
        for j, threshold in enumerate(self.thresholds):
            result[f"rayiou@{threshold:g}"] = nanmean(iou[j])
        result["iou_per_class"] = {CLASS_NAMES[c]: [float(v) for v in iou[:, c]] for c in range(NUM_CLASSES)}
        result["gt_rays_per_class"] = {CLASS_NAMES[c]: int(self.gt_count[c]) for c in range(NUM_CLASSES)}
        return result


def ray_iou(samples: Iterable[tuple], thresholds: Iterable[float] = THRESHOLDS_M, directions=None,
            grid: Grid = GRID) -> dict:
    """RayIoU of ``(pred uint8 [X, Y, Z], gt uint8 [X, Y, Z], origins float [K, 3])`` samples (ego frame of each
    sample, metres); the dict of ``RayIoUMetric.compute``."""
    metric = RayIoUMetric(thresholds, directions, grid)
    for pred, gt, origins in samples:
        metric.update(pred, gt, origins)
    return metric.compute()
