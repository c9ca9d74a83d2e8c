"""Fog: predicted-occupied voxels inside ``mask_camera``, split by whether any training ray crosses them.

A model trained by rendering learns σ only where rays go. Voxels that no ray of a keyframe and its temporal
neighbours passes through (behind walls, under the ground, above the LiDAR's top beam) get no 2D supervision, and
a 2D model may fill them with "fog" (σ ≥ τ) that a camera-mask mIoU punishes only inside the mask. This metric
counts, over the voxels of ``mask_camera``:

- the labelled occupied fraction and the predicted occupied fraction (σ ≥ τ, i.e. occupancy != free), and their
  ratio (the fog factor; 1 = as many occupied voxels as labelled);
- the same split into *crossed* voxels (some training ray passes through or ends in them: camera rays through the
  LiDAR points of t ∈ [-O, O], as training builds them, walked from the camera centre to the LiDAR point) and
  *never crossed* voxels, with the false positives in each.

Everything is in the ego frame of the evaluated keyframe, voxels indexed [x, y, z].
"""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import FREE, GRID
from occflownet.voxel_walk import traverse

_KEYS = ("voxels", "labelled", "predicted", "false_positive", "true_positive")


def crossed_voxels(origins: np.ndarray, directions: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """bool [200, 200, 16]: voxels that rays (origins/directions [R, 3], unit, ego frame; depths [R] metres)
    pass through or end in, walked exactly (3D DDA) from the origin to ``origin + depth · direction``."""
    return traverse(origins, directions, np.zeros(GRID.shape, bool), t_max=np.asarray(depths, dtype=np.float64))


class FogMetric:
    """Accumulates fog counts over samples (sums, like the mIoU confusion matrix)."""

    def __init__(self):
        self.counts = {part: dict.fromkeys(_KEYS, 0) for part in ("camera_mask", "crossed", "never_crossed")}

    def update(self, occupancy: np.ndarray, semantics: np.ndarray, mask_camera: np.ndarray,
               crossed: np.ndarray) -> None:
        """occupancy (prediction) and semantics (labels) uint8 [200, 200, 16] with 17 = free; mask_camera and
        crossed bool/0-1 arrays of the same shape."""
        for name, a in (("occupancy", occupancy), ("semantics", semantics), ("mask_camera", mask_camera),
                        ("crossed", crossed)):
            if np.shape(a) != GRID.shape:
                raise ValueError(f"fog: {name} must have shape {GRID.shape}, got {np.shape(a)}")
        mask = np.asarray(mask_camera).astype(bool)
        crossed = np.asarray(crossed).astype(bool)
        pred, label = np.asarray(occupancy) != FREE, np.asarray(semantics) != FREE
        for part, region in (("camera_mask", mask), ("crossed", mask & crossed), ("never_crossed", mask & ~crossed)):
            c = self.counts[part]
            c["voxels"] += int(region.sum())
            c["labelled"] += int((label & region).sum())
            c["predicted"] += int((pred & region).sum())
            c["false_positive"] += int((pred & ~label & region).sum())
            c["true_positive"] += int((pred & label & region).sum())

    def compute(self) -> dict:
        """{part: {voxels, labelled, predicted, false_positive, true_positive, labelled_fraction,
        predicted_fraction, fog_factor (predicted / labelled), geometry_iou}} for camera_mask, crossed and
        never_crossed (fractions of the part's voxels), plus crossed_fraction of the camera-mask voxels."""
        out = {}
        for part, c in self.counts.items():
            n, lab, pred, tp = c["voxels"], c["labelled"], c["predicted"], c["true_positive"]
            union = lab + pred - tp
            out[part] = {**c,
                         "labelled_fraction": lab / n if n else None,
                         "predicted_fraction": pred / n if n else None,
                         "fog_factor": pred / lab if lab else None,
                         "geometry_iou": tp / union if union else None}
        n = self.counts["camera_mask"]["voxels"]
        out["crossed_fraction"] = self.counts["crossed"]["voxels"] / n if n else None
        return out
