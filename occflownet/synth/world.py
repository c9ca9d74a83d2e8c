"""The synthetic world's geometry: a flat ground (z = 0) with a 2D class raster, and yaw-oriented boxes.

Everything the camera, the LiDAR and the voxeliser see comes from a ``World``: its static boxes and ground raster
(fixed, in the *scene frame*: x along the main road) and its agents (boxes that move with time). ``boxes_at(t)``
gives the geometry of one instant in the *global frame*; ``ego2global(t)`` the ego pose then. Time ``t`` is in
seconds since the scene's first keyframe. The global frame is the scene frame rotated by ``yaw`` about +z and
shifted, so that ego2global is a non-trivial transform like in nuScenes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occflownet.occ3d import LIDARSEG_TO_OCC3D, TERRAIN
from occflownet.geometry import make_transform, rotation_z, transform_points


@dataclass
class Boxes:
    """N yaw-oriented solid boxes. ``center`` [N, 3] and ``yaw`` [N] in the frame named by whoever holds them.

    ``half`` [N, 3] half extents along the box's own x (length), y (width), z (height); ``raw`` [N] uint8 raw
    lidarseg index; ``color`` [N, 3] float32 RGB in [0, 1]; ``texture`` [N] int8 (materials.TEX_*);
    ``reflectivity`` [N] float32; ``instance`` [N] int32 index into ``World.agents`` or -1 for unannotated stuff.
    """

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    raw: np.ndarray
    color: np.ndarray
    texture: np.ndarray
    reflectivity: np.ndarray
    instance: np.ndarray

    @staticmethod
    def empty() -> "Boxes":
        return Boxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.uint8),
                     np.zeros((0, 3), np.float32), np.zeros(0, np.int8), np.zeros(0, np.float32),
                     np.zeros(0, np.int32))

    def __len__(self) -> int:
        return len(self.yaw)

    @property
    def occ(self) -> np.ndarray:
        """Occ3D class per box, uint8 [N]."""
        return LIDARSEG_TO_OCC3D[self.raw]

    @staticmethod
    def concat(parts: list["Boxes"]) -> "Boxes":
        parts = [p for p in parts if len(p)] or [Boxes.empty()]
        return Boxes(*[np.concatenate([getattr(p, f) for p in parts]) for f in Boxes.__dataclass_fields__])

    def subset(self, index) -> "Boxes":
        return Boxes(*[getattr(self, f)[index] for f in Boxes.__dataclass_fields__])

    def transformed(self, T: np.ndarray) -> "Boxes":
        """The same boxes in another frame; ``T`` [4, 4] maps this frame into the new one (rotation about z only)."""
        yaw = np.arctan2(T[1, 0], T[0, 0])
        out = self.subset(slice(None))
        out.center = transform_points(T, self.center)
        out.yaw = self.yaw + yaw
        return out

    def corners(self) -> np.ndarray:
        """The 8 corners of every box, [N, 8, 3], same frame as ``center``."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        local = signs[None] * self.half[:, None, :]
        c, s = np.cos(self.yaw)[:, None], np.sin(self.yaw)[:, None]
        x = c * local[..., 0] - s * local[..., 1]
        y = s * local[..., 0] + c * local[..., 1]
        return np.stack([x, y, local[..., 2]], axis=-1) + self.center[:, None, :]


@dataclass
class Agent:
    """An annotated object (nuScenes instance): parts rigidly attached to a pose moving at constant velocity.

    Parts are in the agent's frame (x forward, y left, z up, origin on the ground under the annotation box
    centre). ``origin`` [2] and ``heading`` are the scene-frame pose at t = 0; it moves ``speed`` m/s along heading.
    ``size`` is the annotation box (w, l, h) in nuScenes order; the annotation box centre is at (0, 0, h/2).
    """

    kind: str
    raw: int
    origin: np.ndarray
    heading: float
    speed: float
    attribute: str
    size: tuple[float, float, float]
    part_center: np.ndarray  # [P, 3]
    part_half: np.ndarray  # [P, 3]
    part_color: np.ndarray  # [P, 3]
    part_texture: np.ndarray  # [P]
    reflectivity: float = 0.5

    def position(self, t: float) -> np.ndarray:
        """Scene-frame (x, y) at time ``t`` [s]."""
        return self.origin + self.speed * t * np.array([np.cos(self.heading), np.sin(self.heading)])


@dataclass
class GroundRaster:
    """Class and paint of the flat ground (z = 0), scene frame. ``cls`` uint8 [NX, NY] Occ3D ground classes
    (driveable_surface, other_flat, sidewalk, terrain), ``paint`` uint8 [NX, NY] (materials.PAINT_*); cell (i, j) covers x0 + i*res .. x0 + (i+1)*res."""

    cls: np.ndarray
    paint: np.ndarray
    x0: float
    y0: float
    res: float
    outside_class: int = TERRAIN

    def lookup(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scene-frame points [..., 2] → (class uint8 [...], paint uint8 [...]); outside the raster: terrain."""
        i = np.floor((xy[..., 0] - self.x0) / self.res).astype(np.int64)
        j = np.floor((xy[..., 1] - self.y0) / self.res).astype(np.int64)
        inside = (i >= 0) & (i < self.cls.shape[0]) & (j >= 0) & (j < self.cls.shape[1])
        i, j = np.where(inside, i, 0), np.where(inside, j, 0)
        cls = np.where(inside, self.cls[i, j], self.outside_class).astype(np.uint8)
        paint = np.where(inside, self.paint[i, j], 0).astype(np.uint8)
        return cls, paint


@dataclass
class World:
    """One scene: static boxes and ground (scene frame), agents, the ego's path, the sun."""

    name: str
    scene2global: np.ndarray  # [4, 4], rotation about z + translation
    ground: GroundRaster
    static: Boxes  # scene frame
    agents: list[Agent]
    ego_start: np.ndarray  # scene-frame (x, y) at t = 0, heading +x
    ego_speed: float  # m/s
    sun: np.ndarray  # unit vector towards the sun, global frame
    sky_seed: int = 0
    meta: dict = field(default_factory=dict)

    def ego2global(self, t: float) -> np.ndarray:
        """Ego pose at time ``t`` [s]: 4×4 ego→global (ego on the ground, level, heading along the road)."""
        x, y = self.ego_start + np.array([self.ego_speed * t, 0.0])
        return self.scene2global @ make_transform(np.eye(3), (x, y, 0.0))

    def agent_boxes(self, t: float) -> Boxes:
        """All agents' parts at time ``t``, scene frame."""
        if not self.agents:
            return Boxes.empty()
        out = []
        for idx, a in enumerate(self.agents):
            x, y = a.position(t)
            c, s = np.cos(a.heading), np.sin(a.heading)
            pc = a.part_center
            center = np.stack([x + c * pc[:, 0] - s * pc[:, 1], y + s * pc[:, 0] + c * pc[:, 1], pc[:, 2]], 1)
            n = len(pc)
            out.append(Boxes(center, a.part_half.copy(), np.full(n, a.heading), np.full(n, a.raw, np.uint8),
                             a.part_color.astype(np.float32), a.part_texture.astype(np.int8),
                             np.full(n, a.reflectivity, np.float32), np.full(n, idx, np.int32)))
        return Boxes.concat(out)

    def boxes_at(self, t: float) -> Boxes:
        """Every box of the world at time ``t`` [s], global frame."""
        return Boxes.concat([self.static, self.agent_boxes(t)]).transformed(self.scene2global)

    def annotation_box(self, agent_index: int, t: float) -> tuple[np.ndarray, float]:
        """Annotation box of one agent at ``t``: (centre [3] global, yaw about +z global)."""
        a = self.agents[agent_index]
        x, y = a.position(t)
        center = transform_points(self.scene2global, np.array([x, y, a.size[2] / 2]))
        yaw = a.heading + np.arctan2(self.scene2global[1, 0], self.scene2global[0, 0])
        return center, float(np.arctan2(np.sin(yaw), np.cos(yaw)))

    def ground_lookup_global(self, xy_global: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global-frame points [..., 2] on the ground → (class, paint) uint8 [...]."""
        g2s = np.linalg.inv(self.scene2global)
        x = g2s[0, 0] * xy_global[..., 0] + g2s[0, 1] * xy_global[..., 1] + g2s[0, 3]
        y = g2s[1, 0] * xy_global[..., 0] + g2s[1, 1] * xy_global[..., 1] + g2s[1, 3]
        return self.ground.lookup(np.stack([x, y], -1))


def scene_to_global(yaw: float, offset) -> np.ndarray:
    """4×4 scene→global: rotation ``yaw`` about +z, then translation ``offset`` (x, y)."""
    T = rotation_z(yaw)
    T[:2, 3] = offset
    return T
