"""One keyframe of a synthetic scene, in memory: six images, a LiDAR sweep, the geometric truth, poses, times; and
the LiDAR sweeps between keyframes.

``render_keyframe(world, frame_index, rig, t0_us, seed)`` is what ``generate`` writes to disk and what tests use to
check consistency (it keeps per-camera z-depth, class and box buffers that are not written); ``render_sweep`` is one
LiDAR sweep at any time (nuScenes records 20 Hz sweeps between its 2 Hz keyframes).
Times: the keyframe (sample) time is the LiDAR's; each camera fires at a small fixed offset from it (like the
nuScenes rig, whose cameras trigger as the LiDAR sweeps past them), and every sensor record gets the ego pose at
its own time. The world's geometry is taken at each sensor's own time.

The benchmark labels (``gts/``) are not made here: ``generate`` runs the label pipeline (``occflownet.labels``) on
the sensors it wrote, as a user would on real recordings. ``Keyframe.truth`` is the world's geometry voxelised
(every surface, ``voxelize``), kept only to check that pipeline.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occflownet.occ3d import CAMERAS
from occflownet.contract import calibration_arrays
from occflownet.rig import default_rig
from occflownet.synth.camera import CameraRender, render_camera
from occflownet.synth.layout import KEYFRAME_INTERVAL_S
from occflownet.synth.lidar import LidarScan, LidarSpec, cast_lidar, default_lidar2ego
from occflownet.synth.voxelize import voxelize
from occflownet.synth.world import Boxes, World

# Camera trigger time relative to the LiDAR keyframe [µs], camera order.
CAMERA_OFFSETS_US = (2000, 10000, -10000, 35000, -27000, 27000)


@dataclass(frozen=True)
class SensorRig:
    """Cameras (intrinsics [6, 3, 3] for width × height, cam2ego [6, 4, 4]), LiDAR mounting and beam layout."""

    width: int
    height: int
    intrinsics: np.ndarray
    cam2ego: np.ndarray
    lidar2ego: np.ndarray = field(default_factory=default_lidar2ego)
    lidar: LidarSpec = LidarSpec()
    camera_offsets_us: tuple[int, ...] = CAMERA_OFFSETS_US

    @staticmethod
    def default(width: int = 480, height: int = 270, **kwargs) -> "SensorRig":
        K, T = calibration_arrays(default_rig(width, height))
        return SensorRig(width, height, K.astype(np.float64), T.astype(np.float64), **kwargs)


@dataclass
class Keyframe:
    """Everything about one keyframe. Poses are ego→global [4, 4] at each sensor's time; ``truth`` uint8
    [200, 200, 16] (17 free) the geometry voxelised in the ego frame at ``lidar_time_us``; ``boxes`` the geometry at
    the LiDAR time (global)."""

    frame_index: int
    scene_time: float  # seconds since the scene's first keyframe, at the LiDAR time
    lidar_time_us: int
    camera_times_us: list[int]
    lidar_ego2global: np.ndarray
    camera_ego2global: list[np.ndarray]
    cameras: list[CameraRender]
    scan: LidarScan
    truth: np.ndarray
    boxes: Boxes


def keyframe_time_us(t0_us: int, frame_index: int) -> int:
    return int(t0_us + round(frame_index * KEYFRAME_INTERVAL_S * 1e6))


def render_keyframe(world: World, frame_index: int, rig: SensorRig, t0_us: int, seed: int,
                    scene_index: int = 0) -> Keyframe:
    """Render cameras, LiDAR and ground truth of keyframe ``frame_index`` (deterministic for the arguments)."""
    rng = np.random.default_rng([int(seed), int(scene_index), int(frame_index), 1])
    lidar_us = keyframe_time_us(t0_us, frame_index)
    t_lidar = (lidar_us - t0_us) * 1e-6
    ego_lidar = world.ego2global(t_lidar)
    boxes = world.boxes_at(t_lidar)
    scan = cast_lidar(world, boxes, ego_lidar @ rig.lidar2ego, rig.lidar, rng)

    cam_times, cam_poses, renders = [], [], []
    for c, name in enumerate(CAMERAS):
        us = lidar_us + int(rig.camera_offsets_us[c])
        t = (us - t0_us) * 1e-6
        pose = world.ego2global(t)
        renders.append(render_camera(world, world.boxes_at(t), rig.intrinsics[c], pose @ rig.cam2ego[c],
                                     rig.width, rig.height, rng))
        cam_times.append(us)
        cam_poses.append(pose)

    truth = voxelize(world, boxes, ego_lidar)
    return Keyframe(frame_index, t_lidar, lidar_us, cam_times, ego_lidar, cam_poses, renders, scan, truth, boxes)


def sweep_times_us(t0_us: int, frame_index: int, sweeps: int) -> list[int]:
    """The times of the ``sweeps`` LiDAR sweeps evenly between keyframes ``frame_index`` and ``frame_index + 1``."""
    start = keyframe_time_us(t0_us, frame_index)
    step = (keyframe_time_us(t0_us, frame_index + 1) - start) / (sweeps + 1)
    return [int(start + round(j * step)) for j in range(1, sweeps + 1)]


def render_sweep(world: World, time_us: int, rig: SensorRig, t0_us: int, seed: int, scene_index: int = 0
                 ) -> tuple[LidarScan, np.ndarray]:
    """One LiDAR sweep at ``time_us`` (not a keyframe): (scan, ego2global [4, 4] at that time). Deterministic."""
    rng = np.random.default_rng([int(seed), int(scene_index), int(time_us - t0_us), 2])
    t = (time_us - t0_us) * 1e-6
    ego = world.ego2global(t)
    return cast_lidar(world, world.boxes_at(t), ego @ rig.lidar2ego, rig.lidar, rng), ego
