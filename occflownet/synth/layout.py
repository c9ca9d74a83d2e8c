"""Procedural layout of one synthetic scene: a main road along the scene's +x axis, maybe a cross street,
sidewalks, lots with buildings / parks / plazas / a construction site, street furniture, and traffic.

``build_world(config, seed, scene_index, frames)`` → ``world.World``. Deterministic: every random draw comes from
``numpy.random.default_rng([seed, scene_index])``; no global RNG.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import DRIVEABLE_SURFACE, OTHER_FLAT, SIDEWALK, TERRAIN
from occflownet.options import check_fields, option
from occflownet.synth.agents import default_attribute, instance_color, make_agent
from occflownet.synth.materials import MATERIALS, PAINT_WHITE, PAINT_YELLOW
from occflownet.synth.world import Boxes, GroundRaster, World, scene_to_global

KEYFRAME_INTERVAL_S = 0.5  # 2 Hz keyframes, like nuScenes
SCENE_SIZE = "scene size"  # the --help section of WorldConfig's options


@dataclass(frozen=True)
class WorldConfig:
    """Size and density of a synthetic scene; `occflownet synth` derives its scene-size options from these fields
    (``occflownet/options.py``)."""

    margin: float = option(100.0, "world extent in metres beyond the ego's path and to each side (the grid reaches "
                                  "40 m from the ego)", minimum=45.0, group=SCENE_SIZE)
    ego_speed: tuple[float, float] = option((4.0, 8.0), "ego speed range in m/s, drawn per scene (MAX at most 20)",
                                            minimum=0.0, group=SCENE_SIZE)
    lanes: tuple[int, int] = option((1, 2), "lanes per direction, drawn per scene (MAX at most 4)", minimum=1,
                                    group=SCENE_SIZE)
    traffic: float = option(1.0, "vehicle density scale (moving and parked; above 0)", minimum=0.0,
                            group=SCENE_SIZE)
    pedestrians: float = option(1.0, "pedestrian density scale", minimum=0.0, group=SCENE_SIZE)
    cross_street_probability: float = option(0.7, "probability of a cross street per scene", minimum=0.0,
                                             flag="cross-street", group=SCENE_SIZE)
    raster_res: float = 0.1  # ground raster cell [m]; not a command-line option

    def __post_init__(self):
        check_fields(self)                      # the smallest values; the ranges' upper ends and order below
        if not self.lanes[0] <= self.lanes[1] <= 4:
            raise ValueError(f"lanes (MIN, MAX) must satisfy 1 <= MIN <= MAX <= 4, got {self.lanes}")
        if not self.ego_speed[0] <= self.ego_speed[1] <= 20.0:
            raise ValueError(f"ego_speed (MIN, MAX) must satisfy 0 <= MIN <= MAX <= 20 m/s, got {self.ego_speed}")
        if self.traffic <= 0 or self.cross_street_probability > 1:
            raise ValueError(f"traffic must be > 0 and cross_street_probability at most 1, got {self.traffic} and "
                             f"{self.cross_street_probability}")


class _Builder:
    """Accumulates static boxes and agents in the scene frame while the layout is drawn."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.static: list[tuple] = []
        self.agents = []

    def box(self, kind, cx, cy, z0, z1, length, width, yaw=0.0, color=None, texture=None):
        m = MATERIALS[kind]
        color = instance_color(m.color, self.rng) if color is None else color
        self.static.append(((cx, cy, (z0 + z1) / 2), (length / 2, width / 2, (z1 - z0) / 2), yaw, m.raw,
                            color, m.texture if texture is None else texture, m.reflectivity))

    def agent(self, kind, x, y, heading, speed=0.0, attribute=None):
        attribute = default_attribute(kind, speed > 0, self.rng) if attribute is None else attribute
        self.agents.append(make_agent(kind, self.rng, (x, y), heading, speed, attribute))

    def static_boxes(self) -> Boxes:
        s = self.static
        if not s:
            return Boxes.empty()
        return Boxes(np.array([q[0] for q in s], float), np.array([q[1] for q in s], float),
                     np.array([q[2] for q in s], float), np.array([q[3] for q in s], np.uint8),
                     np.array([q[4] for q in s], np.float32), np.array([q[5] for q in s], np.int8),
                     np.array([q[6] for q in s], np.float32), np.full(len(s), -1, np.int32))


class _Raster:
    def __init__(self, x0, x1, y0, y1, res):
        self.x0, self.y0, self.res = x0, y0, res
        nx, ny = int(np.ceil((x1 - x0) / res)), int(np.ceil((y1 - y0) / res))
        self.cls = np.full((nx, ny), TERRAIN, np.uint8)  # terrain everywhere first
        self.paint = np.zeros((nx, ny), np.uint8)

    def _idx(self, v, origin, n):
        return int(np.clip(round((v - origin) / self.res), 0, n))

    def fill(self, arr, x0, x1, y0, y1, value):
        i0, i1 = self._idx(x0, self.x0, arr.shape[0]), self._idx(x1, self.x0, arr.shape[0])
        j0, j1 = self._idx(y0, self.y0, arr.shape[1]), self._idx(y1, self.y0, arr.shape[1])
        arr[i0:i1, j0:j1] = value


@dataclass
class _Road:
    """The main road's cross-section (scene-frame y, per side s = -1 right, +1 left) and the optional cross street
    (at x = xc, half width ``cross_half``; ``corridor`` = its x range including its sidewalks, (inf, inf) if none)."""

    x_min: float
    x_max: float
    y_half: float
    n_lanes: int
    lane_w: float
    median: float  # width of the central median (0: a yellow double line instead)
    parking: dict  # side → has a parking lane
    main_parking: int  # the side whose parking lane holds every vehicle kind
    road_edge: dict  # side → |y| of the kerb
    sidewalk_w: float
    lot_front: dict  # side → |y| where the lots begin (back of the sidewalk)
    cross: bool
    xc: float | None
    cross_half: float
    corridor: tuple[float, float]

    def in_cross(self, x0, x1):
        """Whether [x0, x1] overlaps the cross street's corridor."""
        return self.cross and x1 > self.corridor[0] and x0 < self.corridor[1]


def build_world(config: WorldConfig, seed: int, scene_index: int, frames: int) -> World:
    """Draw one scene. The ego starts at scene (0, lane y) and drives +x for ``frames`` keyframes."""
    rng = np.random.default_rng([int(seed), int(scene_index)])
    b = _Builder(rng)
    ego_speed = rng.uniform(*config.ego_speed)
    path = ego_speed * KEYFRAME_INTERVAL_S * max(frames - 1, 0)
    m = config.margin
    road = _draw_road(rng, config, path, -m, path + m, m)
    ras = _Raster(road.x_min, road.x_max, -road.y_half, road.y_half, config.raster_res)
    _ground_classes(ras, road)
    _road_paint(ras, road)
    _roadside(b, ras, rng, road, path)
    ego_y = _road_users(b, rng, config, road, ego_speed, path)

    yaw = rng.uniform(-np.pi, np.pi)
    offset = rng.uniform(300.0, 1800.0, 2)
    sun_az, sun_el = rng.uniform(-np.pi, np.pi), np.radians(rng.uniform(30.0, 60.0))
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    ground = GroundRaster(ras.cls, ras.paint, road.x_min, -road.y_half, config.raster_res)
    meta = {"lanes": road.n_lanes, "cross_street": bool(road.cross), "path_m": float(path),
            "extent_x": (road.x_min, road.x_max), "extent_y": (-road.y_half, road.y_half)}
    return World(name=f"scene-{scene_index + 1:04d}", scene2global=scene_to_global(yaw, offset), ground=ground,
                 static=b.static_boxes(), agents=b.agents, ego_start=np.array([0.0, ego_y]), ego_speed=ego_speed,
                 sun=sun, sky_seed=int(rng.integers(1 << 30)), meta=meta)


def _draw_road(rng, config: WorldConfig, path, x_min, x_max, y_half) -> _Road:
    """Cross-section of the main road (y): median, lanes, parking lanes, sidewalks; then maybe a cross street."""
    n_lanes = int(rng.integers(config.lanes[0], config.lanes[1] + 1))
    lane_w = rng.uniform(3.2, 3.7)
    median = rng.uniform(1.5, 3.0) if (n_lanes >= 2 and rng.random() < 0.6) else 0.0
    parking = {s: rng.random() < 0.6 for s in (-1, 1)}
    main_parking = -1 if rng.random() < 0.5 else 1
    parking[main_parking] = True  # at least one parking lane: parked agents of every kind live there
    road_edge = {s: median / 2 + n_lanes * lane_w + (2.4 if parking[s] else 0.0) for s in (-1, 1)}
    sidewalk_w = rng.uniform(3.0, 5.0)
    lot_front = {s: road_edge[s] + sidewalk_w for s in (-1, 1)}

    cross = rng.random() < config.cross_street_probability
    xc = rng.uniform(-10.0, path + 40.0) if cross else None
    cross_half = rng.uniform(3.2, 4.5) if cross else 0.0
    corridor = (xc - cross_half - sidewalk_w, xc + cross_half + sidewalk_w) if cross else (np.inf, np.inf)
    return _Road(x_min, x_max, y_half, n_lanes, lane_w, median, parking, main_parking, road_edge, sidewalk_w,
                 lot_front, cross, xc, cross_half, corridor)


def _ground_classes(ras: _Raster, road: _Road) -> None:
    """Sidewalks, the road surface (both streets) and the median into the class raster (terrain elsewhere)."""
    r = road
    for s in (-1, 1):
        lo, hi = sorted((s * r.road_edge[s], s * r.lot_front[s]))
        ras.fill(ras.cls, r.x_min, r.x_max, lo, hi, SIDEWALK)
    if r.cross:
        ras.fill(ras.cls, r.corridor[0], r.corridor[1], -r.y_half, r.y_half, SIDEWALK)
        ras.fill(ras.cls, r.xc - r.cross_half, r.xc + r.cross_half, -r.y_half, r.y_half, DRIVEABLE_SURFACE)
    ras.fill(ras.cls, r.x_min, r.x_max, -r.road_edge[-1], r.road_edge[1], DRIVEABLE_SURFACE)
    if r.median:
        ras.fill(ras.cls, r.x_min, r.x_max, -r.median / 2, r.median / 2, OTHER_FLAT)
        if r.cross:
            ras.fill(ras.cls, r.xc - r.cross_half, r.xc + r.cross_half, -r.median / 2, r.median / 2,
                     DRIVEABLE_SURFACE)


def _road_paint(ras: _Raster, road: _Road) -> None:
    """Paint: lane lines, centre line, crosswalks, stop lines."""
    r = road
    for s in (-1, 1):
        for k in range(1, r.n_lanes):  # dashed lines between lanes of one direction
            y = s * (r.median / 2 + k * r.lane_w)
            for x in np.arange(r.x_min, r.x_max, 9.0):
                if not r.in_cross(x, x + 3):
                    ras.fill(ras.paint, x, x + 3.0, y - 0.08, y + 0.08, PAINT_WHITE)
        y = s * (r.median / 2 + r.n_lanes * r.lane_w)  # solid edge line
        for x0, x1 in _gaps(r.x_min, r.x_max, r.corridor):
            ras.fill(ras.paint, x0, x1, y - 0.08, y + 0.08, PAINT_WHITE)
    if not r.median:
        for x0, x1 in _gaps(r.x_min, r.x_max, r.corridor):
            ras.fill(ras.paint, x0, x1, -0.22, -0.08, PAINT_YELLOW)
            ras.fill(ras.paint, x0, x1, 0.08, 0.22, PAINT_YELLOW)
    if r.cross:
        for xs in (r.corridor[0], r.corridor[1] - 3.0):  # zebra crossings over the main road
            for y in np.arange(-r.road_edge[-1] + 0.3, r.road_edge[1] - 0.3, 1.0):
                ras.fill(ras.paint, xs, xs + 3.0, y, y + 0.5, PAINT_WHITE)
        ras.fill(ras.paint, r.corridor[0] - 0.6, r.corridor[0] - 0.2, -r.road_edge[-1], -r.median / 2, PAINT_WHITE)
        ras.fill(ras.paint, r.corridor[1] + 0.2, r.corridor[1] + 0.6, r.median / 2, r.road_edge[1], PAINT_WHITE)
        ras.fill(ras.paint, r.xc - 0.08, r.xc + 0.08, -r.y_half, -r.lot_front[-1], PAINT_YELLOW)
        ras.fill(ras.paint, r.xc - 0.08, r.xc + 0.08, r.lot_front[1], r.y_half, PAINT_YELLOW)


def _roadside(b: _Builder, ras: _Raster, rng, road: _Road, path) -> None:
    """Lots along both sides (buildings, parks, plazas, one construction site near the ego's path), street
    furniture, and bushes on the median."""
    r = road
    site_side = -1 if rng.random() < 0.5 else 1
    site_x = _free_x(rng, path / 2 + rng.uniform(-15, 15), 14.0, r.corridor)
    for s in (-1, 1):
        x = r.x_min
        while x < r.x_max - 6.0:
            length = rng.uniform(10.0, 32.0)
            if x + length > r.corridor[0] and x < r.corridor[1]:
                x = r.corridor[1] + 0.5
                continue
            if s == site_side and x <= site_x < x + length + 14.0:
                _construction_site(b, ras, s, site_x, r.lot_front[s], r.sidewalk_w)
                x = site_x + 9.0
                continue
            _lot(b, ras, rng, s, x, min(x + length, r.x_max), r.lot_front[s])
            x += length
        _street_furniture(b, rng, s, r.x_min, r.x_max, r.road_edge[s], r.sidewalk_w, r.corridor)
    if r.median:
        for x in np.arange(r.x_min + rng.uniform(0, 20), r.x_max, rng.uniform(14, 30)):
            if not r.in_cross(x - 2, x + 2):
                b.box("vegetation", x, 0.0, 0.0, rng.uniform(0.6, 1.1), rng.uniform(1.5, 3.0), r.median * 0.6)


def _road_users(b: _Builder, rng, config: WorldConfig, road: _Road, ego_speed, path) -> float:
    """Traffic in every lane, parked vehicles, pedestrians, queues on the cross street; returns the ego's lane y."""
    r = road
    ego_lane = int(rng.integers(0, r.n_lanes))
    ego_y = -(r.median / 2 + (ego_lane + 0.5) * r.lane_w)
    _traffic(b, rng, config, r.x_min, r.x_max, r.n_lanes, r.lane_w, r.median, ego_lane, ego_speed, path, r.corridor)
    for s in (-1, 1):
        if r.parking[s]:
            _parked(b, rng, config, s, r.x_min, r.x_max, r.road_edge[s], path, r.corridor,
                    every_kind=s == r.main_parking)
        _pedestrians(b, rng, config, s, r.x_min, r.x_max, r.road_edge[s], r.sidewalk_w, r.corridor)
    if r.cross:
        _cross_traffic(b, rng, config, r.xc, r.cross_half, r.road_edge, r.y_half)
    return ego_y


def _gaps(x0, x1, corridor):
    """The x-intervals of [x0, x1] outside the cross street's corridor."""
    if not np.isfinite(corridor[0]):
        return [(x0, x1)]
    return [(x0, min(x1, corridor[0])), (max(x0, corridor[1]), x1)]


def _free_x(rng, x, half, corridor):
    if np.isfinite(corridor[0]) and x + half > corridor[0] and x - half < corridor[1]:
        return corridor[1] + half + 1.0 if rng.random() < 0.5 else corridor[0] - half - 1.0
    return x


def _lot(b: _Builder, ras: _Raster, rng, s, x0, x1, front):
    """One lot beside the road between x0 and x1 on side s (-1 right, +1 left), starting at |y| = front."""
    kind = rng.choice(["building", "building", "building", "park", "plaza", "wall"], p=[.3, .2, .15, .15, .1, .1])
    length = x1 - x0
    xm = (x0 + x1) / 2
    if kind == "building":
        gap = rng.uniform(0.0, 4.0)
        setback = 0.0 if rng.random() < 0.5 else rng.uniform(1.0, 6.0)
        depth, height = rng.uniform(8.0, 20.0), rng.choice([rng.uniform(4.0, 9.0), rng.uniform(9.0, 24.0)])
        b.box("building", xm, s * (front + setback + depth / 2), 0.0, height, max(length - gap, 3.0), depth)
        if setback > 2.0 and rng.random() < 0.6:
            for x in np.arange(x0 + 2.0, x1 - 1.0, rng.uniform(3.0, 6.0)):
                b.box("vegetation", x, s * (front + setback / 2), 0.0, rng.uniform(0.5, 1.2), 1.2, setback * 0.5)
    elif kind == "park":
        for _ in range(int(length / 6) + 1):
            x, y = rng.uniform(x0 + 1, x1 - 1), s * (front + rng.uniform(2.0, 25.0))
            _tree(b, rng, x, y)
        for _ in range(int(length / 8) + 1):
            x, y = rng.uniform(x0 + 1, x1 - 1), s * (front + rng.uniform(1.0, 20.0))
            b.box("vegetation", x, y, 0.0, rng.uniform(0.5, 1.5), rng.uniform(1.0, 3.0), rng.uniform(1.0, 3.0))
    elif kind == "plaza":
        lo, hi = sorted((s * front, s * (front + rng.uniform(8.0, 20.0))))
        ras.fill(ras.cls, x0 + 0.5, x1 - 0.5, lo, hi, OTHER_FLAT)
        for _ in range(int(rng.integers(1, 4))):
            b.box("static_other", rng.uniform(x0 + 1, x1 - 1), s * (front + rng.uniform(1.0, 6.0)), 0.0,
                  rng.uniform(0.8, 2.2), rng.uniform(0.6, 2.5), rng.uniform(0.5, 1.5))
        depth = rng.uniform(8.0, 15.0)
        b.box("building", xm, s * (front + 22.0 + depth / 2), 0.0, rng.uniform(6.0, 20.0), length, depth)
    else:  # a wall with trees behind it
        b.box("wall", xm, s * (front + 0.6), 0.0, rng.uniform(1.2, 2.5), length - 0.5, 0.3)
        for x in np.arange(x0 + 2.0, x1 - 1.0, rng.uniform(4.0, 8.0)):
            _tree(b, rng, x, s * (front + rng.uniform(3.0, 8.0)))


def _tree(b: _Builder, rng, x, y, kerb: bool = False):
    """A tree: trunk and crown (vegetation). Kerb trees are smaller, higher and square to the road."""
    trunk = rng.uniform(2.2, 3.0) if kerb else rng.uniform(1.8, 2.8)
    crown = rng.uniform(1.5, 1.9) if kerb else rng.uniform(2.0, 4.0)
    b.box("trunk", x, y, 0.0, trunk + 0.3, 0.3, 0.3)
    yaw = rng.uniform(0, np.pi / 2) if kerb is False else 0.0  # kerb trees stay clear of parked trucks
    b.box("vegetation", x, y, trunk, trunk + rng.uniform(2.0, 4.0), crown, crown * (1.0 if kerb else 1.2), yaw=yaw)


def _street_furniture(b: _Builder, rng, s, x_min, x_max, edge, sidewalk_w, corridor):
    """Trees and lamp posts by the kerb, bins and boxes at the back of the sidewalk (side s)."""
    blocked = (lambda x: np.isfinite(corridor[0]) and corridor[0] - 1.0 < x < corridor[1] + 1.0)
    x = x_min + rng.uniform(0, 10)
    while x < x_max:
        if not blocked(x):
            if rng.random() < 0.55:
                _tree(b, rng, x, s * (edge + 1.0), kerb=True)
            elif rng.random() < 0.5:
                b.box("pole", x, s * (edge + 0.3), 0.0, rng.uniform(5.5, 7.5), 0.2, 0.2)
        x += rng.uniform(8.0, 16.0)
    x = x_min + rng.uniform(0, 10)
    while x < x_max:
        if not blocked(x):
            y = s * (edge + sidewalk_w - 0.5)
            if rng.random() < 0.6:
                b.agent("pushable", x, y, 0.0)
            else:
                b.box("static_other", x, y, 0.0, rng.uniform(0.8, 1.6), rng.uniform(0.5, 1.5), 0.6)
        x += rng.uniform(10.0, 30.0)


def _construction_site(b: _Builder, ras: _Raster, s, x, front, sidewalk_w):
    """A fenced site (other_flat ground) with barriers along the sidewalk, cones, and a construction vehicle."""
    rng = b.rng
    lo, hi = sorted((s * front, s * (front + 16.0)))
    ras.fill(ras.cls, x - 8.0, x + 8.0, lo, hi, OTHER_FLAT)
    for bx in np.arange(x - 7.0, x + 7.5, 2.2):
        if abs(bx - x) > 2.2:  # leave a gate in the middle, closed by cones
            b.agent("barrier", bx, s * (front + 0.4), 0.0)
    for cx in (-1.0, 0.0, 1.0):
        b.agent("traffic_cone", x + cx, s * (front + 0.4), 0.0)
    for bx in (x - 8.0, x + 8.0):
        for d in (2.5, 5.0, 7.5):
            b.agent("barrier", bx, s * (front + d), np.pi / 2)
    for cx in np.arange(x - 6.0, x + 6.5, 3.0):
        if abs(cx - x) > 2.2:
            b.agent("traffic_cone", cx, s * (front + 1.3), 0.0)
    b.agent("construction", x + rng.uniform(-1.5, 1.5), s * (front + rng.uniform(5.5, 7.0)),
            rng.uniform(-0.3, 0.3) + (0.0 if rng.random() < 0.5 else np.pi), speed=0.0)
    b.box("building", x, s * (front + 14.0), 0.0, rng.uniform(3.0, 12.0), rng.uniform(8.0, 14.0), 4.0,
          color=instance_color((0.7, 0.7, 0.72), rng))


def _vehicle_kind(rng) -> str:
    return str(rng.choice(["car", "truck", "bus", "motorcycle", "bicycle", "construction"],
                          p=[0.64, 0.1, 0.07, 0.08, 0.07, 0.04]))


def _traffic(b, rng, config, x_min, x_max, n_lanes, lane_w, median, ego_lane, ego_speed, path, corridor):
    """Moving vehicles in every lane of the main road (constant speed per lane, so they never collide)."""
    for s in (-1, 1):  # s = -1: lanes driving +x (right-hand traffic); s = +1: driving -x
        for k in range(n_lanes):
            y = s * (median / 2 + (k + 0.5) * lane_w)
            heading = 0.0 if s < 0 else np.pi
            ego = s < 0 and k == ego_lane
            speed = ego_speed if ego else rng.uniform(3.0, 11.0)
            travel = speed * (path / max(ego_speed, 1e-6) + 1.0)
            x = x_min - (travel if s < 0 else 0.0) + rng.uniform(0, 15)  # free road starts here (lower x)
            end = x_max + (travel if s > 0 else 0.0)
            while x < end:
                kind = _vehicle_kind(rng)
                b.agent(kind, 0.0, y + rng.uniform(-0.3, 0.3), heading, speed)
                car = b.agents[-1]
                parts = [car]
                if kind == "truck" and not ego and rng.random() < 0.4:  # a trailer behind (moves with it)
                    b.agent("trailer", 0.0, y, heading, speed)
                    parts = [b.agents[-1], car] if s < 0 else [car, b.agents[-1]]  # ordered by increasing x
                length = sum(a.size[1] for a in parts) + 0.8 * (len(parts) - 1)
                if ego and x < 14.0 and x + length > -12.0:  # keep the ego's own lane clear around it
                    del b.agents[-len(parts):]
                    x = 14.0 + rng.uniform(0, 5)
                    continue
                for a in parts:
                    a.origin[0] = x + a.size[1] / 2
                    x += a.size[1] + 0.8
                x += rng.uniform(8.0, 40.0) / max(config.traffic, 1e-3) - 0.8


def _parked(b, rng, config, s, x_min, x_max, edge, path, corridor, every_kind: bool):
    """Parked vehicles in the parking lane of side s, filled forwards and backwards from near the middle of the
    ego's path; with ``every_kind`` the ones nearest to it are of every vehicle kind (so that every class appears
    near the ego in every scene)."""
    y = s * (edge - 1.3)
    heading = 0.0 if s < 0 else np.pi
    guaranteed = ["trailer", "bus", "truck", "motorcycle", "bicycle", "car"] if every_kind else ["car", "trailer"]
    rng.shuffle(guaranteed)
    blocked = (lambda lo, hi: np.isfinite(corridor[0]) and hi > corridor[0] - 3.0 and lo < corridor[1] + 3.0)
    for direction in (1, -1):
        x = path / 2 - 25.0 + (rng.uniform(0, 5) if direction > 0 else -1.0)  # the free lane's edge
        while x_min + 5 < x < x_max - 5:
            from_list = bool(guaranteed) and abs(x - path / 2) < 40.0
            if from_list:
                kind = guaranteed.pop()
            else:
                kind = str(rng.choice(["car", "car", "car", "truck", "trailer"])) if direction > 0 else "car"
            b.agent(kind, 0.0, y, heading, 0.0)
            length = b.agents[-1].size[1]
            lo, hi = (x, x + length) if direction > 0 else (x - length, x)
            if blocked(lo, hi):  # it does not fit before the cross street: try again behind it
                del b.agents[-1]
                if from_list:
                    guaranteed.append(kind)
                x = (corridor[1] + 3.0) if direction > 0 else (corridor[0] - 3.0)
                continue
            b.agents[-1].origin[0] = (lo + hi) / 2
            gap = rng.uniform(1.0, 4.0) if guaranteed else rng.uniform(1.0, 20.0) / max(config.traffic, 1e-3)
            x += direction * (length + gap)


def _pedestrians(b, rng, config, s, x_min, x_max, edge, sidewalk_w, corridor):
    """People walking along (or standing on) the sidewalk of side s; none start on top of another."""
    count = int(rng.poisson(6.0 * config.pedestrians * (x_max - x_min) / 100.0))
    placed: list[tuple[float, float]] = []
    for _ in range(count):
        x = rng.uniform(x_min, x_max)
        y = s * (edge + rng.uniform(1.6, max(sidewalk_w - 1.25, 1.6)))
        if any(abs(x - px) < 1.0 and abs(y - py) < 0.9 for px, py in placed):
            continue
        placed.append((x, y))
        moving = rng.random() < 0.8
        heading = (0.0 if rng.random() < 0.5 else np.pi) if moving else rng.uniform(-np.pi, np.pi)
        b.agent("pedestrian", x, y, heading, rng.uniform(0.8, 1.6) if moving else 0.0)


def _cross_traffic(b, rng, config, xc, half, road_edge, y_half):
    """Vehicles stopped in queues on the cross street, waiting at the main road."""
    for s in (-1, 1):
        # right-hand traffic: coming from -y (s = -1) drives +y in the lane at x > xc, and vice versa
        x = xc + (half / 2 if s < 0 else -half / 2)
        heading = np.pi / 2 if s < 0 else -np.pi / 2
        y = s * (road_edge[s] + 3.5)
        for _ in range(int(rng.integers(0, 4))):
            b.agent(str(rng.choice(["car", "car", "truck", "bus"])), x, 0.0, heading, 0.0,
                    attribute="vehicle.stopped")
            length = b.agents[-1].size[1]
            b.agents[-1].origin = np.array([x, y + s * length / 2])
            y += s * (length + rng.uniform(1.5, 4.0))
            if abs(y) > y_half - 15:
                break
