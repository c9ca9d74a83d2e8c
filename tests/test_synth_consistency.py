"""Images, LiDAR and Occ3D ground truth of the synthetic world come from one geometry: measured agreement."""
import json

import numpy as np
import pytest

from occflownet.occ3d import GRID, map_lidarseg
from occflownet.geometry import invert, make_transform, transform_points
from occflownet.synth.camera import cast_rays, render_camera
from occflownet.synth.frame import render_keyframe
from occflownet.synth.layout import WorldConfig, build_world
from occflownet.synth.preview import project_lidar
from occflownet.synth.voxelize import voxelize


def test_lidar_points_lie_in_gt_voxels_of_their_class(synth_root):
    """Read back from disk: LiDAR → ego with the calibrated_sensor, look up labels.npz, compare mapped classes."""
    root, version = synth_root
    t = {n: json.loads((root / version / f"{n}.json").read_text())
         for n in ("sample", "sample_data", "calibrated_sensor", "sensor", "scene", "lidarseg")}
    cs = {r["token"]: r for r in t["calibrated_sensor"]}
    lidar = next(s["token"] for s in t["sensor"] if s["channel"] == "LIDAR_TOP")
    samples = {s["token"]: s for s in t["sample"]}
    scene = {s["token"]: s["name"] for s in t["scene"]}
    seg = {r["sample_data_token"]: r["filename"] for r in t["lidarseg"]}
    agree, total = 0, 0
    for sd in t["sample_data"]:
        calib = cs[sd["calibrated_sensor_token"]]
        if calib["sensor_token"] != lidar:
            continue
        pts = np.fromfile(root / sd["filename"], dtype=np.float32).reshape(-1, 5)
        cls = map_lidarseg(np.fromfile(root / seg[sd["token"]], dtype=np.uint8))
        ego = transform_points(make_transform(calib["rotation"], calib["translation"]), pts[:, :3])
        s = samples[sd["sample_token"]]
        with np.load(root / "gts" / scene[s["scene_token"]] / s["token"] / "labels.npz") as z:
            sem = z["semantics"]
        inside = GRID.contains(ego)
        ijk = GRID.index_of(ego[inside])
        agree += int(np.sum(sem[ijk[:, 0], ijk[:, 1], ijk[:, 2]] == cls[inside]))
        total += int(inside.sum())
    assert total > 50_000
    assert agree / total >= 0.95, f"only {agree / total:.3f} of LiDAR points in a voxel of their class"


def test_lidar_depth_matches_camera_rays(synth_world):
    """A LiDAR point on something static is exactly where the camera ray through its projection hits first (or
    hidden behind something nearer); the rendered pixel it falls in shows the same depth up to pixel size."""
    world, rig, t0 = synth_world
    kf = render_keyframe(world, 2, rig, t0, 7)
    moving = np.array([a.speed > 0 for a in world.agents] + [False])
    exact, pixel, n = 0, 0, 0
    for c in range(6):
        u, v, idx = project_lidar(kf, rig, c)
        cam2global = kf.camera_ego2global[c] @ rig.cam2ego[c]
        z = transform_points(invert(cam2global) @ kf.lidar_ego2global @ rig.lidar2ego,
                             kf.scan.points[idx, :3].astype(np.float64))[:, 2]
        K = rig.intrinsics[c]
        d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        t, _ = cast_rays(world.boxes_at((kf.camera_times_us[c] - t0) * 1e-6), cam2global[:3, 3],
                         d_cam @ cam2global[:3, :3].T)
        static = ~moving[kf.scan.instance[idx]]
        assert np.all(z[static] >= t[static] - 1e-3), "a camera ray passed a static LiDAR point without hitting it"
        exact += int(np.sum(np.abs(z - t)[static] < 1e-3))
        depth = kf.cameras[c].depth[v.astype(int), u.astype(int)]
        pixel += int(np.sum((np.abs(z - depth) < 0.05 + 0.05 * z)[static]))
        n += int(static.sum())
    assert n > 5000
    assert exact / n > 0.8 and pixel / n > 0.85, (exact / n, pixel / n)


def test_renderer_matches_unculled_ray_cast(synth_world):
    """Screen-space culling loses no hit: the depth buffer equals a brute-force cast at the pixel centres."""
    world, rig, t0 = synth_world
    boxes = world.boxes_at(1.0)
    ego = world.ego2global(1.0)
    rng = np.random.default_rng(0)
    for c in (0, 3, 4):
        cam2global = ego @ rig.cam2ego[c]
        r = render_camera(world, boxes, rig.intrinsics[c], cam2global, rig.width, rig.height)
        rows, cols = rng.integers(0, rig.height, 800), rng.integers(0, rig.width, 800)
        K = rig.intrinsics[c]
        d = np.stack([(cols + 0.5 - K[0, 2]) / K[0, 0], (rows + 0.5 - K[1, 2]) / K[1, 1], np.ones(800)], -1)
        t, ids = cast_rays(boxes, cam2global[:3, 3], d @ cam2global[:3, :3].T)
        assert np.allclose(r.depth[rows, cols], t, rtol=1e-5, equal_nan=False)
        assert np.array_equal(r.box[rows, cols], ids)
        assert np.isinf(r.depth).any() and (r.occ[np.isinf(r.depth)] == 17).all()  # sky


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_all_17_classes_appear_in_a_default_world(seed):
    frames = 6
    world = build_world(WorldConfig(), seed, 0, frames)
    present = set()
    for k in range(frames):
        t = 0.5 * k
        present |= set(np.unique(voxelize(world, world.boxes_at(t), world.ego2global(t))).tolist())
    assert present == set(range(18)), f"missing classes {set(range(18)) - present}"
