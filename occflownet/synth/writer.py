"""nuScenes tables for a synthetic dataset: builds the 13 tables + lidarseg.json in memory, writes them as JSON.

Tokens are 32 hex digits derived from the seed and the record's identity (``token(...)``), so a dataset is
reproducible and every file name that contains a token can be computed before the tables are written.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from occflownet.occ3d import CAMERAS, LIDAR, LIDARSEG_NAMES
from occflownet.geometry import matrix_to_quaternion

TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
          "scene", "sample", "sample_data", "sample_annotation", "map")
ATTRIBUTES = ("vehicle.moving", "vehicle.stopped", "vehicle.parked", "cycle.with_rider", "cycle.without_rider",
              "pedestrian.sitting_lying_down", "pedestrian.standing", "pedestrian.moving")
VISIBILITY = (("1", "v0-40", "visibility of whole object is between 0 and 40%"),
              ("2", "v40-60", "visibility of whole object is between 40 and 60%"),
              ("3", "v60-80", "visibility of whole object is between 60 and 80%"),
              ("4", "v80-100", "visibility of whole object is between 80 and 100%"))


def token(*parts) -> str:
    """Deterministic 32-hex-digit token of the given identity parts."""
    return hashlib.md5("|".join(str(p) for p in parts).encode()).hexdigest()


def visibility_token(fraction: float) -> str:
    """nuScenes visibility token ('1'..'4') of the visible fraction of an object in the cameras."""
    return "1" if fraction < 0.4 else "2" if fraction < 0.6 else "3" if fraction < 0.8 else "4"


def pose_record(tok: str, T: np.ndarray, **extra) -> dict:
    """A record with nuScenes ``translation`` [3] and ``rotation`` quaternion (w, x, y, z) from a 4×4 pose."""
    return {"token": tok, **extra, "translation": [float(v) for v in T[:3, 3]],
            "rotation": [float(v) for v in matrix_to_quaternion(T[:3, :3])]}


def link(records: list[dict]) -> None:
    """Set ``prev``/``next`` of records in sequence order ('' at the ends)."""
    for i, r in enumerate(records):
        r["prev"] = records[i - 1]["token"] if i > 0 else ""
        r["next"] = records[i + 1]["token"] if i + 1 < len(records) else ""


class Tables:
    """The nuScenes tables of one dataset version, filled scene by scene."""

    def __init__(self, seed: int):
        self.seed = seed
        self.t: dict[str, list[dict]] = {name: [] for name in TABLES}
        self.lidarseg: list[dict] = []
        self.t["category"] = [{"token": token("category", n), "name": n, "description": f"nuScenes-lidarseg {n}",
                               "index": i} for i, n in enumerate(LIDARSEG_NAMES)]
        self.t["attribute"] = [{"token": token("attribute", a), "name": a, "description": a} for a in ATTRIBUTES]
        self.t["visibility"] = [{"token": tk, "level": lv, "description": d} for tk, lv, d in VISIBILITY]
        self.t["sensor"] = [{"token": token("sensor", ch), "channel": ch, "modality": "camera"} for ch in CAMERAS]
        self.t["sensor"].append({"token": token("sensor", LIDAR), "channel": LIDAR, "modality": "lidar"})

    def category_token(self, raw: int) -> str:
        return token("category", LIDARSEG_NAMES[raw])

    def attribute_token(self, name: str) -> str:
        if name not in ATTRIBUTES:
            raise ValueError(f"unknown attribute {name!r}")
        return token("attribute", name)

    def write(self, version_dir: Path) -> None:
        version_dir.mkdir(parents=True, exist_ok=True)
        for name in TABLES:
            with open(version_dir / f"{name}.json", "w") as f:
                json.dump(self.t[name], f, indent=0)
        with open(version_dir / "lidarseg.json", "w") as f:
            json.dump(self.lidarseg, f, indent=0)


def calibrated_sensor_records(tables: Tables, scene_key: str, intrinsics: np.ndarray, cam2ego: np.ndarray,
                              lidar2ego: np.ndarray) -> dict[str, str]:
    """Add one calibrated_sensor per channel for a scene; returns channel → token."""
    out = {}
    for c, ch in enumerate(CAMERAS):
        tok = token(tables.seed, scene_key, "calibrated_sensor", ch)
        tables.t["calibrated_sensor"].append(pose_record(
            tok, cam2ego[c], sensor_token=token("sensor", ch),
            camera_intrinsic=[[float(v) for v in row] for row in intrinsics[c]]))
        out[ch] = tok
    tok = token(tables.seed, scene_key, "calibrated_sensor", LIDAR)
    tables.t["calibrated_sensor"].append(pose_record(tok, lidar2ego, sensor_token=token("sensor", LIDAR),
                                                     camera_intrinsic=[]))
    out[LIDAR] = tok
    return out
