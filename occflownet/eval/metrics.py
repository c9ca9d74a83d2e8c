"""Occ3D-nuScenes semantic occupancy mIoU, accumulated like the official ``Metric_mIoU``.

The official code (Occ3D / CVPR 2023 occupancy challenge, ``occ_metrics.py``) keeps one 18×18 confusion matrix
``hist[gt, pred]`` = ``np.bincount(18 * gt + pred)`` over the evaluated voxels, summed over the whole split, and
reports ``IoU_c = hist[c, c] / (hist[c, :].sum() + hist[:, c].sum() - hist[c, c])`` and
``mIoU = nanmean(IoU_0..16)`` (class 17, free, excluded; a class absent from both prediction and ground truth
has 0/0 = NaN and is skipped by the mean). Ground-truth voxels with a label outside 0..17 (255, "ignore") are
left out, as in ``hist_info``. The camera-mask variant keeps only voxels where ``mask_camera`` is set.

This module is numpy only. Volumes are ``[X, Y, Z] = [200, 200, 16]`` class indices in the ego frame of the
sample (Occ3D layout, see ``occflownet.occ3d``).
"""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import CLASS_NAMES, DYNAMIC_CLASSES, FREE, NUM_CLASSES, STATIC_CLASSES

NUM_LABELS = FREE + 1  # 18: classes 0..16 and free
IGNORE = 255  # ground-truth label left out of the confusion matrix (official ``hist_info``: gt outside [0, 18))


def check_labels(name: str, labels, allow_ignore: bool = False) -> np.ndarray:
    """Validate a semantic volume of class indices and return it as uint8 (no copy when already uint8).

    ``labels``: integer array, values 0..17 (17 = free); with ``allow_ignore`` also 255 (left out of the
    metric). Raises ``ValueError`` naming ``name`` for float/bool dtypes or out-of-range values.
    """
    arr = np.asarray(labels)
    if arr.dtype == np.bool_ or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: expected integer class indices (uint8), got dtype {arr.dtype}")
    if arr.size == 0:
        raise ValueError(f"{name}: empty volume")
    if arr.dtype == np.uint8:
        counts = np.bincount(arr.ravel(), minlength=256)
        bad = np.flatnonzero(counts[NUM_LABELS:])
        bad = bad + NUM_LABELS
        if allow_ignore:
            bad = bad[bad != IGNORE]
        if bad.size:
            raise ValueError(f"{name}: class indices must lie in 0..{FREE}"
                             f"{' or be 255 (ignore)' if allow_ignore else ''}; found {bad[:8].tolist()}")
        return arr
    if int(arr.min()) < 0 or int(arr.max()) > FREE:
        bad_mask = (arr < 0) | (arr > FREE)
        if allow_ignore:
            bad_mask &= arr != IGNORE
        if bad_mask.any():
            raise ValueError(f"{name}: class indices must lie in 0..{FREE}"
                             f"{' or be 255 (ignore)' if allow_ignore else ''}; "
                             f"found {np.unique(arr[bad_mask])[:8].tolist()}")
    return arr.astype(np.uint8)


def check_mask(name: str, mask, shape: tuple[int, ...]) -> np.ndarray:
    """Validate a visibility mask and return it as bool.

    Accepted: bool, or integers/floats whose values are all in {0, 1} or all in {0, 255} (Occ3D stores 0/1
    uint8; 0/255 is what image-style masks use). Anything else (e.g. 0/1/2) raises ``ValueError``: silently
    treating every non-zero value as visible would hide a wrong file.
    """
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise ValueError(f"{name}: shape {m.shape} does not match the volume shape {tuple(shape)}")
    if m.dtype == np.bool_:
        return m
    if not (np.issubdtype(m.dtype, np.integer) or np.issubdtype(m.dtype, np.floating)):
        raise ValueError(f"{name}: expected a bool or 0/1 integer mask, got dtype {m.dtype}")
    if m.dtype == np.uint8:
        present = np.flatnonzero(np.bincount(m.ravel(), minlength=256))
    else:
        present = np.unique(m)
    nonzero = set(present.tolist()) - {0}
    if not (nonzero <= {1} or nonzero <= {255}):
        raise ValueError(f"{name}: mask values must be 0/1 or 0/255 (or bool); found {sorted(nonzero)[:8]}")
    return m != 0


def _pair_index(pred, gt) -> tuple[np.ndarray, np.ndarray | None]:
    """Validated ``18 * gt + pred`` as int16 [X*Y*Z] and the voxels to count (None = all; gt 255 left out)."""
    pred = check_labels("pred", pred)
    gt = check_labels("gt", gt, allow_ignore=True)
    if pred.shape != gt.shape:
        raise ValueError(f"pred shape {pred.shape} != gt shape {gt.shape}")
    index = (gt.astype(np.int16) * NUM_LABELS + pred).ravel()
    valid = index < NUM_LABELS * NUM_LABELS  # gt == 255 gives >= 255 * 18: left out like the reference
    return index, (None if valid.all() else valid)


def _bincount(index: np.ndarray) -> np.ndarray:
    size = NUM_LABELS * NUM_LABELS
    return np.bincount(index, minlength=size).reshape(NUM_LABELS, NUM_LABELS).astype(np.int64)


def confusion_matrix(pred, gt, mask=None) -> np.ndarray:
    """One sample's confusion matrix ``hist[gt, pred]``, int64 [18, 18].

    pred, gt: uint8 [X, Y, Z] class indices (gt may hold 255 = ignore). mask: optional [X, Y, Z] (bool, 0/1 or
    0/255); only voxels where it is set are counted.
    """
    index, valid = _pair_index(pred, gt)
    keep = valid
    if mask is not None:
        m = check_mask("mask_camera", mask, np.shape(gt)).ravel()
        keep = m if valid is None else m & valid
    return _bincount(index if keep is None else index[keep])


def iou_from_confusion(hist: np.ndarray) -> np.ndarray:
    """Per-class IoU float64 [18] from ``hist[gt, pred]``: TP / (TP + FP + FN); NaN where the class is absent
    from both prediction and ground truth (0/0)."""
    hist = np.asarray(hist, dtype=np.float64)
    tp = np.diag(hist)
    denom = hist.sum(0) + hist.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return tp / denom


def nanmean(values) -> float:
    """Mean of the non-NaN values as a Python float; NaN when all are NaN (no warning, unlike np.nanmean)."""
    values = np.asarray(values, dtype=np.float64)
    finite = ~np.isnan(values)
    return float(values[finite].mean()) if finite.any() else float("nan")


def summarize_confusion(hist: np.ndarray) -> dict:
    """Scores of one accumulated confusion matrix ``hist[gt, pred]`` int [18, 18].

    Returns ``{"miou", "miou_static", "miou_dynamic", "geometry_iou", "iou_per_class": {name: IoU} (17 classes),
    "voxels", "confusion": [[int]*18]*18}``; IoUs are fractions in [0, 1] or NaN (class absent from both).
    ``geometry_iou`` is the occupied-vs-free IoU (any class 0..16 counts as occupied).
    """
    hist = np.asarray(hist, dtype=np.int64)
    iou = iou_from_confusion(hist)[:NUM_CLASSES]
    occupied_tp = hist[:FREE, :FREE].sum()
    occupied_fp = hist[FREE, :FREE].sum()
    occupied_fn = hist[:FREE, FREE].sum()
    occupied_denom = occupied_tp + occupied_fp + occupied_fn
    return {
        "miou": nanmean(iou),
        "miou_static": nanmean(iou[list(STATIC_CLASSES)]),
        "miou_dynamic": nanmean(iou[list(DYNAMIC_CLASSES)]),
        "geometry_iou": float(occupied_tp / occupied_denom) if occupied_denom else float("nan"),
        "iou_per_class": {CLASS_NAMES[c]: float(iou[c]) for c in range(NUM_CLASSES)},
        "voxels": int(hist.sum()),
        "confusion": hist.tolist(),
    }


class OccupancyMetric:
    """Occ3D mIoU over a split: call ``update`` once per sample, then ``compute``.

    Accumulates two confusion matrices: over voxels where ``mask_camera`` is set (the Occ3D benchmark
    number) and over all voxels. Either every sample comes with a mask or none does (mixing raises).
    """

    def __init__(self):
        self.hist_camera = np.zeros((NUM_LABELS, NUM_LABELS), dtype=np.int64)
        self.hist_all = np.zeros((NUM_LABELS, NUM_LABELS), dtype=np.int64)
        self.samples = 0
        self.samples_with_mask = 0

    def update(self, pred, gt, mask_camera=None) -> None:
        """Add one sample. pred, gt: uint8 [X, Y, Z] class indices 0..17 (gt may hold 255 = ignore), ego frame
        of the sample; mask_camera: optional [X, Y, Z] bool, 0/1 or 0/255."""
        has_mask = mask_camera is not None
        if self.samples and has_mask != (self.samples_with_mask == self.samples):
            raise ValueError("mask_camera given for some samples and not for others; pass it for every sample "
                             "or for none")
        index, valid = _pair_index(pred, gt)
        self.hist_all += _bincount(index if valid is None else index[valid])
        if has_mask:
            mask = check_mask("mask_camera", mask_camera, np.shape(gt)).ravel()
            self.hist_camera += _bincount(index[mask if valid is None else mask & valid])
            self.samples_with_mask += 1
        self.samples += 1

    def merge(self, other: "OccupancyMetric") -> None:
        """Add another accumulator's counts (e.g. from another worker process)."""
        if self.samples and other.samples and \
                (self.samples_with_mask == self.samples) != (other.samples_with_mask == other.samples):
            raise ValueError("cannot merge a metric with camera masks into one without")
        self.hist_camera += other.hist_camera
        self.hist_all += other.hist_all
        self.samples += other.samples
        self.samples_with_mask += other.samples_with_mask

    def compute(self) -> dict:
        """``{"metric": "occ3d_miou", "samples": n, "camera_mask": summary or None (no masks given),
        "all_voxels": summary}`` with summaries as in ``summarize_confusion``. Raises if no sample was added."""
        if self.samples == 0:
            raise ValueError("OccupancyMetric.compute(): no samples were added")
        return {
            "metric": "occ3d_miou",
            "samples": self.samples,
            "camera_mask": summarize_confusion(self.hist_camera) if self.samples_with_mask else None,
            "all_voxels": summarize_confusion(self.hist_all),
        }
