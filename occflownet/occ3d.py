"""The Occ3D-nuScenes definitions: the voxel grid, the class table and colours, the lidarseg mapping, sensor names.

One source of truth, imported everywhere (training, export, serving metadata, the synthetic world).
This module imports numpy only, so ``serve/`` may use it without pulling in torch.

Frames: the grid lives in the *ego frame* (x forward, y left, z up, metres). A voxel index (i, j, k) has its
centre at ``GRID.lower + (index + 0.5) * GRID.voxel_size``; arrays are indexed ``[x, y, z]`` like Occ3D.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Grid:
    """The Occ3D-nuScenes voxel grid, ego frame."""

    lower: tuple[float, float, float] = (-40.0, -40.0, -1.0)
    upper: tuple[float, float, float] = (40.0, 40.0, 5.4)
    voxel_size: float = 0.4
    shape: tuple[int, int, int] = (200, 200, 16)

    @property
    def num_voxels(self) -> int:
        """X·Y·Z: the rows of one flattened grid."""
        return int(np.prod(self.shape))

    def centers(self, axis: int) -> np.ndarray:
        """Voxel centre coordinates along one axis, float64 [shape[axis]]."""
        return self.lower[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel_size

    def index_of(self, points):
        """Ego-frame points [..., 3] → integer voxel indices [..., 3] (may lie outside the grid):
        floor((p − lower) / voxel_size), the one rule for which voxel holds a point. numpy in → int64 numpy
        (computed in float64); a torch tensor in → an int64 tensor on its device, computed in the tensor's own dtype
        (the exported model's float32 arithmetic), without this module importing torch."""
        if hasattr(points, "new_tensor"):  # a torch.Tensor
            return self.cells_of(points).long()
        return np.floor((np.asarray(points) - np.asarray(self.lower)) / self.voxel_size).astype(np.int64)

    def cells_of(self, points):
        """:meth:`index_of`'s rule for a torch tensor of ego-frame points [..., 3], before the conversion to
        integers: floor((p − lower) / voxel_size) in the tensor's own float dtype (a non-finite point stays
        non-finite, so range checks on it fail instead of wrapping around). The [3] offset is subtracted from rows of
        the last two axes merged ([..., n·3] minus the offset repeated n times: the same values), because
        onnxruntime broadcasts a [3] vector over [..., 3] three numbers at a time (0.23 ms on tiny's frustum against
        0.03 ms)."""
        n = points.shape[-2] if points.dim() > 1 else 1
        rows = points.reshape(tuple(points.shape[:-2]) + (n * 3,))
        return ((rows - rows.new_tensor(tuple(self.lower) * n)) / self.voxel_size).floor().reshape(points.shape)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean [...]: whether ego-frame points [..., 3] lie inside the grid's range."""
        p = np.asarray(points)
        return np.all((p >= np.asarray(self.lower)) & (p < np.asarray(self.upper)), axis=-1)

    def to_dict(self) -> dict:
        return {"lower": list(self.lower), "upper": list(self.upper), "voxel_size": self.voxel_size,
                "shape": list(self.shape), "axes": "x,y,z", "frame": "ego"}


GRID = Grid()

# Occ3D-nuScenes classes; index 17 is free space.
CLASS_NAMES: tuple[str, ...] = (
    "others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
    "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk", "terrain", "manmade",
    "vegetation", "free",
)
NUM_CLASSES = 17  # semantic classes 0..16 (free excluded), the width of the semantic logits
FREE = 17
# Named class indices (positions in CLASS_NAMES), for code that means one class.
OTHERS = CLASS_NAMES.index("others")
BARRIER = CLASS_NAMES.index("barrier")
BICYCLE = CLASS_NAMES.index("bicycle")
BUS = CLASS_NAMES.index("bus")
CAR = CLASS_NAMES.index("car")
CONSTRUCTION_VEHICLE = CLASS_NAMES.index("construction_vehicle")
MOTORCYCLE = CLASS_NAMES.index("motorcycle")
PEDESTRIAN = CLASS_NAMES.index("pedestrian")
TRAFFIC_CONE = CLASS_NAMES.index("traffic_cone")
TRAILER = CLASS_NAMES.index("trailer")
TRUCK = CLASS_NAMES.index("truck")
DRIVEABLE_SURFACE = CLASS_NAMES.index("driveable_surface")
OTHER_FLAT = CLASS_NAMES.index("other_flat")
SIDEWALK = CLASS_NAMES.index("sidewalk")
TERRAIN = CLASS_NAMES.index("terrain")
MANMADE = CLASS_NAMES.index("manmade")
VEGETATION = CLASS_NAMES.index("vegetation")

# RGB colours per class (Occ3D visualisation palette; free is white, never drawn).
CLASS_COLORS = np.array([
    [112, 128, 144], [255, 120, 50], [255, 192, 203], [255, 255, 0], [0, 150, 245], [0, 255, 255],
    [200, 180, 0], [255, 0, 0], [255, 240, 150], [135, 60, 0], [160, 32, 240], [255, 0, 255],
    [139, 137, 137], [75, 0, 75], [150, 240, 80], [230, 230, 250], [0, 175, 0], [255, 255, 255],
], dtype=np.uint8)

# Classes shown as dynamic in the paper's tables (Table 1 grey columns, Table 2 "dynamic" mean).
DYNAMIC_CLASSES: tuple[int, ...] = (2, 3, 4, 5, 6, 7, 9, 10)
STATIC_CLASSES: tuple[int, ...] = tuple(c for c in range(NUM_CLASSES) if c not in DYNAMIC_CLASSES)
# Classes dropped from temporal frames by the dynamic ray filter and zeroed by disocclusion
# (the official code's "best setting"; note it differs from DYNAMIC_CLASSES).
DYNAMIC_FILTER_CLASSES: tuple[int, ...] = (0, 1, 3, 4, 5, 7, 9, 10)

# nuScenes-lidarseg raw categories (index → name), as in lidarseg's category.json.
LIDARSEG_NAMES: tuple[str, ...] = (
    "noise", "animal", "human.pedestrian.adult", "human.pedestrian.child",
    "human.pedestrian.construction_worker", "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer", "human.pedestrian.stroller", "human.pedestrian.wheelchair",
    "movable_object.barrier", "movable_object.debris", "movable_object.pushable_pullable",
    "movable_object.trafficcone", "static_object.bicycle_rack", "vehicle.bicycle", "vehicle.bus.bendy",
    "vehicle.bus.rigid", "vehicle.car", "vehicle.construction", "vehicle.emergency.ambulance",
    "vehicle.emergency.police", "vehicle.motorcycle", "vehicle.trailer", "vehicle.truck",
    "flat.driveable_surface", "flat.other", "flat.sidewalk", "flat.terrain", "static.manmade", "static.other",
    "static.vegetation", "vehicle.ego",
)
_RAW_TO_OCC3D = {9: 1, 14: 2, 15: 3, 16: 3, 17: 4, 18: 5, 21: 6, 2: 7, 3: 7, 4: 7, 6: 7, 12: 8, 22: 9, 23: 10,
                 24: 11, 25: 12, 26: 13, 27: 14, 28: 15, 30: 16}
# Lookup table raw lidarseg index (0..255) → Occ3D class; every unlisted index maps to 0 (others).
LIDARSEG_TO_OCC3D = np.zeros(256, dtype=np.uint8)
for _raw, _occ in _RAW_TO_OCC3D.items():
    LIDARSEG_TO_OCC3D[_raw] = _occ

CAMERAS: tuple[str, ...] = (
    "CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT",
)
LIDAR = "LIDAR_TOP"


def map_lidarseg(raw: np.ndarray) -> np.ndarray:
    """Raw nuScenes-lidarseg indices (uint8 [N]) → Occ3D classes (uint8 [N])."""
    return LIDARSEG_TO_OCC3D[np.asarray(raw, dtype=np.uint8)]


def category_to_occ3d(category_name: str) -> int:
    """A nuScenes category name (e.g. ``vehicle.car``) → Occ3D class, via the lidarseg mapping."""
    try:
        return int(LIDARSEG_TO_OCC3D[LIDARSEG_NAMES.index(category_name)])
    except ValueError:
        return 0
