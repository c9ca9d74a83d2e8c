"""A 32-beam spinning LiDAR (HDL-32E-like, as on the nuScenes car) by ray casting the world's geometry.

Rays form a [beams, azimuth steps] array in the LiDAR frame; a sweep is taken at one instant (no motion
distortion). Each return becomes a point (x, y, z, intensity, ring) in the *LiDAR frame* with its raw
nuScenes-lidarseg index. The LiDAR must be mounted level (its z axis = global z), as in ``default_lidar2ego``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.geometry import make_transform, rotation_z
from occflownet.synth.materials import GROUND_RAW, GROUND_REFLECTIVITY, PAINT_NONE
from occflownet.synth.raycast import Block, box_faces, boxes_in_range, cast_blocks, ground_t
from occflownet.synth.world import Boxes, World


@dataclass(frozen=True)
class LidarSpec:
    """Beam layout and range. Elevations are spread evenly over ``elevation_deg`` (HDL-32E: -30.67° .. 10.67°)."""

    beams: int = 32
    elevation_deg: tuple[float, float] = (-30.67, 10.67)
    azimuth_steps: int = 1084
    max_range: float = 70.0
    range_noise: float = 0.0  # std of Gaussian range noise [m]
    dropout: float = 0.01  # fraction of returns randomly lost

    def elevations(self) -> np.ndarray:
        """Beam elevations [beams] in radians, ascending (ring index = beam index)."""
        return np.radians(np.linspace(self.elevation_deg[0], self.elevation_deg[1], self.beams))

    def azimuths(self) -> np.ndarray:
        """Column azimuths [azimuth_steps] in radians in the LiDAR frame, ascending in (-pi, pi)."""
        return -np.pi + (np.arange(self.azimuth_steps) + 0.5) * (2 * np.pi / self.azimuth_steps)

    def directions(self) -> np.ndarray:
        """Unit ray directions [beams, azimuth_steps, 3] in the LiDAR frame."""
        el, az = np.meshgrid(self.elevations(), self.azimuths(), indexing="ij")
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def default_lidar2ego() -> np.ndarray:
    """LIDAR_TOP mounting like nuScenes: at (0.94, 0, 1.84) m, rotated -90° about z (LiDAR x = ego -y)."""
    return make_transform(rotation_z(-np.pi / 2)[:3, :3], (0.94, 0.0, 1.84))


@dataclass
class LidarScan:
    """One sweep. ``points`` float32 [N, 5] (x, y, z, intensity 0..255, ring) in the LiDAR frame; ``raw`` uint8 [N]
    raw lidarseg index; ``box`` int32 [N] index into the frame's ``Boxes`` (-1: ground); ``instance`` int32 [N]
    agent index (-1: none)."""

    points: np.ndarray
    raw: np.ndarray
    box: np.ndarray
    instance: np.ndarray


def lidar_blocks(boxes: Boxes, lidar2global: np.ndarray, spec: LidarSpec) -> list[Block]:
    """For each box in range, the beams × azimuth columns that may hit it (two blocks when wrapping past ±pi)."""
    origin = lidar2global[:3, 3]
    idx = boxes_in_range(boxes, origin, spec.max_range)
    yaw_l = np.arctan2(lidar2global[1, 0], lidar2global[0, 0])
    el = spec.elevations()
    step = 2 * np.pi / spec.azimuth_steps
    blocks = []
    for i in idx:
        c, s = np.cos(boxes.yaw[i]), np.sin(boxes.yaw[i])
        o = origin - boxes.center[i]
        ol = np.array([c * o[0] + s * o[1], -s * o[0] + c * o[1]])
        hx, hy, hz = boxes.half[i]
        r_min = np.hypot(max(abs(ol[0]) - hx, 0.0), max(abs(ol[1]) - hy, 0.0))
        r_max = np.hypot(abs(ol[0]) + hx, abs(ol[1]) + hy)
        dz_top, dz_bot = boxes.center[i, 2] + hz - origin[2], boxes.center[i, 2] - hz - origin[2]
        e_hi = np.arctan2(dz_top, r_min if dz_top > 0 else r_max)
        e_lo = np.arctan2(dz_bot, r_min if dz_bot < 0 else r_max)
        rows = np.nonzero((el >= e_lo - 1e-6) & (el <= e_hi + 1e-6))[0]
        if len(rows) == 0:
            continue
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        if r_min < 1e-6:
            blocks.append(Block(int(i), r0, r1, 0, spec.azimuth_steps))
            continue
        corners = boxes.subset([i]).corners()[0, ::2, :2] - origin[:2]  # the 4 footprint corners
        a_c = np.arctan2(-o[1], -o[0])
        rel = np.angle(np.exp(1j * (np.arctan2(corners[:, 1], corners[:, 0]) - a_c)))
        lo = a_c + rel.min() - yaw_l + np.pi
        hi = a_c + rel.max() - yaw_l + np.pi
        c0, c1 = int(np.floor(lo / step - 0.5)) - 1, int(np.ceil(hi / step - 0.5)) + 2
        c0_mod = c0 % spec.azimuth_steps
        width = min(c1 - c0, spec.azimuth_steps)
        if c0_mod + width <= spec.azimuth_steps:
            blocks.append(Block(int(i), r0, r1, c0_mod, c0_mod + width))
        else:
            blocks.append(Block(int(i), r0, r1, c0_mod, spec.azimuth_steps))
            blocks.append(Block(int(i), r0, r1, 0, c0_mod + width - spec.azimuth_steps))
    return blocks


def cast_lidar(world: World, boxes: Boxes, lidar2global: np.ndarray, spec: LidarSpec = LidarSpec(),
               rng: np.random.Generator | None = None) -> LidarScan:
    """One sweep of the LiDAR at pose ``lidar2global`` [4, 4] against ``boxes`` (global frame, this instant)."""
    lidar2global = np.asarray(lidar2global, dtype=np.float64)
    if abs(lidar2global[2, 2] - 1.0) > 1e-6:
        raise ValueError("cast_lidar: the LiDAR must be mounted level (z axis along global z)")
    origin = lidar2global[:3, 3]
    dirs_l = spec.directions()
    dirs = dirs_l @ lidar2global[:3, :3].T
    t_buf = np.full(dirs.shape[:2], np.inf)
    id_buf = np.full(dirs.shape[:2], -1, np.int32)
    cast_blocks(origin, dirs, boxes, lidar_blocks(boxes, lidar2global, spec), t_buf, id_buf)
    tg = ground_t(origin, dirs)
    ground = tg < t_buf
    t_buf[ground], id_buf[ground] = tg[ground], -1
    hit = t_buf <= spec.max_range
    if rng is not None and spec.dropout > 0:
        hit &= rng.random(hit.shape) >= spec.dropout
    rows, cols = np.nonzero(hit)
    t = t_buf[rows, cols]
    if rng is not None and spec.range_noise > 0:
        t = t + rng.normal(0.0, spec.range_noise, t.shape)
    ids = id_buf[rows, cols]
    d_g = dirs[rows, cols]
    p_g = origin + t[:, None] * d_g
    raw = np.zeros(len(t), np.uint8)
    refl = np.zeros(len(t), np.float32)
    cos_inc = np.zeros(len(t), np.float32)
    gb = ids < 0
    cls, paint = world.ground_lookup_global(p_g[gb, :2])
    raw[gb] = GROUND_RAW[cls]
    refl[gb] = np.where(paint != PAINT_NONE, 0.9, GROUND_REFLECTIVITY[cls])
    cos_inc[gb] = np.abs(d_g[gb, 2])
    bb = ~gb
    raw[bb] = boxes.raw[ids[bb]]
    refl[bb] = boxes.reflectivity[ids[bb]]
    normal, _, _ = box_faces(boxes, ids[bb], p_g[bb])
    cos_inc[bb] = np.abs(np.sum(normal * d_g[bb], axis=1))
    intensity = np.round(np.clip(255.0 * refl * (0.25 + 0.75 * cos_inc) / (1.0 + (t / 60.0) ** 2), 0, 255))
    points = np.empty((len(t), 5), np.float32)
    points[:, :3] = t[:, None] * dirs_l[rows, cols]
    points[:, 3] = intensity
    points[:, 4] = rows
    instance = np.where(ids >= 0, boxes.instance[np.maximum(ids, 0)], -1).astype(np.int32)
    return LidarScan(points=points, raw=raw, box=ids, instance=instance)
