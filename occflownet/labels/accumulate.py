"""Accumulate a scene's LiDAR: every return of every sweep, loaded and classified once, then placed in the ego frame
of any keyframe.

Each point is either **static** (kept where it was, in the global frame) or **moves with a box**: a point inside an
annotated box at its sweep's time (the box interpolated between keyframes, ``tracks``) is stored in that box's frame
and placed by the same instance's box at the keyframe being labelled, so a moving car is not smeared along its track
and a parked one collects the points of every sweep. A point with a lidarseg class moves with a box only when it
has the box's class: a road, kerb or barrier return inside a car's grown box stays where it is.

Point classes: keyframe points take their lidarseg class (``occ3d.map_lidarseg``; raw noise and ``vehicle.ego`` are
dropped). A sweep point (no lidarseg in nuScenes) takes the class of the nearest labelled point within
``sweep_label_radius``: the static points compared in the global frame, the points of the box it lies in (if any)
in that box's frame, the nearer deciding whether it stays or moves with the box (``_classify``). Returns from the
recording vehicle itself (``ego_box``) are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occflownet.occ3d import OTHERS, map_lidarseg
from occflownet.data.index import SampleIndex
from occflownet.data.loaders import load_lidar, load_lidarseg
from occflownet.data.sweeps import LidarSweep
from occflownet.geometry import invert, transform_points
from occflownet.labels.config import IGNORED_RAW, UNLABELLED, LabelConfig
from occflownet.labels.tracks import BoxTracks, points_in_boxes


@dataclass
class SceneCloud:
    """All returns of one scene's sweeps (S sweeps, N points, D of them moving with a box), global frame."""

    sweep_time: np.ndarray      # int64 [S] µs
    sweep_origin: np.ndarray    # float64 [S, 3] LiDAR centre, global
    sweep: np.ndarray           # int32 [N] the sweep of each point
    xyz: np.ndarray             # float64 [N, 3] where the point was (global, its sweep's time)
    label: np.ndarray           # uint8 [N] Occ3D class, or UNLABELLED
    moving: np.ndarray          # int64 [D] the points that move with a box
    instance: np.ndarray        # int64 [D] their track in ``tracks``
    local: np.ndarray           # float64 [D, 3] their box-frame coordinates
    tracks: BoxTracks
    unlabelled_sweep_points: int = 0   # static sweep points that no keyframe point within the radius labelled
    _static: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.label)

    def static_rows(self) -> np.ndarray:
        """int64 [N - D]: the points that stay where they are (computed once)."""
        if self._static is None:
            static = np.ones(len(self), bool)
            static[self.moving] = False
            self._static = np.flatnonzero(static)
        return self._static


@dataclass(frozen=True)
class KeyframeCloud:
    """The scene's returns placed in one keyframe's ego frame (M points)."""

    points: np.ndarray       # float64 [M, 3] where each surface is at the keyframe (boxes moved)
    label: np.ndarray        # uint8 [M]
    beam_origin: np.ndarray  # float64 [M, 3] the sensor centre at the point's sweep
    beam_end: np.ndarray     # float64 [M, 3] where the beam ended at that time (static world)


def load_scene_cloud(dataroot, index: SampleIndex, sweeps: list[LidarSweep], start: int, stop: int,
                     config: LabelConfig) -> SceneCloud:
    """Load and classify every sweep of the scene whose keyframes are positions [start, stop) of ``index``."""
    tracks = BoxTracks.from_index(index, start, stop)
    parts = [_load_sweep(dataroot, s, tracks, config) for s in sweeps]
    n = [len(p.label) for p in parts]
    offset = np.cumsum([0] + n[:-1]).astype(np.int64)
    for part, o in zip(parts, offset):
        part.cand.rows = part.cand.rows + o                  # point index within the scene
    cand = _Candidates(*(np.concatenate([getattr(p.cand, f) for p in parts]) if parts else np.zeros((0,) + shape, dt)
                         for f, shape, dt in (("rows", (), np.int64), ("instance", (), np.int64),
                                              ("local", (3,), np.float64), ("above_floor", (), bool))))
    xyz = np.concatenate([p.xyz for p in parts]) if parts else np.zeros((0, 3))
    label = np.concatenate([p.label for p in parts]) if parts else np.zeros(0, np.uint8)
    moves, unlabelled = _classify(xyz, label, cand, tracks, config)
    cloud = SceneCloud(
        sweep_time=np.array([s.timestamp for s in sweeps], np.int64),
        sweep_origin=np.array([s.sensor2global[:3, 3] for s in sweeps], np.float64).reshape(-1, 3),
        sweep=np.repeat(np.arange(len(sweeps), dtype=np.int32), n), xyz=xyz, label=label,
        moving=cand.rows[moves], instance=cand.instance[moves], local=cand.local[moves], tracks=tracks)
    cloud.unlabelled_sweep_points = unlabelled
    return cloud


@dataclass
class _Candidates:
    """Points inside some box at their sweep's time (box grown by the margin): C candidates."""

    rows: np.ndarray         # int64 [C] point index
    instance: np.ndarray     # int64 [C] the box's track
    local: np.ndarray        # float64 [C, 3] box-frame coordinates
    above_floor: np.ndarray  # bool [C] at least ``box_floor`` above the box's bottom face


@dataclass
class _Sweep:
    xyz: np.ndarray
    label: np.ndarray
    cand: _Candidates


def _load_sweep(dataroot, sweep: LidarSweep, tracks: BoxTracks, config: LabelConfig) -> _Sweep:
    """One sweep: its points (global), their classes (lidarseg, or UNLABELLED; OTHERS for geometry only) and the
    points inside a box at the sweep's time."""
    raw_points = load_lidar(dataroot, sweep.path)
    ego = transform_points(sweep.sensor2ego, raw_points[:, :3].astype(np.float64))
    keep = ~_inside(ego, config.ego_box)
    if config.geometry_only:
        label = np.full(len(ego), OTHERS, np.uint8)
    elif sweep.lidarseg_path is not None:
        raw = load_lidarseg(dataroot, sweep.lidarseg_path, len(raw_points))
        keep &= ~np.isin(raw, IGNORED_RAW)
        label = map_lidarseg(raw)
    else:
        label = np.full(len(ego), UNLABELLED, np.uint8)
    xyz = transform_points(sweep.ego2global, ego[keep])
    boxes = tracks.at(sweep.timestamp, config.track_gap)
    which, local = points_in_boxes(xyz, boxes, config.box_margin)
    rows = np.flatnonzero(which >= 0)
    above = local[rows, 2] >= -boxes.half[which[rows], 2] + config.box_floor
    return _Sweep(xyz, label[keep], _Candidates(rows, boxes.instance[which[rows]], local[rows], above))


def _classify(xyz, label, cand: _Candidates, tracks: BoxTracks, config: LabelConfig) -> tuple[np.ndarray, int]:
    """Decide which candidates move with their box (bool [C]) and give the unlabelled points a class in place;
    returns (moves, how many points stay unlabelled).

    A point with a class moves with its box when it has the box's class. A point without one (a sweep point)
    takes the class of the nearest labelled point within ``sweep_label_radius``, comparing the static points in the
    global frame with the points of its candidate box in that box's frame: the nearer decides whether it stays or
    moves. With no labelled neighbour, a candidate at least ``box_floor`` above its box's bottom moves and takes the
    box's class; the rest stay unlabelled (geometry only: every candidate above the floor moves)."""
    box_class = tracks.labels[cand.instance] if len(cand.rows) else np.zeros(0, np.uint8)
    if config.geometry_only:
        return cand.above_floor.copy(), 0
    moves = label[cand.rows] == box_class
    unknown = label == UNLABELLED
    if not unknown.any():
        return moves, 0
    static_known = ~unknown
    static_known[cand.rows[moves]] = False
    d_static, from_static = _nearest(xyz[static_known], xyz[unknown], config.sweep_label_radius)
    static_class = label[static_known]
    cand_unknown = unknown[cand.rows]
    d_box = _nearest_in_boxes(cand, moves, cand_unknown, config.sweep_label_radius)
    slot = np.full(len(label), -1, np.int64)
    slot[np.flatnonzero(unknown)] = np.arange(int(unknown.sum()))
    at = slot[cand.rows[cand_unknown]]                       # each unknown candidate's row among the unknowns
    alone = ~np.isfinite(d_static[at]) & ~np.isfinite(d_box)      # no labelled neighbour either way
    by_box = (d_box < d_static[at]) | (alone & cand.above_floor[cand_unknown])
    moved = np.flatnonzero(cand_unknown)[by_box]
    moves[moved] = True
    label[cand.rows[moved]] = box_class[moved]
    stays = np.isfinite(d_static)
    stays[at[by_box]] = False
    rows = np.flatnonzero(unknown)
    label[rows[stays]] = static_class[from_static[stays]]
    return moves, int((label == UNLABELLED).sum())


def _nearest(source: np.ndarray, query: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance [Q] to the nearest of ``source`` within ``radius`` (inf beyond) and its index."""
    from scipy.spatial import cKDTree

    if len(source) == 0 or len(query) == 0:
        return np.full(len(query), np.inf), np.zeros(len(query), np.int64)
    return cKDTree(source).query(query, distance_upper_bound=radius, workers=-1)


def _nearest_in_boxes(cand: _Candidates, moves: np.ndarray, ask: np.ndarray, radius: float) -> np.ndarray:
    """For the candidates ``ask`` (bool [C]): distance [A] to the nearest moving labelled point of the same box, in
    the box's frame (inf beyond ``radius``)."""
    asked = np.flatnonzero(ask)
    dist = np.full(len(asked), np.inf)
    for i in np.unique(cand.instance[asked]):
        mine = asked[cand.instance[asked] == i]
        known = np.flatnonzero(moves & (cand.instance == i))
        dist[np.searchsorted(asked, mine)] = _nearest(cand.local[known], cand.local[mine], radius)[0]
    return dist


def _inside(points: np.ndarray, ranges) -> np.ndarray:
    """bool [N]: points [N, 3] inside the axis-aligned box ((x0, x1), (y0, y1), (z0, z1))."""
    lo = np.array([r[0] for r in ranges])
    hi = np.array([r[1] for r in ranges])
    return np.all((points >= lo) & (points <= hi), axis=1)


def keyframe_cloud(cloud: SceneCloud, ego2global: np.ndarray, time_us: int, sweeps: np.ndarray) -> KeyframeCloud:
    """The returns of the sweeps ``sweeps`` (bool [S]) in the ego frame ``ego2global`` of the keyframe at
    ``time_us``: static points through the poses, box points by their instance's box at that time (annotated
    or interpolated; points of an instance without a box then are dropped). Static points come first."""
    to_ego = invert(ego2global)
    static = cloud.static_rows()
    if not sweeps.all():
        static = static[sweeps[cloud.sweep[static]]]
    boxes = cloud.tracks.at(time_us)
    slot = np.full(len(cloud.tracks), -1, np.int64)
    slot[boxes.instance] = np.arange(len(boxes))
    box = slot[cloud.instance]                                  # [D] the instance's box now, -1: none
    keep = np.flatnonzero((box >= 0) & sweeps[cloud.sweep[cloud.moving]])
    rows = np.concatenate([static, cloud.moving[keep]])
    beam_end = transform_points(to_ego, cloud.xyz[rows])
    points = beam_end.copy()
    T = to_ego @ boxes.box2global[box[keep]]                    # box → current ego, [m, 4, 4]
    points[len(static):] = np.einsum("mij,mj->mi", T[:, :3, :3], cloud.local[keep]) + T[:, :3, 3]
    origin = transform_points(to_ego, cloud.sweep_origin)
    return KeyframeCloud(points=points, label=cloud.label[rows], beam_origin=origin[cloud.sweep[rows]],
                         beam_end=beam_end)
