"""Consistency figures of the synthetic world: do LiDAR labels, Occ3D voxels and image depth agree?

    python benchmarks/synth_consistency.py [--scenes 2 --frames 6 --seed 0 --width 480 --height 270]

Prints, over all keyframes:
- LiDAR → gt: share of LiDAR points inside the grid whose voxel in labels.npz has the point's own class
  (raw lidarseg index mapped with config.map_lidarseg; points moved LiDAR → ego with the calibrated_sensor),
  read back from the files on disk; per class too.
- LiDAR → image depth: for every LiDAR point projected into a camera (LiDAR → ego at LiDAR time → global →
  ego at camera time → camera), |z-depth of the point − rendered depth at its pixel|; share within 5 cm and 0.5 m,
  for all points and for points of static objects (dynamic agents move between LiDAR and camera times).
- masks: mean of mask_lidar / mask_camera, share of LiDAR points' voxels inside mask_lidar, classes present.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from occflownet.occ3d import CLASS_NAMES, GRID, map_lidarseg
from occflownet.geometry import make_transform, transform_points
from occflownet.synth.camera import cast_rays
from occflownet.synth.frame import SensorRig, render_keyframe
from occflownet.synth.generate import FIRST_TIMESTAMP_US, generate
from occflownet.synth.layout import WorldConfig, build_world
from occflownet.synth.preview import project_lidar


def lidar_gt_agreement(root: Path, version: str) -> tuple[np.ndarray, np.ndarray]:
    """(point classes [N], voxel classes at the points [N]) over all keyframes, read from disk."""
    t = {n: json.loads((root / version / f"{n}.json").read_text())
         for n in ("sample", "sample_data", "calibrated_sensor", "sensor", "scene", "lidarseg")}
    cs = {r["token"]: r for r in t["calibrated_sensor"]}
    lidar_sensor = next(s["token"] for s in t["sensor"] if s["channel"] == "LIDAR_TOP")
    scene_name = {s["token"]: s["name"] for s in t["scene"]}
    sample = {s["token"]: s for s in t["sample"]}
    seg = {r["sample_data_token"]: r["filename"] for r in t["lidarseg"]}
    own, vox = [], []
    for sd in t["sample_data"]:
        calib = cs[sd["calibrated_sensor_token"]]
        if calib["sensor_token"] != lidar_sensor:
            continue
        pts = np.fromfile(root / sd["filename"], dtype=np.float32).reshape(-1, 5)
        raw = np.fromfile(root / seg[sd["token"]], dtype=np.uint8)
        ego = transform_points(make_transform(calib["rotation"], calib["translation"]), pts[:, :3])
        s = sample[sd["sample_token"]]
        with np.load(root / "gts" / scene_name[s["scene_token"]] / s["token"] / "labels.npz") as z:
            sem = z["semantics"]
        inside = GRID.contains(ego)
        ijk = GRID.index_of(ego[inside])
        own.append(map_lidarseg(raw[inside]))
        vox.append(sem[ijk[:, 0], ijk[:, 1], ijk[:, 2]])
    return np.concatenate(own), np.concatenate(vox)


def depth_agreement(world, rig, t0_us: int, seed: int, scene_index: int, frames) -> dict[str, np.ndarray]:
    """Per LiDAR point projected into a camera, over the given keyframes:
    ``exact``: |point z-depth − depth of the camera ray through the point's exact (u, v)| (ray cast, no pixels);
    ``pixel``: |point z-depth − rendered depth of the pixel it falls in|; ``class_ok``: the pixel shows the point's
    class; ``static``: the point is on something that does not move."""
    out = {"exact": [], "pixel": [], "class_ok": [], "static": []}
    moving = np.array([a.speed > 0 for a in world.agents] + [False])
    for k in frames:
        kf = render_keyframe(world, k, rig, t0_us, seed, scene_index)
        cls = map_lidarseg(kf.scan.raw)
        for c in range(len(kf.cameras)):
            u, v, idx = project_lidar(kf, rig, c)
            cam2global = kf.camera_ego2global[c] @ rig.cam2ego[c]
            T = np.linalg.inv(cam2global) @ kf.lidar_ego2global @ rig.lidar2ego
            z = transform_points(T, kf.scan.points[idx, :3].astype(np.float64))[:, 2]
            K = rig.intrinsics[c]
            d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
            t_cam = (kf.camera_times_us[c] - t0_us) * 1e-6
            t, _ = cast_rays(world.boxes_at(t_cam), cam2global[:3, 3], d_cam @ cam2global[:3, :3].T)
            out["exact"].append(np.abs(z - t))
            out["pixel"].append(np.abs(z - kf.cameras[c].depth[v.astype(int), u.astype(int)]))
            out["class_ok"].append(kf.cameras[c].occ[v.astype(int), u.astype(int)] == cls[idx])
            out["static"].append(~moving[kf.scan.instance[idx]])  # instance -1 (unannotated) picks the last
    return {key: np.concatenate(val) for key, val in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        res = generate(root, args.scenes, args.frames, args.seed, args.width, args.height, progress=False)
        own, vox = lidar_gt_agreement(root, res.version)
        masks = []
        for p in sorted((root / "gts").glob("*/*/labels.npz")):
            with np.load(p) as z:
                masks.append((z["mask_lidar"].mean(), z["mask_camera"].mean(), np.unique(z["semantics"])))
    print(f"LiDAR points inside the grid: {len(own)}; in a gt voxel of their own class: {np.mean(own == vox):.4f}")
    for c in range(17):
        sel = own == c
        if sel.any():
            print(f"  {CLASS_NAMES[c]:22s} {sel.sum():8d} points  agreement {np.mean(vox[sel] == c):.4f}")
    rig = SensorRig.default(args.width, args.height)
    parts = []
    for s in range(args.scenes):
        world = build_world(WorldConfig(), args.seed, s, args.frames)
        parts.append(depth_agreement(world, rig, FIRST_TIMESTAMP_US + s * 1_000_000_000, args.seed, s,
                                     range(0, args.frames, 2)))
    r = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    st = r["static"]
    print(f"LiDAR points projected into cameras: {len(st)} (every 2nd keyframe; {st.mean():.3f} on static things)")
    for key, name in (("exact", "camera ray through the exact projection"), ("pixel", "rendered pixel")):
        e = r[key]
        print(f"  vs {name}: |depth error| < 0.01 m: all {np.mean(e < 0.01):.4f}, static {np.mean(e[st] < 0.01):.4f};"
              f" < 0.5 m: all {np.mean(e < 0.5):.4f}, static {np.mean(e[st] < 0.5):.4f}; median {np.median(e):.4f} m")
    print(f"  the pixel shows the point's class: all {r['class_ok'].mean():.4f}, static {r['class_ok'][st].mean():.4f}")
    ml, mc, present = zip(*masks)
    classes = set(np.concatenate(present).tolist()) - {17}
    print(f"mask_lidar mean {np.mean(ml):.4f}, mask_camera mean {np.mean(mc):.4f}; "
          f"classes present in gt: {len(classes)}/17 {sorted(classes)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
