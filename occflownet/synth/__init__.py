"""The synthetic driving world behind `occflownet synth`: one procedural scene geometry (flat ground with a class
raster + yaw-oriented boxes) ray cast into six camera images and a 32-beam LiDAR, voxelised into Occ3D ground truth,
and written in the exact nuScenes layout. See docs/synth.md.

Public entry points: ``generate`` (write a dataset), ``build_world`` / ``WorldConfig`` (scene geometry),
``render_keyframe`` / ``SensorRig`` (one keyframe in memory). The visibility masks walk rays with the shared
``occflownet.voxel_walk.traverse``.
Submodules import numpy only at top level; cv2 and tqdm are imported where files are written.
"""
from occflownet.synth.frame import Keyframe, SensorRig, render_keyframe
from occflownet.synth.generate import DEFAULT_VERSION, SynthResult, generate, write_labels_npz
from occflownet.synth.layout import WorldConfig, build_world

__all__ = ["generate", "SynthResult", "DEFAULT_VERSION", "write_labels_npz", "WorldConfig", "build_world",
           "render_keyframe", "SensorRig", "Keyframe"]
