"""Statistics of Occ3D labels (any ``labels.npz``: ours, real Occ3D, the synthetic world's), and the agreement of
labels with a geometric truth. ``benchmarks/studies/labels_stats.py`` prints them side by side (docs/data.md)."""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import DRIVEABLE_SURFACE, FREE, TERRAIN

GROUND_CLASSES = tuple(range(DRIVEABLE_SURFACE, TERRAIN + 1))  # driveable surface, other flat, sidewalk, terrain


def label_stats(semantics: np.ndarray, mask_lidar: np.ndarray, mask_camera: np.ndarray) -> dict:
    """Figures of one keyframe's labels (uint8 [X, Y, Z] each): the voxels in mask_camera and their share of the
    grid, those outside mask_lidar, occupied and free voxels inside mask_camera, the share of occupied voxels that
    lie inside it, the columns holding a ground-class voxel, and the free voxels of mask_camera per layer."""
    occupied = semantics != FREE
    lidar, camera = mask_lidar.astype(bool), mask_camera.astype(bool)
    ground = np.isin(semantics, GROUND_CLASSES).any(axis=2)
    return {"mask_camera": int(camera.sum()), "mask_camera_share": float(camera.mean()),
            "mask_camera_outside_lidar": int((camera & ~lidar).sum()),
            "occupied_in_camera": int((occupied & camera).sum()), "free_in_camera": int((~occupied & camera).sum()),
            "occupied": int(occupied.sum()),
            "occupied_share_in_camera": float((occupied & camera).sum() / max(int(occupied.sum()), 1)),
            "ground_columns": int(ground.sum()), "columns": int(ground.size),
            "free_in_camera_by_layer": (~occupied & camera).sum(axis=(0, 1)).tolist()}


def truth_agreement(semantics: np.ndarray, mask_camera: np.ndarray, truth: np.ndarray) -> dict:
    """Labels against a geometric truth (uint8 [X, Y, Z], 17 free), inside the labels' own mask_camera: precision of
    the occupied voxels (share also occupied in the truth), class agreement on those, and the share of the truth's
    occupied voxels in the mask that the labels found."""
    camera = mask_camera.astype(bool)
    mine, theirs = (semantics != FREE) & camera, (truth != FREE) & camera
    both = mine & theirs
    return {"occupied": int(mine.sum()), "true_positive": int(both.sum()),
            "precision": float(both.sum() / max(int(mine.sum()), 1)),
            "class_agreement": float((semantics[both] == truth[both]).mean()) if both.any() else float("nan"),
            "recall": float(both.sum() / max(int(theirs.sum()), 1))}


def mean_stats(rows: list[dict]) -> dict:
    """Element-wise mean of ``label_stats`` (or ``truth_agreement``) dictionaries; lists averaged per entry."""
    out = {}
    for key in rows[0]:
        values = [r[key] for r in rows]
        out[key] = np.mean(values, axis=0).tolist() if isinstance(values[0], list) else float(np.mean(values))
    return out
