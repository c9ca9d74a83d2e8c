"""Occ3D ground truth from LiDAR by Occ3D's own definition (``occflownet labels``; docs/data.md).

For every keyframe of a nuScenes-format root: accumulate the scene's LiDAR sweeps in the keyframe's ego frame
(points in annotated boxes moved by their boxes), give each voxel the majority class of its points (``semantics``),
walk every beam from its sensor to its return (``mask_lidar``: voxels holding points or passed by beams), and walk a
ray from each camera to each observed voxel (``mask_camera``: what the cameras see of it, up to the first occupied
voxel). ``label_root`` writes ``gts/<scene>/<token>/labels.npz``; the pieces (``load_scene_cloud``,
``label_keyframe``, ``vote``, ``camera_mask``) work on arrays for other callers.

Submodules: ``config`` (LabelConfig), ``tracks`` (boxes in time), ``accumulate`` (the scene's points),
``voxels`` (vote and masks), ``keyframe`` (one keyframe), ``pipeline`` (a whole root: LabelRun), ``npz`` (the file).
"""
from occflownet.labels.config import LabelConfig
from occflownet.labels.npz import write_labels_npz
from occflownet.labels.pipeline import LabelError, LabelReport, LabelRun, label_root

__all__ = ["LabelConfig", "LabelError", "LabelReport", "LabelRun", "label_root", "write_labels_npz"]
