"""What each kind of synthetic geometry *is*: its Occ3D class, its raw lidarseg index, colour, texture, reflectivity.

One table, used by the camera renderer (colour, texture), the LiDAR (raw label, intensity), the voxeliser (Occ3D
class, priority) and the table writer (category names). Colours are linear RGB in [0, 1], chosen to be clearly
different per class (a tiny model must be able to learn them) yet plausible for a street.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import (BARRIER, BICYCLE, BUS, CAR, CONSTRUCTION_VEHICLE, DRIVEABLE_SURFACE, LIDARSEG_NAMES,
                              LIDARSEG_TO_OCC3D, MANMADE, MOTORCYCLE, OTHER_FLAT, OTHERS, PEDESTRIAN, SIDEWALK, TERRAIN,
                              TRAFFIC_CONE, TRAILER, TRUCK, VEGETATION)

# Texture kinds (an int8 per primitive; the renderer switches on these).
TEX_PLAIN, TEX_FACADE, TEX_FOLIAGE, TEX_GLASS, TEX_DARK, TEX_STRIPES, TEX_BUS = range(7)
# Ground texture kinds are chosen from the ground class itself (asphalt, pavers, grass, paving).


@dataclass(frozen=True)
class Material:
    """One kind of thing in the world. ``raw`` is its nuScenes-lidarseg index; its Occ3D class follows from it."""

    raw: int
    color: tuple[float, float, float]
    texture: int = TEX_PLAIN
    reflectivity: float = 0.3  # LiDAR intensity scale in [0, 1]

    @property
    def name(self) -> str:
        return LIDARSEG_NAMES[self.raw]

    @property
    def occ(self) -> int:
        return int(LIDARSEG_TO_OCC3D[self.raw])


# The raw index per kind: the natural nuScenes-lidarseg category of each synthetic object.
MATERIALS: dict[str, Material] = {
    # ground (drawn from the ground raster, never as boxes)
    "driveable": Material(24, (0.30, 0.30, 0.32), reflectivity=0.10),
    "other_flat": Material(25, (0.72, 0.62, 0.44), reflectivity=0.20),
    "sidewalk": Material(26, (0.60, 0.52, 0.62), reflectivity=0.25),
    "terrain": Material(27, (0.42, 0.62, 0.22), reflectivity=0.30),
    # static stuff
    "building": Material(28, (0.80, 0.70, 0.58), TEX_FACADE, 0.35),
    "pole": Material(28, (0.55, 0.56, 0.60), reflectivity=0.6),
    "wall": Material(28, (0.70, 0.66, 0.60), reflectivity=0.35),
    "vegetation": Material(30, (0.12, 0.42, 0.12), TEX_FOLIAGE, 0.45),
    "trunk": Material(30, (0.35, 0.24, 0.14), reflectivity=0.30),
    "static_other": Material(29, (0.46, 0.50, 0.58), reflectivity=0.4),
    # annotated static objects
    "barrier": Material(9, (0.95, 0.40, 0.15), TEX_STRIPES, 0.7),
    "traffic_cone": Material(12, (1.00, 0.50, 0.00), TEX_STRIPES, 0.8),
    "pushable": Material(11, (0.40, 0.46, 0.54), reflectivity=0.4),
    # dynamic agents (body colours; parts below)
    "car": Material(17, (0.15, 0.35, 0.80), reflectivity=0.5),
    "truck": Material(23, (0.55, 0.25, 0.70), reflectivity=0.5),
    "bus": Material(16, (0.95, 0.80, 0.10), TEX_BUS, 0.5),
    "trailer": Material(22, (0.60, 0.38, 0.18), reflectivity=0.5),
    "construction": Material(18, (1.00, 0.62, 0.00), reflectivity=0.6),
    "motorcycle": Material(21, (0.00, 0.68, 0.62), reflectivity=0.5),
    "bicycle": Material(14, (0.95, 0.45, 0.75), reflectivity=0.4),
    "pedestrian": Material(2, (0.85, 0.12, 0.12), reflectivity=0.3),
}

# Voxel class priority when several things overlap one voxel: higher wins (small and dynamic things win over
# large static things, so thin objects are not swallowed by the ground or a facade).
_PRIORITY = {MANMADE: 1, VEGETATION: 2, OTHERS: 3, BARRIER: 4, TRAFFIC_CONE: 5, TRAILER: 6, TRUCK: 6, BUS: 6,
             CONSTRUCTION_VEHICLE: 6, CAR: 7, MOTORCYCLE: 7, BICYCLE: 7, PEDESTRIAN: 8}


def voxel_priority(occ_class: np.ndarray) -> np.ndarray:
    """Occ3D class [N] → priority [N] (ground classes 0; larger overrides smaller)."""
    lut = np.zeros(256, dtype=np.int32)
    for c, p in _PRIORITY.items():
        lut[c] = p
    return lut[np.asarray(occ_class, dtype=np.uint8)]


# Ground classes (Occ3D index) → ground material name, for the ground raster.
GROUND_KINDS: dict[int, str] = {DRIVEABLE_SURFACE: "driveable", OTHER_FLAT: "other_flat", SIDEWALK: "sidewalk",
                                TERRAIN: "terrain"}
GROUND_RAW = np.zeros(256, dtype=np.uint8)
GROUND_COLOR = np.zeros((256, 3), dtype=np.float32)
GROUND_REFLECTIVITY = np.zeros(256, dtype=np.float32)
for _c, _k in GROUND_KINDS.items():
    GROUND_RAW[_c] = MATERIALS[_k].raw
    GROUND_COLOR[_c] = MATERIALS[_k].color
    GROUND_REFLECTIVITY[_c] = MATERIALS[_k].reflectivity

# Paint on the ground (a separate raster; the class under paint stays driveable_surface).
PAINT_NONE, PAINT_WHITE, PAINT_YELLOW = 0, 1, 2
PAINT_COLOR = np.array([[0, 0, 0], [0.92, 0.92, 0.90], [0.95, 0.78, 0.10]], dtype=np.float32)
