"""Rendering supervision: camera rays through labelled LiDAR points (docs/data.md).

For every keyframe each LiDAR point is projected into each of the six cameras; every hit (camera z-depth
≥ ``min_depth``, projection inside the image: 0 ≤ u < W, 0 ≤ v < H) whose point lies inside the occupancy grid of
the *current* ego frame becomes one ray:

- origin    = the camera centre;
- direction = unit vector through the centre of the pixel the point falls in, (floor(u) + 0.5, floor(v) + 0.5);
- depth     = Euclidean distance from the camera centre to the LiDAR point (not the camera z-depth);
- label     = Occ3D class of the point (``occ3d.map_lidarseg`` of its raw lidarseg index).

Because the direction goes through the pixel centre while the depth is the distance to the point itself,
``origin + depth * direction`` misses the point by at most ``depth * θ``, θ being the angle between the ray to the
point and the ray to its pixel centre (≤ ~0.71 px / focal length; see ``pixel_rounding_bound``).

Temporal frames t ∈ [-O, O] of the same scene are moved exactly into the current ego frame (the ego frame at the
current keyframe's LiDAR timestamp, the frame of the Occ3D ground truth):
- points:  current_ego ← global ← ego(t, LiDAR time) ← lidar(t)
- cameras: current_ego ← global ← ego(t, that camera's time) ← camera(t); projection into image t uses the same
  camera pose, so a point is tested against the image it was really seen in.
Per-frame hits are computed in the global frame once and cached; moving them into any current frame is a rigid
transform, which leaves depths unchanged.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, fields

import numpy as np

from occflownet.occ3d import DYNAMIC_FILTER_CLASSES, GRID, map_lidarseg
from occflownet.data.free_space import FreeSpaceConfig, missing_beams
from occflownet.choices import FREE_STRETCH_RULES, RAY_SAMPLINGS
from occflownet.data.free_stretch import free_segment_ends, near_point_voxels, point_clearance_ends
from occflownet.data.line_of_sight import blocked_by_boxes
from occflownet.data.records import EgoBoxes
from occflownet.data.loaders import load_lidar, load_lidarseg
from occflownet.data.tables import DatasetError
from occflownet.geometry import invert, transform_points

EGO_VEHICLE_RAW_LABEL = 31  # nuScenes-lidarseg 'vehicle.ego': returns from the recording car itself
# Bytes of the per-keyframe results a RayBuilder keeps (line-of-sight masks, free-stretch ends, near-point masks,
# most of it the 640 kB near-point masks): on the quickstart's world about 0.75 MB a keyframe at O = 0 and 3 MB at
# O = 3, so every keyframe of a world of about 170 keyframes at O = 0 and of about 40 at O = 3 (the quickstart's and
# the fitting worlds), where samples drawn at random otherwise recompute them at nearly every step (tens of ms a
# keyframe pair).
SIGHT_CACHE_BYTES = 128 * 1024 * 1024


@dataclass(frozen=True)
class RayConfig:
    """How rays are made. The defaults are the paper's / official code's."""

    horizon: int = 3                        # O: temporal frames t ∈ [-O, O] within the scene
    dynamic_filter: bool = True             # drop rays labelled in DYNAMIC_FILTER_CLASSES in frames t ≠ 0
    min_depth: float = 0.05                 # minimum camera z-depth of a hit, metres
    ignored_raw_labels: tuple[int, ...] = (EGO_VEHICLE_RAW_LABEL,)  # lidarseg raw classes that make no ray
    free_space: FreeSpaceConfig | None = None  # also recover free-space beams (data/free_space.py); None: off
    beyond_grid: bool = False               # camera rays to points beyond the grid become free rays (see free_rays)
    box_line_of_sight: bool = False         # drop rays that pass through an object box before their point
                                            # (data/line_of_sight.py; beyond the paper)
    free_stretch: str = "fraction"          # where RayBatch.free_ends puts the end of each ray's free stretch
                                            # (data/free_stretch.py; beyond the paper; "points" also makes the
                                            # free rays leave out the voxels near points, RayBuilder.near_points)

    def __post_init__(self):
        if self.horizon < 0:
            raise ValueError(f"horizon must be >= 0, got {self.horizon}")
        if self.min_depth <= 0:
            raise ValueError(f"min_depth must be > 0, got {self.min_depth}")
        if self.free_stretch not in FREE_STRETCH_RULES:
            raise ValueError(f"free_stretch must be one of {FREE_STRETCH_RULES}, got {self.free_stretch!r}")


@dataclass(frozen=True)
class RayBatch:
    """R rays, all in the current ego frame of one keyframe."""

    origins: np.ndarray       # float32 [R, 3]  camera centre, current ego frame (m)
    directions: np.ndarray    # float32 [R, 3]  unit, through the pixel centre, current ego frame
    depths: np.ndarray        # float32 [R]     distance from the origin to the LiDAR point along the ray (m)
    labels: np.ndarray        # uint8   [R]     Occ3D class 0..16
    time_offsets: np.ndarray  # int8    [R]     t: keyframe offset of the frame the ray comes from (0 = current)
    cameras: np.ndarray       # int8    [R]     camera index in occ3d.CAMERAS order
    pixels: np.ndarray        # float32 [R, 2]  (u, v) pixel centre in that camera's stored image, pixels
    free_ends: np.ndarray     # float32 [R]     end of the free stretch in front of the point, metres along the ray
                              #                 (RayConfig.free_stretch; used by --free-before-point)

    def __len__(self) -> int:
        return len(self.depths)

    def take(self, index) -> "RayBatch":
        """The rays selected by an integer index array or boolean mask."""
        return RayBatch(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    def endpoints(self) -> np.ndarray:
        """float32 [R, 3]: origin + depth · direction (≈ the LiDAR point, current ego frame)."""
        return self.origins + self.depths[:, None] * self.directions

    @staticmethod
    def concatenate(batches: list["RayBatch"]) -> "RayBatch":
        return RayBatch(**{f.name: np.concatenate([getattr(b, f.name) for b in batches]) for f in fields(RayBatch)})


@dataclass(frozen=True)
class CameraHits:
    """Projections of points into cameras: one entry per (point, camera) hit. H hits."""

    point_index: np.ndarray   # int64 [H] index into the projected points
    camera: np.ndarray        # int64 [H] camera index
    uv: np.ndarray            # float64 [H, 2] continuous pixel coordinates of the projection


def project_points(points: np.ndarray, world_to_cams: np.ndarray, intrinsics: np.ndarray,
                   image_sizes: np.ndarray, min_depth: float = 0.05) -> CameraHits:
    """Project points [N, 3] (any frame W) into C cameras.

    world_to_cams: float [C, 4, 4] mapping W into each OpenCV camera frame; intrinsics [C, 3, 3];
    image_sizes [C, 2] (width, height). A hit needs z ≥ min_depth and 0 ≤ u < width, 0 ≤ v < height."""
    points = np.asarray(points, dtype=np.float64)
    idx, cams, uvs = [], [], []
    for c in range(len(world_to_cams)):
        pc = transform_points(world_to_cams[c], points)
        front = np.flatnonzero(pc[:, 2] >= min_depth)
        proj = pc[front] @ np.asarray(intrinsics[c], dtype=np.float64).T
        uv = proj[:, :2] / proj[:, 2:3]
        w, h = image_sizes[c]
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx.append(front[inside])
        cams.append(np.full(int(inside.sum()), c, dtype=np.int64))
        uvs.append(uv[inside])
    return CameraHits(np.concatenate(idx), np.concatenate(cams), np.concatenate(uvs).reshape(-1, 2))


def pixel_centers(uv: np.ndarray) -> np.ndarray:
    """Continuous pixel coordinates [H, 2] → centre of the pixel they fall in: floor(uv) + 0.5."""
    return np.floor(uv) + 0.5


def pixel_rounding_bound(intrinsics: np.ndarray) -> float:
    """Upper bound on the angle (radians) between the ray to a point and the ray through its pixel centre.

    On the normalised image plane (z = 1) the two rays pierce points a, b with |a|, |b| ≥ 1 and
    |a - b| ≤ √2/2 px / f (f the smallest focal length, no skew), so sin θ ≤ |a - b|. The endpoint error of a ray
    of depth d is d · |dir - unit(point)| = 2 d sin(θ/2) ≤ d · θ ≤ d · bound."""
    K = np.asarray(intrinsics, dtype=np.float64).reshape(-1, 3, 3)
    return float(np.arcsin(min(1.0, np.sqrt(0.5) / min(K[:, 0, 0].min(), K[:, 1, 1].min()))))


@dataclass(frozen=True)
class FrameHits:
    """One keyframe's labelled camera hits in the *global* frame (float64), before grid and dynamic filters."""

    points: np.ndarray        # [H, 3] LiDAR point, global
    centers: np.ndarray       # [6, 3] camera centres at each camera's timestamp, global
    directions: np.ndarray    # [H, 3] unit pixel-centre directions, global
    depths: np.ndarray        # [H] distance camera centre → point
    labels: np.ndarray        # uint8 [H] Occ3D class
    cameras: np.ndarray       # int8 [H]
    pixels: np.ndarray        # float32 [H, 2] pixel centres
    point_index: np.ndarray   # int64 [H] index of the point in its sweep
    lidar_origin: np.ndarray  # [3] LiDAR centre, global
    free_directions: np.ndarray  # [F, 3] unit free-space beam directions, global (empty unless configured)


@dataclass(frozen=True)
class FreeRays:
    """F free-space rays, all in the current ego frame of one keyframe: LiDAR firings without a return, and camera
    rays to LiDAR points beyond the grid (``RayConfig.beyond_grid``); the grid is empty along each of them."""

    origins: np.ndarray       # float32 [F, 3]  LiDAR or camera centre of the frame the ray comes from
    directions: np.ndarray    # float32 [F, 3]  unit
    time_offsets: np.ndarray  # int8    [F]     keyframe offset t of that frame

    def __len__(self) -> int:
        return len(self.time_offsets)

    def take(self, index) -> "FreeRays":
        return FreeRays(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


def frame_hits(sample, dataroot, config: RayConfig = RayConfig()) -> FrameHits:
    """Load a SampleRecord's LiDAR + lidarseg and project every labelled point into its six camera images."""
    if sample.lidarseg_path is None:
        raise DatasetError(f"sample {sample.token} (scene {sample.scene_name}) has no lidarseg labels: rays need "
                           f"nuScenes-lidarseg (<version>/lidarseg.json and its label files)")
    sweep = load_lidar(dataroot, sample.lidar.path)
    raw = load_lidarseg(dataroot, sample.lidarseg_path, len(sweep))
    kept = np.flatnonzero(~np.isin(raw, config.ignored_raw_labels))
    lidar2global = sample.lidar.ego2global @ sample.lidar.sensor2ego
    points = transform_points(lidar2global, sweep[kept, :3])
    cam2global = np.stack([c.ego2global @ c.sensor2ego for c in sample.cameras])
    K = sample.intrinsics
    hits = project_points(points, np.stack([invert(T) for T in cam2global]), K, sample.image_sizes,
                          config.min_depth)
    centers_px = pixel_centers(hits.uv)
    rays_cam = np.einsum("hij,hj->hi", np.linalg.inv(K)[hits.camera],
                         np.concatenate([centers_px, np.ones((len(centers_px), 1))], axis=1))
    dirs = np.einsum("hij,hj->hi", cam2global[hits.camera, :3, :3], rays_cam)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hit_points = points[hits.point_index]
    centers = cam2global[:, :3, 3]
    free = np.zeros((0, 3))
    if config.free_space is not None:  # every return counts as "not free", the ego vehicle's own included
        free = missing_beams(sweep, float(sample.lidar.sensor2ego[2, 3]), config.free_space) @ lidar2global[:3, :3].T
    return FrameHits(
        points=hit_points, centers=centers, directions=dirs,
        depths=np.linalg.norm(hit_points - centers[hits.camera], axis=1),
        labels=map_lidarseg(raw[kept][hits.point_index]), cameras=hits.camera.astype(np.int8),
        pixels=centers_px.astype(np.float32), point_index=kept[hits.point_index],
        lidar_origin=lidar2global[:3, 3], free_directions=free,
    )


class RayBuilder:
    """Builds the rays of a keyframe and its temporal neighbours from a SampleIndex (per-frame hits cached)."""

    def __init__(self, index, dataroot, config: RayConfig = RayConfig(), cache_size: int = 16,
                 sight_bytes: int = SIGHT_CACHE_BYTES):
        """``cache_size``: frames whose hits are kept (about 2 MB each for a nuScenes-size sweep); ``sight_bytes``:
        the bytes of line-of-sight masks, free-stretch ends and near-point masks kept, the least recently used
        dropped first (4 entries per keyframe pair, a near-point mask 640 kB)."""
        self.index = index
        self.dataroot = dataroot
        self.config = config
        self.cache_size = cache_size
        self.sight_bytes = sight_bytes
        self._cache: OrderedDict[int, FrameHits] = OrderedDict()
        self._sight: OrderedDict[tuple, tuple[object, int]] = OrderedDict()   # (result, its bytes)
        self._sight_total = 0

    def frame(self, position: int) -> FrameHits:
        """The (cached) global-frame hits of keyframe ``position``."""
        if position in self._cache:
            self._cache.move_to_end(position)
            return self._cache[position]
        hits = frame_hits(self.index[position], self.dataroot, self.config)
        if self.cache_size > 0:
            self._cache[position] = hits
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return hits

    def rays(self, position: int) -> RayBatch:
        """All rays of keyframe ``position`` and its neighbours t ∈ [-O, O] (same scene), current ego frame."""
        to_current = invert(self.index.arrays["lidar_ego2global"][position])
        dynamic = np.asarray(DYNAMIC_FILTER_CLASSES, dtype=np.uint8)
        parts = []
        for t, j in self.index.neighbours(position, self.config.horizon):
            f = self.frame(j)
            points = transform_points(to_current, f.points)
            keep = GRID.contains(points)
            if t != 0 and self.config.dynamic_filter:
                keep &= ~np.isin(f.labels, dynamic)
            keep = np.flatnonzero(keep)
            cams = f.cameras[keep]
            origins = transform_points(to_current, f.centers)[cams]
            directions = f.directions[keep] @ to_current[:3, :3].T
            if self.config.box_line_of_sight:
                seen = self._cached(("rays", position, j), lambda: ~blocked_by_boxes(
                    origins, directions, f.depths[keep], self.sight_boxes(position, j)))
                keep, cams, origins, directions = keep[seen], cams[seen], origins[seen], directions[seen]
            depths = f.depths[keep]
            if self.config.free_stretch == "points":
                free_ends = self._cached(("ends", position, j), lambda: point_clearance_ends(
                    origins, directions, depths, self.near_points(position, j)))
            else:
                free_ends = free_segment_ends(depths)
            parts.append(RayBatch(
                origins=origins.astype(np.float32), directions=directions.astype(np.float32),
                depths=depths.astype(np.float32), labels=f.labels[keep],
                time_offsets=np.full(len(cams), t, dtype=np.int8), cameras=cams, pixels=f.pixels[keep],
                free_ends=free_ends.astype(np.float32),
            ))
        return RayBatch.concatenate(parts)

    def free_rays(self, position: int) -> FreeRays:
        """The free-space rays of keyframe ``position`` and its neighbours t ∈ [-O, O], current ego frame: the
        free-space beams (when ``RayConfig.free_space`` is set) and the beyond-grid rays (when ``beyond_grid``)."""
        to_current = invert(self.index.arrays["lidar_ego2global"][position])
        parts = []
        for t, j in self.index.neighbours(position, self.config.horizon):
            f = self.frame(j)
            origin = transform_points(to_current, f.lidar_origin[None])
            frame_parts = [(np.repeat(origin, len(f.free_directions), 0), f.free_directions @ to_current[:3, :3].T, t)]
            if self.config.beyond_grid:
                frame_parts.append(self._beyond_grid(f, to_current, t))
            if self.config.box_line_of_sight:
                seen = self._cached(("free", position, j), lambda: [
                    ~blocked_by_boxes(o, d, np.full(len(o), np.inf), self.sight_boxes(position, j))
                    for o, d, _ in frame_parts])
                frame_parts = [(o[k], d[k], t) for (o, d, t), k in zip(frame_parts, seen)]
            parts.extend(frame_parts)
        return FreeRays(np.concatenate([o for o, _, _ in parts]).astype(np.float32),
                        np.concatenate([d for _, d, _ in parts]).astype(np.float32),
                        np.concatenate([np.full(len(o), t, dtype=np.int8) for o, _, t in parts]))

    def near_points(self, position: int, j: int) -> np.ndarray:
        """bool [X, Y, Z]: the voxels of the current ego frame of keyframe ``position`` within one voxel of a LiDAR
        point of keyframe ``j`` (``free_stretch.near_point_voxels``; with ``free_stretch="points"`` the free rays
        of frame j leave them out: the tops of trees and vehicles that a ray to a point beyond the grid grazes)."""
        def compute():
            to_current = invert(self.index.arrays["lidar_ego2global"][position])
            return near_point_voxels(transform_points(to_current, self.frame(j).points))
        return self._cached(("near", position, j), compute)

    def _cached(self, key, compute):
        """``compute()``, remembered under ``key`` while the results kept stay within ``sight_bytes`` (line-of-sight
        masks, free-stretch ends and near-point masks are fixed per keyframe pair and cost tens of ms a frame to
        recompute; four kinds of key); the newest result is always kept."""
        if key not in self._sight:
            value = compute()
            size = sum(a.nbytes for a in (value if isinstance(value, list) else [value]))
            self._sight[key] = (value, size)
            self._sight_total += size
            while self._sight_total > self.sight_bytes and len(self._sight) > 1:
                self._sight_total -= self._sight.popitem(last=False)[1][1]
        self._sight.move_to_end(key)
        return self._sight[key][0]

    def sight_boxes(self, position: int, j: int) -> EgoBoxes:
        """The boxes a ray of keyframe ``j`` (rendered for keyframe ``position``) must not pass through, in the
        current ego frame of ``position``: the objects of keyframe ``j`` (the ray's own time) and, for j ≠ position,
        those of ``position`` too (where objects stand in the labels being fitted). Only boxes that reach into the
        grid are kept; a ray is dropped where one of them lies between its origin and its point."""
        ego2global = self.index.arrays["lidar_ego2global"][position]
        boxes = EgoBoxes.concatenate([self.index.boxes(k).in_frame(ego2global) for k in sorted({position, j})])
        reach = np.linalg.norm(boxes.sizes, axis=1)[:, None] / 2.0 + 1.0
        near = np.all((boxes.centers > np.asarray(GRID.lower) - reach)
                      & (boxes.centers < np.asarray(GRID.upper) + reach), axis=1)
        return boxes.take(near)

    @staticmethod
    def _beyond_grid(f: FrameHits, to_current: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Beyond-grid rays of one frame (beyond the paper; docs/data.md): its camera rays whose LiDAR point
        lies outside the grid of the current ego frame, from cameras inside it. The grid is convex, so such a ray
        leaves it before reaching the point and never comes back: every voxel it crosses is free (at time t).
        Training rays end inside the grid (as the official code filters them), so without these the free space in
        front of distant or tall surfaces gets no supervision. → (origins [K, 3], directions [K, 3], t)."""
        centers = transform_points(to_current, f.centers)
        keep = ~GRID.contains(transform_points(to_current, f.points)) & GRID.contains(centers)[f.cameras]
        return centers[f.cameras[keep]], f.directions[keep] @ to_current[:3, :3].T, t

    def visible_point_labels(self, position: int) -> np.ndarray:
        """uint8 [P]: Occ3D labels of the distinct LiDAR points of keyframe ``position`` inside the grid that
        project into at least one camera (what the class counts N_c count; the same hits as the t = 0 rays)."""
        f = self.frame(position)
        inside = GRID.contains(transform_points(invert(self.index.arrays["lidar_ego2global"][position]), f.points))
        _, first = np.unique(f.point_index[inside], return_index=True)
        return f.labels[inside][first]


def endpoint_classes(rays: RayBatch, semantics: np.ndarray) -> np.ndarray:
    """uint8 [R]: class of the voxel of ``semantics`` (uint8 [200, 200, 16], current ego frame, e.g. the Occ3D
    ground truth) that holds each ray's endpoint, 255 where the endpoint lies outside the grid. A check of rays
    against occupancy: on a consistent dataset most rays end in a voxel of their own label."""
    ends = rays.endpoints()
    inside = GRID.contains(ends)
    ijk = GRID.index_of(ends[inside])
    out = np.full(len(rays), 255, dtype=np.uint8)
    out[inside] = semantics[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    return out


def sample_rays(rays: RayBatch, num: int, rng: np.random.Generator, rule: str = "uniform") -> RayBatch:
    """``num`` rays drawn from ``rays`` with ``rng`` (without replacement when there are enough), by ``rule`` of
    :data:`RAY_SAMPLINGS`: "uniform" (the official: every ray alike) or "sqrt-balanced" (beyond the paper, in the
    spirit of RenderOcc's weighted ray sampling): a ray of a class with n_c rays among ``rays`` is drawn with
    probability ∝ 1 / √n_c, so each class's expected share is ∝ √n_c instead of n_c (while a step takes a small part
    of the rays: the draws are without replacement, so a class never gets more than its n_c rays)."""
    if len(rays) == 0:
        raise ValueError("cannot sample rays: the batch is empty (no LiDAR point projects into a camera)")
    if rule not in RAY_SAMPLINGS:
        raise ValueError(f"ray sampling must be one of {RAY_SAMPLINGS}, got {rule!r}")
    replace = len(rays) < num
    if rule == "uniform":
        return rays.take(rng.choice(len(rays), size=num, replace=replace))
    counts = np.bincount(rays.labels, minlength=256).astype(np.float64)
    p = 1.0 / np.sqrt(counts[rays.labels])
    return rays.take(rng.choice(len(rays), size=num, replace=replace, p=p / p.sum()))
