"""Per-class LiDAR point counts N_c and the rendering-loss class weights ω(c) = log(ΣN / N_c).

N_c counts the LiDAR points of Occ3D class c that lie inside the grid and project into at least one camera, at
t = 0 of every keyframe of the chosen split (``RayBuilder.visible_point_labels``: the same hits that make the
t = 0 rays, so counting and training agree). ω is normalised to mean 1 over the classes with N_c > 0.
A class with N_c = 0 gets weight 0: it made no ray in the counted split, so a weight for it is meaningless, and
0 keeps the loss finite if a stray ray of it appears (e.g. when counting on a subset).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from occflownet.data.loaders import load_occupancy
from occflownet.occ3d import NUM_CLASSES


@dataclass(frozen=True)
class ClassStats:
    """What ``prepare`` writes into the index metadata under ``class_stats``."""

    split: str                # the split counted
    num_samples: int          # keyframes counted
    counts: np.ndarray        # int64 [17]: N_c
    weights: np.ndarray       # float32 [17]: ω(c), mean 1 over classes with N_c > 0, 0 where N_c = 0

    def to_dict(self) -> dict:
        return {"split": self.split, "num_samples": self.num_samples, "counts": [int(c) for c in self.counts],
                "weights": [float(w) for w in self.weights],
                "definition": "counts: LiDAR points per Occ3D class inside the grid, projecting into >= 1 camera, "
                              "t=0; weights: log(sum N / N_c) normalised to mean 1 over classes with N_c > 0; "
                              "N_c = 0 -> weight 0"}

    @classmethod
    def from_dict(cls, d: dict) -> "ClassStats":
        counts = np.asarray(d["counts"], dtype=np.int64)
        weights = np.asarray(d["weights"], dtype=np.float32)
        if counts.shape != (NUM_CLASSES,) or weights.shape != (NUM_CLASSES,):
            raise ValueError(f"class_stats must hold {NUM_CLASSES} counts and weights")
        return cls(split=d["split"], num_samples=int(d["num_samples"]), counts=counts, weights=weights)


def class_weights(counts) -> np.ndarray:
    """int [17] counts N_c → float32 [17] weights log(ΣN/N_c), mean 1 over present classes, 0 for absent ones.

    With a single present class every log is 0; that class then gets weight 1."""
    counts = np.asarray(counts, dtype=np.float64)
    if counts.shape != (NUM_CLASSES,) or (counts < 0).any():
        raise ValueError(f"counts must be {NUM_CLASSES} non-negative numbers, got shape {counts.shape}")
    present = counts > 0
    weights = np.zeros(NUM_CLASSES)
    if not present.any():
        raise ValueError("no class has any LiDAR point: cannot compute class weights")
    weights[present] = np.log(counts.sum() / counts[present])
    mean = weights[present].mean()
    weights[present] = weights[present] / mean if mean > 0 else 1.0
    return weights.astype(np.float32)


VOXEL_WEIGHT_CAP = 30.0   # the largest weight voxel_class_weights gives a class (a class of a few voxels stays bounded)


def voxel_class_weights(counts) -> np.ndarray:
    """int [18] voxel counts N_c of the labels (index 17 = free) → float32 [18] weights of the 3D density BCE
    (``--voxel-weighting sqrt-balanced``, beyond the paper): √(N_free / N_c), at least 1 and at most
    :data:`VOXEL_WEIGHT_CAP`; free weighs 1, and so does a class with no voxel (it makes no term)."""
    counts = np.asarray(counts, dtype=np.float64)
    if counts.shape != (NUM_CLASSES + 1,) or (counts < 0).any():
        raise ValueError(f"counts must be {NUM_CLASSES + 1} non-negative numbers (17 = free), got {counts.shape}")
    if counts[NUM_CLASSES] == 0:
        raise ValueError("no free voxel in the counted labels: cannot balance against free space")
    ratio = np.divide(counts[NUM_CLASSES], counts, out=np.ones_like(counts), where=counts > 0)
    return np.clip(np.sqrt(ratio), 1.0, VOXEL_WEIGHT_CAP).astype(np.float32)


def count_voxels(dataroot, index, positions, masked: bool) -> np.ndarray:
    """int64 [18]: voxels per label (17 = free) of the Occ3D labels of keyframes ``positions`` of ``index``, inside
    ``mask_camera`` when ``masked`` (what ``--voxel-mask`` supervises), else every voxel."""
    counts = np.zeros(NUM_CLASSES + 1, dtype=np.int64)
    for position in positions:
        occ = load_occupancy(dataroot, index[int(position)].occupancy_path)
        labels = occ.semantics[occ.mask_camera.astype(bool)] if masked else occ.semantics
        counts += np.bincount(labels.reshape(-1), minlength=NUM_CLASSES + 1)[:NUM_CLASSES + 1]
    return counts


def count_classes(builder, positions, progress: bool = False) -> np.ndarray:
    """int64 [17]: N_c over the keyframes ``positions`` of ``builder.index`` (a RayBuilder)."""
    counts = np.zeros(NUM_CLASSES, dtype=np.int64)
    items = positions
    if progress:
        from tqdm import tqdm
        items = tqdm(positions, desc="class counts", unit="sample", file=sys.stderr)
    for position in items:
        counts += np.bincount(builder.visible_point_labels(int(position)), minlength=NUM_CLASSES)[:NUM_CLASSES]
    return counts


def compute_class_stats(builder, split: str, progress: bool = False) -> ClassStats:
    """Count the classes of ``split`` and derive the weights."""
    positions = builder.index.split_positions(split)
    if len(positions) == 0:
        raise ValueError(f"split {split!r} has no samples to count")
    counts = count_classes(builder, positions, progress)
    return ClassStats(split=split, num_samples=len(positions), counts=counts, weights=class_weights(counts))
