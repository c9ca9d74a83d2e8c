"""One keyframe's Occ3D labels from its scene's accumulated LiDAR (``accumulate``) and its six cameras."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import FREE
from occflownet.data.records import SampleRecord
from occflownet.labels.accumulate import SceneCloud, keyframe_cloud
from occflownet.labels.config import LabelConfig
from occflownet.labels.voxels import beam_free_space, camera_mask, lidar_mask, vote


@dataclass(frozen=True)
class KeyframeLabels:
    """uint8 [X, Y, Z] arrays in the keyframe's ego frame, and what went into them."""

    semantics: np.ndarray     # 0..16, 17 free (also every unobserved voxel)
    mask_lidar: np.ndarray    # 0/1
    mask_camera: np.ndarray   # 0/1, inside mask_lidar
    stats: dict               # points used, moving points, beams, occupied / unlabelled / observed voxels


def window_sweeps(cloud: SceneCloud, keyframe_times: np.ndarray, k: int, window: int | None) -> np.ndarray:
    """bool [S]: the sweeps accumulated for keyframe ``k`` of a scene with keyframe timestamps ``keyframe_times``
    (µs, time order): all of them (window None), else those from keyframe k − window to k + window (clamped to
    the scene), the sweeps between them included."""
    if window is None:
        return np.ones(len(cloud.sweep_time), bool)
    lo = keyframe_times[max(k - window, 0)]
    hi = keyframe_times[min(k + window, len(keyframe_times) - 1)]
    return (cloud.sweep_time >= lo) & (cloud.sweep_time <= hi)


def label_keyframe(cloud: SceneCloud, sample: SampleRecord, sweeps: np.ndarray,
                   config: LabelConfig) -> KeyframeLabels:
    """The labels of ``sample`` (one keyframe of the scene of ``cloud``) from the sweeps ``sweeps`` (bool [S])."""
    grid = config.grid
    points = keyframe_cloud(cloud, sample.ego2global, sample.lidar.timestamp, sweeps)
    voted = vote(points.points, points.label, grid, config.min_points)
    crossed = beam_free_space(points.beam_origin, points.beam_end, grid)
    observed = lidar_mask(voted, crossed)
    seen = camera_mask(observed, voted.occupied, sample.intrinsics, sample.cam2current_ego(), sample.image_sizes,
                       grid)
    occupied = voted.semantics != FREE
    stats = {"points": len(points.label), "occupied": int(occupied.sum()),
             "unlabelled_voxels": int(voted.unlabelled.sum()),
             "mask_lidar": int(observed.sum()), "mask_camera": int(seen.sum()),
             "occupied_in_mask_camera": int((occupied & seen).sum())}
    return KeyframeLabels(voted.semantics, observed.astype(np.uint8), seen.astype(np.uint8), stats)
