"""One keyframe of a synthetic scene, in memory: six images, a LiDAR sweep, Occ3D ground truth, poses, times.

``render_keyframe(world, frame_index, rig, t0_us, seed)`` is what ``generate`` writes to disk and what tests use to
check consistency (it keeps per-camera z-depth, class and box buffers that are not written).
Times: the keyframe (sample) time is the LiDAR's; each camera fires at a small fixed offset from it (like the
nuScenes rig, whose cameras trigger as the LiDAR sweeps past them), and every sensor record gets the ego pose at
its own time. The world's geometry is taken at each sensor's own time.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occflownet.occ3d import CAMERAS, FREE, GRID, Grid
from occflownet.geometry import transform_points
from occflownet.contract import calibration_arrays
from occflownet.rig import default_rig
from occflownet.synth.camera import CameraRender, render_camera
from occflownet.synth.layout import KEYFRAME_INTERVAL_S
from occflownet.synth.lidar import LidarScan, LidarSpec, cast_lidar, default_lidar2ego
from occflownet.synth.voxelize import voxelize
from occflownet.synth.world import Boxes, World
from occflownet.voxel_walk import traverse

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
    mask_ray_angle: float = 0.008  # angular spacing [rad] of the camera rays cast for mask_camera

    @staticmethod
    def default(width: int = 480, height: int = 270, **kwargs) -> "SensorRig":
        K, T = calibration_arrays(default_rig(width, height))
        return SensorRig(width, height, K.astype(np.float64), T.astype(np.float64), **kwargs)


@dataclass
class Keyframe:
    """Everything about one keyframe. Poses are ego→global [4, 4] at each sensor's time; ``semantics`` and masks
    uint8 [200, 200, 16] in the ego frame at ``lidar_time_us``; ``boxes`` the geometry at the LiDAR time (global)."""

    frame_index: int
    scene_time: float  # seconds since the scene's first keyframe, at the LiDAR time
    lidar_time_us: int
    camera_times_us: list[int]
    lidar_ego2global: np.ndarray
    camera_ego2global: list[np.ndarray]
    cameras: list[CameraRender]
    scan: LidarScan
    semantics: np.ndarray
    mask_lidar: np.ndarray
    mask_camera: np.ndarray
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

    semantics = voxelize(world, boxes, ego_lidar)
    occupied = semantics != FREE
    mask_lidar = lidar_mask(scan, rig.lidar2ego, occupied)
    mask_camera = camera_mask(rig, occupied)
    return Keyframe(frame_index, t_lidar, lidar_us, cam_times, ego_lidar, cam_poses, renders, scan, semantics,
                    mask_lidar.astype(np.uint8), mask_camera.astype(np.uint8), boxes)


def lidar_mask(scan: LidarScan, lidar2ego: np.ndarray, occupied: np.ndarray, grid: Grid = GRID) -> np.ndarray:
    """Voxels passed by the LiDAR's rays from the sensor to each return, up to the first occupied one."""
    pts = transform_points(lidar2ego, scan.points[:, :3].astype(np.float64))
    origin = np.broadcast_to(lidar2ego[:3, 3], pts.shape)
    return traverse(origin, pts - origin, occupied, np.full(len(pts), 1.0 + 1e-6), grid.lower, grid.voxel_size)


def camera_rays(rig: SensorRig) -> tuple[np.ndarray, np.ndarray]:
    """Pixel rays of all cameras, ego frame: (origins [N, 3], unit directions [N, 3]), pixels taken at a stride so
    that neighbouring rays are about ``rig.mask_ray_angle`` apart (fine enough for 0.4 m voxels at 40 m)."""
    origins, dirs = [], []
    for c in range(len(CAMERAS)):
        K = rig.intrinsics[c]
        stride = max(1, int(np.ceil(rig.mask_ray_angle * K[0, 0] - 1e-9)))
        u, v = np.meshgrid(np.arange(stride / 2, rig.width, stride), np.arange(stride / 2, rig.height, stride))
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        d = d @ rig.cam2ego[c][:3, :3].T
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        origins.append(np.broadcast_to(rig.cam2ego[c][:3, 3], d.shape))
    return np.concatenate(origins), np.concatenate(dirs)


def surface_rays(rig: SensorRig, occupied: np.ndarray, targets: np.ndarray | None = None, grid: Grid = GRID):
    """Rays from each camera to the centre of every surface voxel (occupied, with a free 6-neighbour; optionally
    only those in ``targets``) that projects into its image: (origins [M, 3], directions [M, 3] reaching the centre
    at t = 1), ego frame. They catch the voxels that pixel rays skip where they graze the ground far away."""
    pad = np.pad(occupied, 1, constant_values=False)
    inner = pad[2:, 1:-1, 1:-1] & pad[:-2, 1:-1, 1:-1] & pad[1:-1, 2:, 1:-1] & pad[1:-1, :-2, 1:-1] \
        & pad[1:-1, 1:-1, 2:] & pad[1:-1, 1:-1, :-2]
    ijk = np.argwhere(occupied & ~inner & (True if targets is None else targets))
    centers = np.asarray(grid.lower) + (ijk + 0.5) * grid.voxel_size
    origins, dirs = [], []
    for c in range(len(CAMERAS)):
        T, K = rig.cam2ego[c], rig.intrinsics[c]
        pc = (centers - T[:3, 3]) @ T[:3, :3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[:, 0] / z + K[0, 2]
            v = K[1, 1] * pc[:, 1] / z + K[1, 2]
        ok = (z > 0.05) & (u >= 0) & (u < rig.width) & (v >= 0) & (v < rig.height)
        dirs.append(centers[ok] - T[:3, 3])
        origins.append(np.broadcast_to(T[:3, 3], dirs[-1].shape))
    return np.concatenate(origins), np.concatenate(dirs)


def camera_mask(rig: SensorRig, occupied: np.ndarray, grid: Grid = GRID) -> np.ndarray:
    """Voxels seen by the cameras (ego frame): every voxel on some camera ray before or at its first occupied voxel.
    Rays: the pixel rays of ``camera_rays`` (to the grid's edge), then rays to the centres of the surface voxels
    those did not reach (``surface_rays``)."""
    o1, d1 = camera_rays(rig)
    seen = traverse(o1, d1, occupied, lower=grid.lower, voxel_size=grid.voxel_size)
    o2, d2 = surface_rays(rig, occupied, targets=~seen, grid=grid)
    return seen | traverse(o2, d2, occupied, np.full(len(o2), 1.0), lower=grid.lower, voxel_size=grid.voxel_size)
