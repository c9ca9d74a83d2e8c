"""Build a :class:`SampleIndex` from the JSON tables of a nuScenes-format root (done once, by ``prepare``).

Broken references are errors naming the table, token and field; no sample is skipped. Occupancy ground truth
(Occ3D ``gts/<scene name>/<sample token>/labels.npz``) is optional per scene: a scene without a
``gts/<scene name>/`` directory gets no occupancy path, but inside such a directory every keyframe must have its
``labels.npz``.
"""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from occflownet.occ3d import CAMERAS, LIDAR, category_to_occ3d
from occflownet.data.index import MINI_SPLITS, SampleIndex
from occflownet.data.tables import DatasetError, Tables, field, load_tables
from occflownet.geometry import make_transform

CHANNELS = (*CAMERAS, LIDAR)


def pose_matrix(record: dict, table: str) -> np.ndarray:
    """4×4 child→parent from a record's ``rotation`` (w, x, y, z) and ``translation``."""
    rot = np.asarray(field(record, table, "rotation"), dtype=np.float64)
    trans = np.asarray(field(record, table, "translation"), dtype=np.float64)
    if rot.shape != (4,) or trans.shape != (3,) or not (np.isfinite(rot).all() and np.isfinite(trans).all()):
        raise DatasetError(f"table '{table}': record {record.get('token')} has a malformed rotation/translation")
    if abs(np.linalg.norm(rot) - 1.0) > 1e-3:
        raise DatasetError(f"table '{table}': record {record.get('token')} has a non-unit rotation quaternion")
    return make_transform(rot, trans)


def channel_of_calibration(tables: Tables) -> dict[str, str]:
    """calibrated_sensor token → sensor channel (e.g. LIDAR_TOP), each reference checked."""
    channel_of_sensor = {t: field(r, "sensor", "channel") for t, r in tables.by_token("sensor").items()}
    channel_of_calib = {}
    for token, r in tables.by_token("calibrated_sensor").items():
        sensor = field(r, "calibrated_sensor", "sensor_token")
        if sensor not in channel_of_sensor:
            raise DatasetError(f"calibrated_sensor {token} refers to sensor token {sensor!r}, which table 'sensor' lacks")
        channel_of_calib[token] = channel_of_sensor[sensor]
    return channel_of_calib


def _keyframe_data(tables: Tables) -> dict[tuple[str, str], dict]:
    """(sample token, channel) → keyframe sample_data record, for the six cameras and the LiDAR."""
    channel_of_calib = channel_of_calibration(tables)
    out: dict[tuple[str, str], dict] = {}
    for r in tables.records["sample_data"]:
        if not field(r, "sample_data", "is_key_frame"):
            continue
        calib = field(r, "sample_data", "calibrated_sensor_token")
        if calib not in channel_of_calib:
            raise DatasetError(f"sample_data {r.get('token')} refers to calibrated_sensor token {calib!r}, "
                               f"which table 'calibrated_sensor' lacks")
        channel = channel_of_calib[calib]
        if channel not in CHANNELS:
            continue
        key = (field(r, "sample_data", "sample_token"), channel)
        if key in out:
            raise DatasetError(f"sample {key[0]} has two keyframe sample_data records for {channel}: "
                               f"{out[key]['token']} and {r.get('token')}")
        out[key] = r
    return out


def _splits(dataroot: Path, version: str, scene_names: list[str]) -> dict[str, list[str]]:
    """'all', plus ``<version>/splits.json`` when present, else the built-in v1.0-mini splits."""
    splits = {"all": list(scene_names)}
    path = dataroot / version / "splits.json"
    if path.is_file():
        try:
            named = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise DatasetError(f"{path}: not valid JSON ({e})") from e
        if not isinstance(named, dict) or not all(isinstance(v, list) and all(isinstance(n, str) for n in v)
                                                  for v in named.values()):
            raise DatasetError(f"{path}: must map split names to lists of scene names")
        if "all" in named:
            raise DatasetError(f"{path}: the split name 'all' is reserved (every scene)")
        splits.update(named)
    elif version == "v1.0-mini":
        splits.update(MINI_SPLITS)
        splits["train"], splits["val"] = MINI_SPLITS["mini_train"], MINI_SPLITS["mini_val"]
    return splits


def _occupancy_path(dataroot: Path, scene: str, token: str) -> str:
    """Relative Occ3D labels path of a sample, '' when its scene has no gts directory (error if the file lacks)."""
    scene_dir = dataroot / "gts" / scene
    if not scene_dir.is_dir():
        return ""
    rel = f"gts/{scene}/{token}/labels.npz"
    if not (dataroot / rel).is_file():
        raise DatasetError(f"{dataroot / rel}: Occ3D labels missing for sample {token} (its scene directory "
                           f"{scene_dir} exists)")
    return rel


def build_index(dataroot, version: str | None = None, verify_files: bool = False) -> SampleIndex:
    """Read the tables of ``DATAROOT/<version>`` and index every keyframe of every scene.

    ``verify_files``: also check that every image, LiDAR and lidarseg file exists (one error listing the missing
    ones). Without it, a missing data file is reported when it is loaded."""
    return index_from_tables(load_tables(dataroot, version), verify_files=verify_files)


def index_from_tables(tables: Tables, verify_files: bool = False, occupancy: bool = True) -> SampleIndex:
    """``build_index`` on tables already read. ``occupancy=False``: do not look for Occ3D labels (every
    ``occupancy_path`` empty), for the label pipeline, which runs before they exist (or while they are half
    written)."""
    dataroot = tables.dataroot
    version = tables.version
    keyframes = _keyframe_data(tables)
    lidarseg = _lidarseg_files(tables)
    samples_of_scene, boxes_of_sample = _group_samples_and_boxes(tables)
    cols = defaultdict(list)
    instance_ids, category_ids = {}, {}
    scene_names, scene_tokens, scene_start = [], [], [0]
    for scene in tables.records["scene"]:
        scene_token, name = field(scene, "scene", "token"), field(scene, "scene", "name")
        samples = sorted(samples_of_scene.get(scene_token, []), key=lambda r: field(r, "sample", "timestamp"))
        if not samples:
            raise DatasetError(f"scene {name} ({scene_token}) has no samples in table 'sample'")
        for s in samples:
            token = field(s, "sample", "token")
            cols["sample_token"].append(token)
            cols["sample_timestamp"].append(s["timestamp"])
            cols["sample_scene"].append(len(scene_names))
            _add_sensors(cols, tables, keyframes, token, name, lidarseg)
            cols["occupancy_path"].append(_occupancy_path(dataroot, name, token) if occupancy else "")
            for box in boxes_of_sample.get(token, []):
                _add_box(cols, tables, box, instance_ids, category_ids)
            cols["box_start"].append(len(cols["box_label"]))
        scene_names.append(name)
        scene_tokens.append(scene_token)
        scene_start.append(len(cols["sample_token"]))
    if len(set(scene_names)) != len(scene_names):
        raise DatasetError(f"{dataroot / version / 'scene.json'}: scene names are not unique")

    arrays = _to_arrays(cols, scene_names, scene_tokens, scene_start, instance_ids, category_ids)
    index = SampleIndex(version, arrays, _splits(dataroot, version, scene_names),
                        {"table_sizes": tables.table_sizes()})
    if verify_files:
        missing = index.missing_files(dataroot)
        if missing:
            shown = "\n  ".join(missing[:10])
            raise DatasetError(f"{len(missing)} file(s) referenced by {dataroot / version} are missing, e.g.:\n  {shown}")
    return index


def _lidarseg_files(tables: Tables) -> dict[str, str]:
    """{LiDAR sample_data token: lidarseg label file} (empty without the lidarseg table)."""
    lidarseg = {}
    if tables.has("lidarseg"):
        for r in tables.records["lidarseg"]:
            sd = field(r, "lidarseg", "sample_data_token")
            if sd in lidarseg:
                raise DatasetError(f"table 'lidarseg': two label files for sample_data {sd}")
            lidarseg[sd] = field(r, "lidarseg", "filename")
    return lidarseg


def _group_samples_and_boxes(tables: Tables) -> tuple[dict, dict]:
    """({scene token: [sample records]}, {sample token: [annotation records]}), each reference checked."""
    samples_of_scene = defaultdict(list)
    for r in tables.records["sample"]:
        scene = field(r, "sample", "scene_token")
        tables.get("scene", scene, f"sample {r.get('token')}")
        samples_of_scene[scene].append(r)
    boxes_of_sample = defaultdict(list)
    for r in tables.records["sample_annotation"]:
        boxes_of_sample[field(r, "sample_annotation", "sample_token")].append(r)
    for token in boxes_of_sample:
        tables.get("sample", token, f"sample_annotation of sample {token}")
    return samples_of_scene, boxes_of_sample


def _add_sensors(cols, tables: Tables, keyframes, token: str, scene: str, lidarseg: dict) -> None:
    cam_cols = defaultdict(list)
    for channel in CHANNELS:
        sd = keyframes.get((token, channel))
        if sd is None:
            raise DatasetError(f"sample {token} (scene {scene}) has no keyframe sample_data for {channel}")
        where = f"sample_data {field(sd, 'sample_data', 'token')} ({channel} of sample {token})"
        calib = tables.get("calibrated_sensor", sd["calibrated_sensor_token"], where)
        ego = tables.get("ego_pose", field(sd, "sample_data", "ego_pose_token"), where)
        prefix = "lidar" if channel == LIDAR else "cam"
        group = cols if channel == LIDAR else cam_cols
        group[f"{prefix}_token"].append(sd["token"])
        group[f"{prefix}_path"].append(field(sd, "sample_data", "filename"))
        group[f"{prefix}_sensor2ego"].append(pose_matrix(calib, "calibrated_sensor"))
        group[f"{prefix}_ego2global"].append(pose_matrix(ego, "ego_pose"))
        group[f"{prefix}_timestamp"].append(field(sd, "sample_data", "timestamp"))
        if channel == LIDAR:
            cols["lidarseg_path"].append(lidarseg.get(sd["token"], ""))
            continue
        K = np.asarray(field(calib, "calibrated_sensor", "camera_intrinsic"), dtype=np.float64)
        if K.shape != (3, 3) or abs(np.linalg.det(K)) < 1e-9:
            raise DatasetError(f"calibrated_sensor {calib['token']} ({channel}): camera_intrinsic must be an "
                               f"invertible 3x3 matrix")
        size = (int(field(sd, "sample_data", "width")), int(field(sd, "sample_data", "height")))
        if min(size) <= 0:
            raise DatasetError(f"{where}: image width/height must be positive, got {size}")
        cam_cols["cam_intrinsic"].append(K)
        cam_cols["cam_size"].append(size)
    for key, values in cam_cols.items():
        cols[key].append(values)


def _add_box(cols, tables: Tables, box: dict, instance_ids: dict, category_ids: dict) -> None:
    where = f"sample_annotation {box.get('token')}"
    instance_token = field(box, "sample_annotation", "instance_token")
    instance = tables.get("instance", instance_token, where)
    category = tables.get("category", field(instance, "instance", "category_token"), f"instance {instance_token}")
    name = field(category, "category", "name")
    pose = pose_matrix(box, "sample_annotation")  # validates rotation/translation
    size = np.asarray(field(box, "sample_annotation", "size"), dtype=np.float64)
    if size.shape != (3,) or not (size > 0).all():
        raise DatasetError(f"{where}: size must be 3 positive numbers (w, l, h), got {size.tolist()}")
    cols["box_instance"].append(instance_ids.setdefault(instance_token, len(instance_ids)))
    cols["box_category"].append(category_ids.setdefault(name, len(category_ids)))
    cols["box_label"].append(category_to_occ3d(name))
    cols["box_translation"].append(pose[:3, 3])
    cols["box_size"].append(size)
    cols["box_rotation"].append(np.asarray(box["rotation"], dtype=np.float64) / np.linalg.norm(box["rotation"]))


def _bytes(values) -> np.ndarray:
    return np.array([v.encode("utf-8") for v in values], dtype="S") if len(values) else np.zeros(0, dtype="S1")


def _to_arrays(cols, scene_names, scene_tokens, scene_start, instance_ids, category_ids) -> dict[str, np.ndarray]:
    S = len(cols["sample_token"])

    def floats(key, shape):
        return np.asarray(cols[key], dtype=np.float64).reshape(shape)

    def flat(key):
        return [v for row in cols[key] for v in row]

    return {
        "scene_name": _bytes(scene_names), "scene_token": _bytes(scene_tokens),
        "scene_start": np.asarray(scene_start, dtype=np.int64),
        "sample_token": _bytes(cols["sample_token"]),
        "sample_timestamp": np.asarray(cols["sample_timestamp"], dtype=np.int64),
        "sample_scene": np.asarray(cols["sample_scene"], dtype=np.int64),
        "cam_token": _bytes(flat("cam_token")).reshape(S, 6),
        "cam_path": _bytes(flat("cam_path")).reshape(S, 6),
        "cam_intrinsic": floats("cam_intrinsic", (S, 6, 3, 3)),
        "cam_sensor2ego": floats("cam_sensor2ego", (S, 6, 4, 4)),
        "cam_ego2global": floats("cam_ego2global", (S, 6, 4, 4)),
        "cam_timestamp": np.asarray(cols["cam_timestamp"], dtype=np.int64).reshape(S, 6),
        "cam_size": np.asarray(cols["cam_size"], dtype=np.int64).reshape(S, 6, 2),
        "lidar_token": _bytes(cols["lidar_token"]), "lidar_path": _bytes(cols["lidar_path"]),
        "lidar_sensor2ego": floats("lidar_sensor2ego", (S, 4, 4)),
        "lidar_ego2global": floats("lidar_ego2global", (S, 4, 4)),
        "lidar_timestamp": np.asarray(cols["lidar_timestamp"], dtype=np.int64),
        "lidarseg_path": _bytes(cols["lidarseg_path"]), "occupancy_path": _bytes(cols["occupancy_path"]),
        "box_start": np.asarray([0] + cols["box_start"], dtype=np.int64),
        "box_instance": np.asarray(cols["box_instance"], dtype=np.int64),
        "instance_token": _bytes(list(instance_ids)),
        "box_category": np.asarray(cols["box_category"], dtype=np.int64),
        "category_name": _bytes(list(category_ids)),
        "box_label": np.asarray(cols["box_label"], dtype=np.uint8),
        "box_translation": floats("box_translation", (-1, 3)), "box_size": floats("box_size", (-1, 3)),
        "box_rotation": floats("box_rotation", (-1, 4)),
    }
