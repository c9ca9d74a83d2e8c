"""The synthetic driving world behind `occflownet synth`: one procedural scene geometry (flat ground with a class
raster + yaw-oriented boxes) ray cast into six camera images and a 32-beam LiDAR (keyframes and the sweeps between
them), written in the exact nuScenes layout and then labelled by the same pipeline a user runs on real recordings
(``occflownet.labels``). See docs/data.md.

Public entry points: ``generate`` / ``SynthConfig`` (write and label a dataset), ``build_world`` / ``WorldConfig`` (scene geometry),
``render_keyframe`` / ``render_sweep`` / ``SensorRig`` (sensors in memory).
Submodules import numpy only at top level; cv2 and tqdm are imported where files are written.
"""
from occflownet.synth.frame import Keyframe, SensorRig, render_keyframe, render_sweep
from occflownet.synth.generate import DEFAULT_VERSION, SynthConfig, SynthResult, generate
from occflownet.synth.layout import WorldConfig, build_world

__all__ = ["generate", "SynthConfig", "SynthResult", "DEFAULT_VERSION", "WorldConfig", "build_world", "render_keyframe",
           "render_sweep", "SensorRig", "Keyframe"]
