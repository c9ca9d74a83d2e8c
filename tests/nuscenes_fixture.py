"""A tiny hand-built nuScenes-format root with known geometry, for the data reader and ray tests.

World (global frame, offset far from the origin like real nuScenes maps):
- static points on a few walls and the ground, with raw lidarseg labels (manmade, barrier, driveable, static.other);
- a moving car (raw 17) and a walking pedestrian (raw 2), with sample_annotation boxes and instances;
- a bicycle (raw 14, Occ3D 2: *not* in the dynamic filter set) standing still;
- a few returns on the ego car itself (raw 31, 'vehicle.ego').
Between consecutive keyframes the LiDAR also records ``LIDAR_SWEEPS`` non-keyframe sweeps (``sweeps/LIDAR_TOP``, no
lidarseg, like nuScenes), which the sample index ignores and the label pipeline accumulates.
The ego drives a curve with some pitch and roll; each camera fires at its own time (up to ±75 ms from the LiDAR),
so a reader that used the LiDAR's ego pose for a camera would misplace that camera by up to ~0.7 m.
Scene ``scene-a`` has 5 keyframes and Occ3D labels; ``scene-b`` has 2 keyframes, no ``gts`` directory.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from occflownet.occ3d import CAMERAS, LIDAR
from occflownet.geometry import invert, make_transform, matrix_to_quaternion, transform_points, yaw_to_quaternion
from occflownet.rig import default_rig

VERSION = "v1.0-fixture"
IMAGE_SIZE = (1600, 900)
LIDAR2EGO = make_transform(np.array([0.7071, 0.0, 0.0, -0.7071]), [0.94, 0.0, 1.84])  # rotated -90° like nuScenes
ORIGIN = np.array([411.3, 1180.9, 0.0])  # global position of the trajectory start
CAMERA_DELAY_US = [-75_000, -45_000, -15_000, 15_000, 45_000, 75_000]  # camera time - LiDAR time
KEYFRAME_US = 500_000
LIDAR_SWEEPS = 2  # non-keyframe LiDAR sweeps between consecutive keyframes
SCENES = (("scene-a", 5, 1_533_000_000_000_000), ("scene-b", 2, 1_533_100_000_000_000))
# returns from the ego car's bonnet (ego frame), seen by CAM_FRONT; labelled 'vehicle.ego'
EGO_BODY_POINTS = np.array([[3.9, 0.0, 0.9], [3.9, 0.3, 1.0], [-1.0, -0.5, 0.6]])
RAW_MANMADE, RAW_BARRIER, RAW_DRIVEABLE, RAW_OTHER, RAW_CAR, RAW_PED, RAW_BIKE, RAW_EGO = 28, 9, 24, 29, 17, 2, 14, 31


def token(*parts) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def ego_pose(scene: int, time_us: int) -> np.ndarray:
    """ego → global at ``time_us``: a curve at ~8 m/s, turning, with small pitch/roll."""
    s = (time_us - SCENES[scene][2]) / 1e6
    yaw = 0.3 + 0.12 * s
    pos = ORIGIN + [8.0 * s * np.cos(0.3 + 0.06 * s), 8.0 * s * np.sin(0.3 + 0.06 * s), 0.1 * s]
    pitch, roll = 0.02 * np.sin(s), -0.015 * np.cos(s)
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    R = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) \
        @ np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return make_transform(R, pos)


def static_points() -> tuple[np.ndarray, np.ndarray]:
    """Global static points [P, 3] float64 and their raw lidarseg labels [P] uint8 (deterministic)."""
    rng = np.random.default_rng(7)
    parts, labels = [], []
    heading = np.array([np.cos(0.35), np.sin(0.35), 0.0])
    side = np.array([-heading[1], heading[0], 0.0])
    for offset, raw in ((12.0, RAW_MANMADE), (-10.0, RAW_MANMADE), (6.0, RAW_BARRIER), (-5.0, RAW_OTHER)):
        n = 500
        along = rng.uniform(-30, 50, n)
        height = rng.uniform(0.1, 4.0 if raw == RAW_MANMADE else 1.0, n)
        parts.append(ORIGIN + along[:, None] * heading + offset * side + height[:, None] * [0, 0, 1])
        labels.append(np.full(n, raw))
    ground = ORIGIN + rng.uniform(-30, 50, (800, 1)) * heading + rng.uniform(-9, 11, (800, 1)) * side
    ground[:, 2] = ORIGIN[2] + 0.02
    parts.append(ground)
    labels.append(np.full(len(ground), RAW_DRIVEABLE))
    bike = ORIGIN + 18.0 * heading + 3.5 * side + rng.uniform(-0.4, 0.4, (60, 3)) + [0, 0, 0.6]
    parts.append(bike)
    labels.append(np.full(len(bike), RAW_BIKE))
    return np.concatenate(parts), np.concatenate(labels).astype(np.uint8)


# name, category, raw label, size (w, l, h), box pose as a function of seconds since the scene start
def _car_pose(s):
    return ORIGIN + [20.0 + 11.0 * s, 4.0 + 2.0 * s, 0.8], 0.2


def _ped_pose(s):
    return ORIGIN + [12.0, -3.0 + 1.4 * s, 0.9], np.pi / 2


MOVERS = (("car", "vehicle.car", RAW_CAR, (1.9, 4.5, 1.6), _car_pose),
          ("ped", "human.pedestrian.adult", RAW_PED, (0.6, 0.7, 1.8), _ped_pose))


def mover_box(mover, s) -> np.ndarray:
    """box → global 4×4 of a mover at ``s`` seconds since its scene's start."""
    centre, yaw = mover[4](s)
    return make_transform(yaw_to_quaternion(yaw), centre)


def mover_points(mover) -> np.ndarray:
    """Points on the mover's surface in its box frame [M, 3] (deterministic)."""
    rng = np.random.default_rng(sum(map(ord, mover[0])))
    w, l, h = mover[3]
    local = rng.uniform(-0.5, 0.5, (120, 3)) * [l, w, h]
    face = rng.integers(0, 3, 120)
    local[np.arange(120), face] = np.sign(local[np.arange(120), face]) * np.array([l, w, h])[face] / 2
    return local


@dataclass
class Fixture:
    root: Path
    version: str
    sample_tokens: dict = field(default_factory=dict)   # scene name → [sample tokens]
    static: np.ndarray = None                           # [P, 3] global
    static_raw: np.ndarray = None                       # [P]

    def lidar_time(self, scene: int, k: int) -> int:
        return SCENES[scene][2] + k * KEYFRAME_US

    def points_global(self, scene: int, k: float) -> tuple[np.ndarray, np.ndarray]:
        """The world as the LiDAR saw it at keyframe k (fractional k: a sweep between keyframes): global points
        [N, 3] and raw labels [N] (no ego points)."""
        s = k * KEYFRAME_US / 1e6
        pts, raw = [self.static], [self.static_raw]
        for mover in MOVERS:
            pts.append(transform_points(mover_box(mover, s), mover_points(mover)))
            raw.append(np.full(len(pts[-1]), mover[2], dtype=np.uint8))
        return np.concatenate(pts), np.concatenate(raw)


def _image(path: Path, colour) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((IMAGE_SIZE[1], IMAGE_SIZE[0], 3), dtype=np.uint8)
    img[:] = colour[::-1]  # BGR on disk
    cv2.imwrite(str(path), img)


def write_fixture(root, version: str = VERSION, write_images: bool = True) -> Fixture:
    """Write the fixture root under ``root``; returns its ground truth. ``write_images=False`` leaves out the
    camera images and the Occ3D labels (for tests of the tables alone)."""
    root = Path(root)
    fx = Fixture(root=root, version=version)
    fx.static, fx.static_raw = static_points()
    rig = default_rig(*IMAGE_SIZE)
    t = {name: [] for name in ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor",
                               "sample_annotation", "instance", "category", "lidarseg", "log")}
    categories = sorted({m[1] for m in MOVERS})
    for i, name in enumerate(categories):
        t["category"].append({"token": token("cat", name), "name": name, "description": "", "index": i})
    channels = (*CAMERAS, LIDAR, "RADAR_FRONT")
    for ch in channels:
        t["sensor"].append({"token": token("sensor", ch), "channel": ch,
                            "modality": "camera" if ch.startswith("CAM") else ch.split("_")[0].lower()})
        if ch.startswith("CAM"):
            T = np.asarray(rig["cameras"][ch]["cam2ego"])
            K = rig["cameras"][ch]["intrinsic"]
        else:
            T, K = (LIDAR2EGO if ch == LIDAR else np.eye(4)), []
        t["calibrated_sensor"].append({"token": token("calib", ch), "sensor_token": token("sensor", ch),
                                       "translation": T[:3, 3].tolist(), "rotation": _quat(T),
                                       "camera_intrinsic": K})
    t["log"].append({"token": token("log"), "logfile": "fixture", "vehicle": "v", "date_captured": "2018-08-01",
                     "location": "singapore-onenorth"})
    for si, (scene, n, start) in enumerate(SCENES):
        tokens = [token(scene, "sample", k) for k in range(n)]
        fx.sample_tokens[scene] = tokens
        t["scene"].append({"token": token("scene", scene), "name": scene, "description": "", "log_token": token("log"),
                           "nbr_samples": n, "first_sample_token": tokens[0], "last_sample_token": tokens[-1]})
        for m in MOVERS:
            t["instance"].append({"token": token(scene, m[0]), "category_token": token("cat", m[1]),
                                  "nbr_annotations": n})
        for k, tok in enumerate(reversed(tokens)):  # written in reverse time order: the reader must sort
            k = n - 1 - k
            _write_sample(fx, t, si, k, tok, tokens, rig, write_images)
    vdir = root / version
    vdir.mkdir(parents=True, exist_ok=True)
    for name, records in t.items():
        (vdir / f"{name}.json").write_text(json.dumps(records))
    return fx


def _write_sample(fx: Fixture, t: dict, si: int, k: int, tok: str, tokens: list, rig: dict, images: bool) -> None:
    scene = SCENES[si][0]
    lidar_us = fx.lidar_time(si, k)
    t["sample"].append({"token": tok, "timestamp": lidar_us, "scene_token": token("scene", scene),
                        "prev": tokens[k - 1] if k else "", "next": tokens[k + 1] if k + 1 < len(tokens) else ""})
    for c, ch in enumerate((*CAMERAS, LIDAR)):
        time_us = lidar_us + (CAMERA_DELAY_US[c] if c < 6 else 0)
        sd = token(scene, k, ch)
        t["ego_pose"].append({"token": token("ego", sd), "timestamp": time_us,
                              "translation": ego_pose(si, time_us)[:3, 3].tolist(),
                              "rotation": _quat(ego_pose(si, time_us))})
        fname = f"samples/{ch}/{scene}__{ch}__{time_us}." + ("jpg" if c < 6 else "pcd.bin")
        rec = {"token": sd, "sample_token": tok, "ego_pose_token": token("ego", sd),
               "calibrated_sensor_token": token("calib", ch), "timestamp": time_us, "fileformat": fname[-3:],
               "is_key_frame": True, "height": IMAGE_SIZE[1] if c < 6 else 0, "width": IMAGE_SIZE[0] if c < 6 else 0,
               "filename": fname, "prev": "", "next": ""}
        t["sample_data"].append(rec)
        if c < 6:
            if images:
                _image(fx.root / fname, (40 * c, 255 - 40 * c, 128))
            # a non-keyframe sweep of the same camera: must be ignored by the reader
            t["sample_data"].append({**rec, "token": token(sd, "sweep"), "is_key_frame": False,
                                     "timestamp": time_us + 80_000, "filename": "sweeps/" + fname[8:]})
    radar = token(scene, k, "RADAR_FRONT")
    t["ego_pose"].append({"token": token("ego", radar), "timestamp": lidar_us,
                          "translation": ego_pose(si, lidar_us)[:3, 3].tolist(), "rotation": _quat(ego_pose(si, lidar_us))})
    t["sample_data"].append({"token": radar, "sample_token": tok, "ego_pose_token": token("ego", radar),
                             "calibrated_sensor_token": token("calib", "RADAR_FRONT"), "timestamp": lidar_us,
                             "fileformat": "pcd", "is_key_frame": True, "height": 0, "width": 0,
                             "filename": f"samples/RADAR_FRONT/{scene}_{k}.pcd", "prev": "", "next": ""})
    _write_lidar(fx, t, si, k, scene, lidar_us)
    if k + 1 < len(tokens):
        _write_lidar_sweeps(fx, t, si, k, scene, tokens)
    # boxes
    for m in MOVERS:
        box = mover_box(m, k * KEYFRAME_US / 1e6)
        t["sample_annotation"].append({
            "token": token(scene, k, m[0], "ann"), "sample_token": tok, "instance_token": token(scene, m[0]),
            "translation": box[:3, 3].tolist(), "size": list(m[3]), "rotation": _quat(box),
            "visibility_token": "4", "attribute_tokens": [], "num_lidar_pts": 120, "num_radar_pts": 0,
            "prev": "", "next": ""})
    # Occ3D labels for scene-a only
    if scene == "scene-a" and images:
        occ = fx.root / "gts" / scene / tok / "labels.npz"
        occ.parent.mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng(k)
        sem = rng.integers(0, 18, (200, 200, 16)).astype(np.uint8)
        np.savez(occ, semantics=sem, mask_lidar=(sem < 9).astype(np.uint8),
                            mask_camera=(sem < 12).astype(np.uint8))


def _sweep_file(fx: Fixture, si: int, k: float, path: Path) -> np.ndarray:
    """Write the LiDAR sweep at keyframe k (fractional: between keyframes) to ``path``, in the LiDAR frame with the
    ego-body points last; returns the raw labels of its points."""
    pts, raw = fx.points_global(si, k)
    lidar2global = ego_pose(si, SCENES[si][2] + round(k * KEYFRAME_US)) @ LIDAR2EGO
    local = transform_points(invert(lidar2global), pts)
    ego_body = transform_points(invert(LIDAR2EGO), EGO_BODY_POINTS)
    local = np.concatenate([local, ego_body])
    sweep = np.zeros((len(local), 5), dtype=np.float32)
    sweep[:, :3] = local
    sweep[:, 4] = np.arange(len(local)) % 32
    path.parent.mkdir(parents=True, exist_ok=True)
    sweep.tofile(path)
    return np.concatenate([raw, np.full(3, RAW_EGO, dtype=np.uint8)])


def _write_lidar_sweeps(fx: Fixture, t: dict, si: int, k: int, scene: str, tokens: list) -> None:
    """The non-keyframe LiDAR sweeps between keyframes k and k + 1 (no lidarseg; each belongs to the nearer one)."""
    for j in range(1, LIDAR_SWEEPS + 1):
        frac = j / (LIDAR_SWEEPS + 1)
        time_us = fx.lidar_time(si, k) + round(frac * KEYFRAME_US)
        sd = token(scene, k, LIDAR, "sweep", j)
        fname = f"sweeps/{LIDAR}/{scene}__{LIDAR}__{time_us}.pcd.bin"
        _sweep_file(fx, si, k + frac, fx.root / fname)
        t["ego_pose"].append({"token": token("ego", sd), "timestamp": time_us,
                              "translation": ego_pose(si, time_us)[:3, 3].tolist(),
                              "rotation": _quat(ego_pose(si, time_us))})
        t["sample_data"].append({"token": sd, "sample_token": tokens[k] if frac <= 0.5 else tokens[k + 1],
                                 "ego_pose_token": token("ego", sd),
                                 "calibrated_sensor_token": token("calib", LIDAR),
                                 "timestamp": time_us, "fileformat": "pcd", "is_key_frame": False, "height": 0,
                                 "width": 0, "filename": fname, "prev": "", "next": ""})


def _write_lidar(fx: Fixture, t: dict, si: int, k: int, scene: str, lidar_us: int) -> None:
    """The LiDAR sweep of keyframe k (in the LiDAR frame, with the ego-body points) and its lidarseg labels."""
    lidar_sd = token(scene, k, LIDAR)
    raw = _sweep_file(fx, si, k, fx.root / f"samples/{LIDAR}/{scene}__{LIDAR}__{lidar_us}.pcd.bin")
    seg = f"lidarseg/{fx.version}/{lidar_sd}_lidarseg.bin"
    (fx.root / seg).parent.mkdir(parents=True, exist_ok=True)
    raw.astype(np.uint8).tofile(fx.root / seg)
    t["lidarseg"].append({"token": lidar_sd, "sample_data_token": lidar_sd, "filename": seg})


def _quat(T) -> list:
    return matrix_to_quaternion(np.asarray(T)[:3, :3]).tolist()


def visible_hits(fx: Fixture, scene: int, k: int) -> np.ndarray:
    """int [N]: for each true point of keyframe k (``points_global`` order), in how many camera images it falls
    while inside the grid of keyframe k's ego frame; computed from the fixture's own poses, not the reader's."""
    from occflownet.occ3d import GRID

    pts, _ = fx.points_global(scene, k)
    lidar_us = fx.lidar_time(scene, k)
    inside = GRID.contains(transform_points(invert(ego_pose(scene, lidar_us)), pts))
    rig = default_rig(*IMAGE_SIZE)
    hits = np.zeros(len(pts), dtype=np.int64)
    for c, name in enumerate(CAMERAS):
        cam2global = ego_pose(scene, lidar_us + CAMERA_DELAY_US[c]) @ np.asarray(rig["cameras"][name]["cam2ego"])
        p = transform_points(invert(cam2global), pts)
        K = np.asarray(rig["cameras"][name]["intrinsic"])
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
            v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
        hits += (p[:, 2] >= 0.05) & (u >= 0) & (u < IMAGE_SIZE[0]) & (v >= 0) & (v < IMAGE_SIZE[1]) & inside
    return hits


_WRITTEN: dict = {}


@pytest.fixture(scope="session")
def fixture_world(tmp_path_factory) -> Fixture:
    """The fixture root with images and Occ3D labels, written once per test session (treat as read-only)."""
    if "world" not in _WRITTEN:
        _WRITTEN["world"] = write_fixture(tmp_path_factory.mktemp("nuscenes_fixture"))
    return _WRITTEN["world"]
