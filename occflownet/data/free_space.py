"""Free-space beams: LiDAR firings that returned nothing, recovered from the scan itself (beyond the paper).

A spinning LiDAR fires every ring at a fixed azimuth step; a firing without a return says "no surface along this
direction within range". The sweep file keeps only the returns, but each point carries its ring index (the 5th
float of nuScenes ``LIDAR_TOP`` ``.pcd.bin`` files, and of the synthetic LiDAR), so the missing firings can be
recovered per ring:

1. ring elevation = median elevation of the ring's points (LiDAR frame);
2. azimuth bin of each point, ``floor((atan2(y, x) + π) / 2π · azimuth_steps)``; bins without a point are missing;
3. a missing firing is a *free-space beam* only if
   - its ring could not have hit flat ground within range: elevation > -atan(mount height / max_range)
     (a downward beam always meets the road, so its missing return is a dropout, not free space), and
   - it lies in a run of at least ``min_run`` consecutive missing bins of its ring (isolated dropouts: dark or
     specular surfaces, the sensor's own losses, are not taken as free space);
   - the ring has at least ``min_ring_points`` returns (else its elevation is unknown).

Directions are unit vectors in the LiDAR frame through the bin centres at the ring's elevation. What they
supervise: the rendered opacity of the grid along the beam goes to 0 (``occflownet.train.losses.free_space_loss``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FreeSpaceConfig:
    """How missing firings become free-space beams. Defaults: a 32-beam HDL-32E as on the nuScenes car."""

    azimuth_steps: int = 1084        # firings per ring per revolution (HDL-32E at 20 Hz)
    max_range: float = 70.0          # metres: a beam with no return saw nothing closer
    min_run: int = 2                 # consecutive missing firings of a ring needed to call them free space
    min_ring_points: int = 50        # returns a ring needs for its elevation to be estimated

    def __post_init__(self):
        if self.azimuth_steps < 8 or self.max_range <= 0 or self.min_run < 1 or self.min_ring_points < 1:
            raise ValueError(f"FreeSpaceConfig: invalid values {self}")


def _runs_at_least(missing: np.ndarray, length: int) -> np.ndarray:
    """bool [n] → bool [n]: True where ``missing`` is in a circular run of at least ``length`` True values."""
    n = len(missing)
    if length <= 1 or missing.all():
        return missing.copy()
    start = int(np.flatnonzero(~missing)[0])       # rotate so that the sequence starts on a present bin
    rolled = np.roll(missing, -start)
    edges = np.diff(np.concatenate([[0], rolled.astype(np.int8), [0]]))
    begins, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    keep = np.zeros(n, dtype=bool)
    for b, e in zip(begins, ends):
        if e - b >= length:
            keep[b:e] = True
    return np.roll(keep, start)


def missing_beams(sweep: np.ndarray, mount_height: float, config: FreeSpaceConfig = FreeSpaceConfig()) -> np.ndarray:
    """Free-space beam directions float64 [F, 3] (unit, LiDAR frame) of one sweep.

    sweep: float [N, ≥5] points (x, y, z, intensity, ring) in the LiDAR frame, with the LiDAR mounted level;
    mount_height: height of the LiDAR above the ground plane (metres, e.g. the z of lidar2ego).
    """
    sweep = np.asarray(sweep)
    if sweep.ndim != 2 or sweep.shape[1] < 5:
        raise ValueError(f"missing_beams needs points [N, 5] (x, y, z, intensity, ring), got {sweep.shape}")
    if len(sweep) == 0:
        return np.zeros((0, 3))
    xyz = sweep[:, :3].astype(np.float64)
    ring = np.rint(sweep[:, 4]).astype(np.int64)
    elevation = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    steps = config.azimuth_steps
    az_bin = np.floor((np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi) * steps).astype(np.int64) % steps
    lowest_free = -np.arctan2(max(mount_height, 0.0), config.max_range)
    centres = -np.pi + (np.arange(steps) + 0.5) * (2 * np.pi / steps)
    out = []
    for r in np.unique(ring):
        sel = ring == r
        if sel.sum() < config.min_ring_points:
            continue
        el = float(np.median(elevation[sel]))
        if el <= lowest_free:
            continue
        missing = np.ones(steps, dtype=bool)
        missing[az_bin[sel]] = False
        free = _runs_at_least(missing, config.min_run)
        az = centres[free]
        out.append(np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(len(az), np.sin(el))], -1))
    return np.concatenate(out) if out else np.zeros((0, 3))
