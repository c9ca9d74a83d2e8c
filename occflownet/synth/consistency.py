"""Consistency checks of a synthetic world: do LiDAR labels, Occ3D voxels and camera depth agree?

Images, LiDAR and the geometric truth come from one geometry, so they should. Two measurements, used by
``tests/test_synth_consistency.py`` (thresholds) and ``benchmarks/studies/synth_consistency.py`` (the figures in
docs/results.md):

- ``lidar_label_agreement(root, version)``: read back from the files on disk, each keyframe LiDAR point moved LiDAR →
  ego with its calibrated_sensor, its mapped lidarseg class against the class of the voxel it falls in in the
  keyframe's geometric truth (``truth/<scene>/<sample token>/semantics.npz``; the benchmark labels in ``gts/`` are
  made from these points, so comparing with them would say little);
- ``lidar_camera_depths(world, rig, t0_us, seed, scene_index, frames)``: in memory, each LiDAR point projected into
  each camera (LiDAR → ego at LiDAR time → global → ego at camera time → camera), its z-depth against the depth of
  the camera ray through its exact projection and against the rendered depth of the pixel it falls in.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from occflownet.geometry import make_transform, transform_points
from occflownet.occ3d import GRID, map_lidarseg
from occflownet.synth.camera import cast_rays
from occflownet.synth.frame import render_keyframe
from occflownet.synth.generate import load_truth
from occflownet.synth.preview import project_points

_TABLES = ("sample", "sample_data", "calibrated_sensor", "sensor", "scene", "lidarseg")


def lidar_label_agreement(root, version: str) -> tuple[np.ndarray, np.ndarray]:
    """(point classes uint8 [N], voxel classes at the points uint8 [N]) over every keyframe LiDAR sweep of a
    dataset written by ``generate``, for the points inside the grid: the raw lidarseg index mapped to Occ3D
    (``occ3d.map_lidarseg``) and the geometric truth of the keyframe at the point's voxel."""
    root = Path(root)
    t = {n: json.loads((root / version / f"{n}.json").read_text()) for n in _TABLES}
    cs = {r["token"]: r for r in t["calibrated_sensor"]}
    lidar_sensor = next(s["token"] for s in t["sensor"] if s["channel"] == "LIDAR_TOP")
    scene_name = {s["token"]: s["name"] for s in t["scene"]}
    sample = {s["token"]: s for s in t["sample"]}
    seg = {r["sample_data_token"]: r["filename"] for r in t["lidarseg"]}
    own, vox = [], []
    for sd in t["sample_data"]:
        calib = cs[sd["calibrated_sensor_token"]]
        if calib["sensor_token"] != lidar_sensor or not sd["is_key_frame"]:
            continue
        pts = np.fromfile(root / sd["filename"], dtype=np.float32).reshape(-1, 5)
        raw = np.fromfile(root / seg[sd["token"]], dtype=np.uint8)
        ego = transform_points(make_transform(calib["rotation"], calib["translation"]), pts[:, :3])
        s = sample[sd["sample_token"]]
        sem = load_truth(root, scene_name[s["scene_token"]], s["token"])
        inside = GRID.contains(ego)
        ijk = GRID.index_of(ego[inside])
        own.append(map_lidarseg(raw[inside]))
        vox.append(sem[ijk[:, 0], ijk[:, 1], ijk[:, 2]])
    return np.concatenate(own), np.concatenate(vox)


def lidar_camera_depths(world, rig, t0_us: int, seed: int, scene_index: int, frames) -> dict[str, np.ndarray]:
    """Per LiDAR point projected into a camera, over the keyframes ``frames`` of ``world`` rendered with ``rig``
    (as ``render_keyframe(world, k, rig, t0_us, seed, scene_index)``), float64/bool [M]:

    ``lidar``: the point's z-depth in the camera; ``ray``: z-depth where the camera ray through the point's exact
    (u, v) first hits the geometry at the camera's time (ray cast, no pixels); ``pixel``: the rendered depth of the
    pixel the point falls in; ``class_ok``: the pixel shows the point's class; ``static``: the point lies on
    something that does not move (dynamic agents move between the LiDAR's and the camera's times)."""
    out = {"lidar": [], "ray": [], "pixel": [], "class_ok": [], "static": []}
    moving = np.array([a.speed > 0 for a in world.agents] + [False])
    for k in frames:
        kf = render_keyframe(world, k, rig, t0_us, seed, scene_index)
        cls = map_lidarseg(kf.scan.raw)
        for c in range(len(kf.cameras)):
            cam2global = kf.camera_ego2global[c] @ rig.cam2ego[c]
            T = np.linalg.inv(cam2global) @ kf.lidar_ego2global @ rig.lidar2ego
            K = rig.intrinsics[c]
            u, v, idx = project_points(kf.scan.points[:, :3].astype(np.float64), T, K, rig.width, rig.height)
            d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
            t_cam = (kf.camera_times_us[c] - t0_us) * 1e-6
            t, _ = cast_rays(world.boxes_at(t_cam), cam2global[:3, 3], d_cam @ cam2global[:3, :3].T)
            row, col = v.astype(int), u.astype(int)
            out["lidar"].append(transform_points(T, kf.scan.points[idx, :3].astype(np.float64))[:, 2])
            out["ray"].append(t)
            out["pixel"].append(kf.cameras[c].depth[row, col])
            out["class_ok"].append(kf.cameras[c].occ[row, col] == cls[idx])
            out["static"].append(~moving[kf.scan.instance[idx]])  # instance -1 (unannotated) picks the last
    return {key: np.concatenate(val) for key, val in out.items()}
