"""Per-keyframe records handed out by the sample index (plain dataclasses of numpy arrays, float64 poses).

Frames and conventions (nuScenes):
- poses are 4×4 child→parent matrices: ``sensor2ego`` (sensor → ego), ``ego2global`` (ego → global);
- every sensor has its *own* ``ego2global``: the ego pose at that sensor's timestamp (cameras fire up to ~40 ms
  apart from the LiDAR on real nuScenes);
- the *current ego frame* of a keyframe is the ego frame at its LiDAR timestamp (``SampleRecord.ego2global``);
  the Occ3D ground truth is expressed in that frame;
- camera frames are OpenCV (x right, y down, z forward); paths are relative to the dataroot.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from occflownet.geometry import invert, quaternion_to_matrix, transform_points


@dataclass(frozen=True)
class CameraRecord:
    """One camera image of a keyframe."""

    name: str                 # channel, e.g. CAM_FRONT
    path: str                 # image file, relative to the dataroot
    intrinsic: np.ndarray     # float64 [3, 3] for the stored image of width × height pixels
    sensor2ego: np.ndarray    # float64 [4, 4] camera (OpenCV) → ego
    ego2global: np.ndarray    # float64 [4, 4] ego → global, at the camera's timestamp
    timestamp: int            # µs
    width: int
    height: int
    token: str                # sample_data token


@dataclass(frozen=True)
class LidarRecord:
    """The keyframe's LiDAR sweep."""

    path: str                 # .pcd.bin (5 float32 per point, LiDAR frame), relative to the dataroot
    sensor2ego: np.ndarray    # float64 [4, 4] LiDAR → ego
    ego2global: np.ndarray    # float64 [4, 4] ego → global, at the LiDAR timestamp
    timestamp: int            # µs
    token: str                # sample_data token (lidarseg files are named after it)


@dataclass(frozen=True)
class EgoBoxes:
    """3D boxes expressed in one ego frame (see ``Boxes.in_frame``). B boxes."""

    instance_tokens: np.ndarray   # str [B]: the same object keeps its instance token across keyframes
    labels: np.ndarray            # uint8 [B]: Occ3D class of the box's category
    centers: np.ndarray           # float64 [B, 3]
    sizes: np.ndarray             # float64 [B, 3]: (w, l, h) = extent along the box's y, x, z axes (nuScenes wlh)
    rotations: np.ndarray         # float64 [B, 3, 3]: box → ego rotation (box x = heading)
    yaws: np.ndarray              # float64 [B]: heading about +z, atan2(R[1,0], R[0,0])

    def __len__(self) -> int:
        return len(self.labels)

    def take(self, index) -> "EgoBoxes":
        """The boxes selected by an integer index array or boolean mask."""
        return EgoBoxes(**{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @staticmethod
    def concatenate(parts: list["EgoBoxes"]) -> "EgoBoxes":
        """The boxes of several sets (all in the same ego frame), in order."""
        return EgoBoxes(**{f.name: np.concatenate([getattr(b, f.name) for b in parts]) for f in fields(EgoBoxes)})

    def transforms(self) -> np.ndarray:
        """float64 [B, 4, 4]: box frame → this ego frame."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = self.rotations
        T[:, :3, 3] = self.centers
        return T

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """bool [B, N]: whether points [N, 3] (this ego frame) lie in each box grown by ``margin`` metres per side."""
        points = np.asarray(points, dtype=np.float64)
        local = np.einsum("bji,bnj->bni", self.rotations, points[None] - self.centers[:, None])  # R^T (p - c)
        half = self.sizes[:, [1, 0, 2]] / 2.0 + margin                                         # (l, w, h) / 2
        return np.all(np.abs(local) <= half[:, None, :], axis=-1)


@dataclass(frozen=True)
class Boxes:
    """The keyframe's sample_annotation boxes in the *global* frame. B boxes."""

    instance_tokens: np.ndarray   # str [B]
    category_names: np.ndarray    # str [B], e.g. vehicle.car
    labels: np.ndarray            # uint8 [B]: Occ3D class via occ3d.category_to_occ3d
    translations: np.ndarray      # float64 [B, 3]: box centre, global
    sizes: np.ndarray             # float64 [B, 3]: (w, l, h)
    rotations: np.ndarray         # float64 [B, 4]: quaternion (w, x, y, z), box → global

    def __len__(self) -> int:
        return len(self.labels)

    def in_frame(self, ego2global: np.ndarray) -> EgoBoxes:
        """The boxes in the ego frame whose pose is ``ego2global`` (e.g. another keyframe's current ego frame)."""
        to_ego = invert(ego2global)
        rot = np.stack([to_ego[:3, :3] @ quaternion_to_matrix(q) for q in self.rotations]) if len(self) \
            else np.zeros((0, 3, 3))
        return EgoBoxes(
            instance_tokens=self.instance_tokens, labels=self.labels,
            centers=transform_points(to_ego, self.translations).reshape(-1, 3), sizes=self.sizes, rotations=rot,
            yaws=np.arctan2(rot[:, 1, 0], rot[:, 0, 0]),
        )


@dataclass(frozen=True)
class SampleRecord:
    """One keyframe (nuScenes ``sample``) with everything needed to load and supervise it."""

    position: int                 # position in the SampleIndex
    token: str
    scene_name: str
    scene_token: str
    timestamp: int                # µs (the sample's timestamp)
    index_in_scene: int           # 0-based position among the scene's keyframes (time order)
    scene_sample_tokens: tuple    # tokens of all keyframes of the scene, in time order
    cameras: tuple                # 6 CameraRecord in occ3d.CAMERAS order
    lidar: LidarRecord
    lidarseg_path: str | None     # raw lidarseg labels (uint8 per point), relative to the dataroot
    occupancy_path: str | None    # Occ3D labels.npz, relative to the dataroot
    boxes: Boxes

    @property
    def ego2global(self) -> np.ndarray:
        """float64 [4, 4]: the current ego frame (ego at the LiDAR timestamp = frame of the Occ3D gt) → global."""
        return self.lidar.ego2global

    @property
    def intrinsics(self) -> np.ndarray:
        """float64 [6, 3, 3] in camera order."""
        return np.stack([c.intrinsic for c in self.cameras])

    @property
    def cam2ego(self) -> np.ndarray:
        """float64 [6, 4, 4]: camera → ego (calibration; the same at any timestamp)."""
        return np.stack([c.sensor2ego for c in self.cameras])

    @property
    def image_sizes(self) -> np.ndarray:
        """int64 [6, 2]: (width, height) per camera."""
        return np.array([[c.width, c.height] for c in self.cameras], dtype=np.int64)

    def cam2current_ego(self) -> np.ndarray:
        """float64 [6, 4, 4]: camera → current ego frame, through each camera's own ego pose.

        ``inv(ego2global_lidar) @ ego2global_cam @ cam2ego``: differs from ``cam2ego`` by the ego motion between
        the camera and LiDAR timestamps (a few cm on real nuScenes)."""
        to_current = invert(self.ego2global)
        return np.stack([to_current @ c.ego2global @ c.sensor2ego for c in self.cameras])

    def boxes_in_ego(self) -> EgoBoxes:
        """The keyframe's boxes in its own current ego frame."""
        return self.boxes.in_frame(self.ego2global)
