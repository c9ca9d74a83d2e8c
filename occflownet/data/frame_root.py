"""One calibrated frame → a one-keyframe nuScenes-format root, so that the tools that read roots (``labels``,
``prepare``, ``eval``) run on a single recording.

The frame folder holds the six camera images ``CAM_*.jpg`` (or ``.png``), the LiDAR sweep ``lidar.bin`` (nuScenes
``.pcd.bin`` layout: 5 float32 per point, LiDAR frame) and ``calib.json``: the calibration JSON of the ONNX contract
(``cameras.<name>.intrinsic`` 3×3 for the images as stored, ``cameras.<name>.cam2ego`` 4×4) plus ``lidar2ego`` and
``ego2global`` 4×4 (the file in ``../shared/data/nuscenes-frame/`` has this form). No boxes, no lidarseg: label it
with ``occflownet labels --geometry-only``.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from occflownet.occ3d import CAMERAS, LIDAR
from occflownet.contract.images import decode_rgb
from occflownet.data.tables import DatasetError
from occflownet.geometry import matrix_to_quaternion

FRAME_VERSION = "v1.0-frame"


def _token(*parts) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _pose(token: str, T, **extra) -> dict:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DatasetError(f"pose {token}: expected a 4x4 matrix, got shape {T.shape}")
    return {"token": token, **extra, "translation": T[:3, 3].tolist(),
            "rotation": matrix_to_quaternion(T[:3, :3]).tolist()}


def _image(frame: Path, name: str) -> Path:
    for ext in (".jpg", ".jpeg", ".png"):
        if (frame / f"{name}{ext}").is_file():
            return frame / f"{name}{ext}"
    raise DatasetError(f"{frame}: no image {name}.jpg or {name}.png")


def write_frame_root(frame_dir, out, scene: str = "frame-0001", timestamp_us: int = 1_500_000_000_000_000) -> Path:
    """Write the root under ``out`` (version ``FRAME_VERSION``, one scene, one keyframe); returns ``out``.
    DatasetError naming the file when the frame folder lacks a part."""
    frame, root = Path(frame_dir), Path(out)
    calib_path = frame / "calib.json"
    if not calib_path.is_file():
        raise DatasetError(f"{calib_path}: calibration file is missing")
    calib = json.loads(calib_path.read_text())
    for key in ("cameras", "lidar2ego", "ego2global"):
        if key not in calib:
            raise DatasetError(f"{calib_path}: lacks '{key}'")
    if not (frame / "lidar.bin").is_file():
        raise DatasetError(f"{frame / 'lidar.bin'}: LiDAR file is missing")
    sample = _token(scene, "sample")
    t = {name: [] for name in ("scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor",
                               "sample_annotation", "instance", "category", "log")}
    t["log"].append({"token": _token(scene, "log"), "logfile": scene, "vehicle": "", "date_captured": "",
                     "location": ""})
    t["scene"].append({"token": _token(scene), "name": scene, "description": f"frame {frame}", "nbr_samples": 1,
                       "log_token": _token(scene, "log"), "first_sample_token": sample, "last_sample_token": sample})
    t["sample"].append({"token": sample, "timestamp": timestamp_us, "scene_token": _token(scene), "prev": "",
                        "next": ""})
    for ch in (*CAMERAS, LIDAR):
        camera = ch != LIDAR
        src = _image(frame, ch) if camera else frame / "lidar.bin"
        rel = f"samples/{ch}/{scene}__{ch}__{timestamp_us}" + (src.suffix if camera else ".pcd.bin")
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src, root / rel)
        if camera and ch not in calib["cameras"]:
            raise DatasetError(f"{calib_path}: lacks cameras.{ch}")
        cam = calib["cameras"].get(ch, {})
        h, w = (decode_rgb(src.read_bytes()).shape[:2]) if camera else (0, 0)
        t["sensor"].append({"token": _token("sensor", ch), "channel": ch, "modality": "camera" if camera else "lidar"})
        sensor2ego = cam["cam2ego"] if camera else calib["lidar2ego"]
        t["calibrated_sensor"].append(_pose(_token(scene, "calib", ch), sensor2ego, sensor_token=_token("sensor", ch),
                                            camera_intrinsic=cam["intrinsic"] if camera else []))
        t["ego_pose"].append(_pose(_token(scene, "ego", ch), calib["ego2global"], timestamp=timestamp_us))
        t["sample_data"].append({"token": _token(scene, "sd", ch), "sample_token": sample,
                                 "ego_pose_token": _token(scene, "ego", ch),
                                 "calibrated_sensor_token": _token(scene, "calib", ch), "timestamp": timestamp_us,
                                 "fileformat": src.suffix.lstrip(".") if camera else "pcd", "is_key_frame": True,
                                 "height": int(h), "width": int(w), "filename": rel, "prev": "", "next": ""})
    (root / FRAME_VERSION).mkdir(parents=True, exist_ok=True)
    for name, records in t.items():
        (root / FRAME_VERSION / f"{name}.json").write_text(json.dumps(records))
    return root
