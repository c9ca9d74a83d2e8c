"""Evaluation metrics, numpy only (no torch): Occ3D mIoU, RayIoU (CPU), and their reports.

- ``OccupancyMetric`` / ``confusion_matrix`` / ``summarize_confusion``: Occ3D-nuScenes mIoU like the official
  ``Metric_mIoU`` (camera-mask and all-voxel variants, static/dynamic means).
- ``RayIoUMetric`` / ``ray_iou`` / ``first_hits`` / ``scene_ray_origins`` / ``lidar_ray_directions``: SparseOcc's
  RayIoU with an exact voxel traversal in numpy.
- ``format_table`` / ``to_json_ready`` / ``dumps_json``: a per-class table and strict JSON.

See docs/eval.md for the definitions and the deviations from the reference code.
"""
from occflownet.eval.metrics import (IGNORE, OccupancyMetric, check_labels, check_mask, confusion_matrix,
                                     iou_from_confusion, nanmean, summarize_confusion)
from occflownet.eval.ray_iou import (THRESHOLDS_M, RayIoUMetric, first_hits, lidar_ray_directions, ray_iou,
                                     scene_ray_origins)
from occflownet.eval.report import dumps_json, format_table, to_json_ready

__all__ = [
    "IGNORE", "OccupancyMetric", "check_labels", "check_mask", "confusion_matrix", "iou_from_confusion", "nanmean",
    "summarize_confusion", "THRESHOLDS_M", "RayIoUMetric", "first_hits", "lidar_ray_directions", "ray_iou",
    "scene_ray_origins", "dumps_json", "format_table", "to_json_ready",
]
