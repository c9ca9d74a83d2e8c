"""Images, LiDAR and Occ3D ground truth of the synthetic world come from one geometry: measured agreement."""
import numpy as np
import pytest

from occflownet.synth.camera import cast_rays, render_camera
from occflownet.synth.consistency import lidar_camera_depths, lidar_label_agreement
from occflownet.synth.layout import WorldConfig, build_world
from occflownet.synth.voxelize import voxelize


def test_lidar_points_lie_in_gt_voxels_of_their_class(synth_root):
    """Read back from disk: LiDAR → ego with the calibrated_sensor, look up labels.npz, compare mapped classes."""
    own, vox = lidar_label_agreement(*synth_root)
    assert len(own) > 50_000
    agree = np.mean(own == vox)
    assert agree >= 0.95, f"only {agree:.3f} of LiDAR points in a voxel of their class"


def test_lidar_depth_matches_camera_rays(synth_world):
    """A LiDAR point on something static is exactly where the camera ray through its projection hits first (or
    hidden behind something nearer); the rendered pixel it falls in shows the same depth up to pixel size."""
    world, rig, t0 = synth_world
    r = lidar_camera_depths(world, rig, t0, 7, 0, [2])
    static = r["static"]
    z, t = r["lidar"][static], r["ray"][static]
    assert np.all(z >= t - 1e-3), "a camera ray passed a static LiDAR point without hitting it"
    exact = np.mean(np.abs(z - t) < 1e-3)
    pixel = np.mean(np.abs(z - r["pixel"][static]) < 0.05 + 0.05 * z)
    assert static.sum() > 5000
    assert exact > 0.8 and pixel > 0.85, (exact, pixel)


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
        # box ids (integers) from float64 ray-box tests at random pixel centres (none within ~1e-9 of a box edge)
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
