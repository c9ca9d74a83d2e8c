"""RayIoU on the CPU (occflownet.eval.ray_iou): exact first hits, the reference's counting, origins."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from occflownet.occ3d import GRID, Grid
from occflownet.eval import (RayIoUMetric, first_hits, lidar_ray_directions, ray_iou, scene_ray_origins,
                             to_json_ready)
from occflownet.eval.ray_iou import _cast, _reference_rays
from occflownet.geometry import make_transform, yaw_to_quaternion

SHARED = Path(__file__).resolve().parents[2] / "shared"
LABELS = SHARED / "data" / "occ3d-sample" / "labels.npz"
FREE = 17
LIDAR_IN_EGO = np.array([0.98, 0.0, 1.84])


def kernel_first_hit(occupied, origin, end=None, direction=None):
    """Line-by-line Python port of the reference ``dvr`` kernel (``render_forward``, phase "test").

    occupied: bool [X, Y, Z]; origin, end: voxel units (the kernel derives the direction from end − origin);
    or ``direction`` given directly (unit, voxel units). Returns (voxel index, exit distance in voxel units)."""
    X, Y, Z = occupied.shape
    dbl_max = sys.float_info.max
    xo, yo, zo = (float(v) for v in origin)
    vx, vy, vz = int(xo), int(yo), int(zo)
    if direction is None:
        rx, ry, rz = (float(e) - o for e, o in zip(end, (xo, yo, zo)))
        gt_d = math.sqrt(rx * rx + ry * ry + rz * rz)
        dx, dy, dz = rx / gt_d, ry / gt_d, rz / gt_d
    else:
        dx, dy, dz = (float(v) for v in direction)
    step_x, step_y, step_z = (1 if v >= 0 else -1 for v in (dx, dy, dz))
    t_max_x = (vx + (0 if step_x < 0 else 1) - xo) / dx if dx != 0 else dbl_max
    t_max_y = (vy + (0 if step_y < 0 else 1) - yo) / dy if dy != 0 else dbl_max
    t_max_z = (vz + (0 if step_z < 0 else 1) - zo) / dz if dz != 0 else dbl_max
    t_delta_x = step_x / dx if dx != 0 else dbl_max
    t_delta_y = step_y / dy if dy != 0 else dbl_max
    t_delta_z = step_z / dz if dz != 0 else dbl_max
    path, dist, step, was_inside = [], [], 0, False
    while True:
        inside = 0 <= vx < X and 0 <= vy < Y and 0 <= vz < Z
        if inside:
            was_inside = True
            current = (vx, vy, vz)
        elif was_inside:
            break
        if t_max_x < t_max_y:
            if t_max_x < t_max_z:
                d, vx, t_max_x = t_max_x, vx + step_x, t_max_x + t_delta_x
            else:
                d, vz, t_max_z = t_max_z, vz + step_z, t_max_z + t_delta_z
        else:
            if t_max_y < t_max_z:
                d, vy, t_max_y = t_max_y, vy + step_y, t_max_y + t_delta_y
            else:
                d, vz, t_max_z = t_max_z, vz + step_z, t_max_z + t_delta_z
        if inside:
            path.append(current)
            dist.append(d)
        step += 1
        if step > 1000:
            break
    for voxel, d in zip(path, dist):
        if occupied[voxel]:
            return voxel, d
    return path[-1], dist[-1]


def empty_volume(shape=GRID.shape):
    return np.full(shape, FREE, dtype=np.uint8)


def test_first_hits_hand_made_walls():
    vol = empty_volume()
    vol[150, :, :] = 15  # manmade wall: x ∈ [20.0, 20.4)
    vol[:, :, 0] = 11  # road layer: z ∈ [-1.0, -0.6)
    origin = np.array([0.2, 0.2, 2.1])
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 0, -1], [0, 0, 1], [1, 1, 0], [3, 0, 0]], dtype=float)
    cls, dist = first_hits(vol, origin, dirs)
    # +x: leaves the wall voxel at x = 20.4; -x: no hit, leaves the grid at x = -40; down: leaves the road voxel at
    # z = -1.0 (enters it at 2.7 m); up: no hit, leaves at z = 5.4; non-unit direction is normalised.
    assert cls.tolist() == [15, FREE, 11, FREE, 15, 15]
    assert dist[[0, 1, 2, 3, 5]] == pytest.approx([20.2, 40.2, 3.1, 3.3, 20.2], abs=1e-9)
    # 45° in the xy plane from (0.1, 0.3): enters the wall at x = 20, y = 20.2 and leaves through the y = 20.4
    # face at x = 20.2 → distance (20.2 − 0.1)·√2
    cls, dist = first_hits(vol, [0.1, 0.3, 2.1], np.array([[1.0, 1.0, 0.0]]))
    assert cls[0] == 15 and dist[0] == pytest.approx(20.1 * math.sqrt(2), abs=1e-9)


def test_first_hits_origin_in_occupied_voxel_and_outside_grid():
    vol = empty_volume()
    vol[150, :, :] = 4
    # starting inside the occupied voxel: it is the hit, at its exit
    cls, dist = first_hits(vol, [20.1, 0.2, 2.1], np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert cls.tolist() == [4, 4] and dist == pytest.approx([0.3, 0.1], abs=1e-9)
    # outside the grid: enters at x = -40 and still measures from the given origin; pointing away never enters
    cls, dist = first_hits(vol, [-50.0, 0.2, 2.1], np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert cls.tolist() == [4, FREE]
    assert dist[0] == pytest.approx(70.4, abs=1e-9) and dist[1] == np.inf
    with pytest.raises(ValueError, match="directions"):
        first_hits(vol, [0, 0, 0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="shape"):
        first_hits(vol[:10], [0, 0, 0], np.ones((2, 3)))


def test_traversal_matches_reference_kernel_exactly_including_ties():
    small = Grid(lower=(-4.0, -4.0, -1.0), upper=(4.0, 4.0, 2.2), voxel_size=0.4, shape=(20, 20, 8))
    rng = np.random.default_rng(1)
    occupied = rng.random(small.shape) < 0.03
    vol = np.where(occupied, rng.integers(0, 17, small.shape), FREE).astype(np.uint8)
    origins = rng.uniform([0.5, 0.5, 0.5], [19.5, 19.5, 7.5], size=(300, 3))
    dirs = rng.normal(size=(300, 3))
    # ties: voxel corners and edges, axis-parallel and diagonal directions
    corner = np.array([[10.0, 10.0, 4.0]] * 8)
    tie_dirs = np.array([[1, 1, 0], [1, -1, 0], [-1, 1, 1], [1, 1, 1], [0, 0, 1], [1, 0, 0], [0, -1, 0],
                         [-1, -1, -1]], dtype=float)
    origins, dirs = np.concatenate([origins, corner]), np.concatenate([dirs, tie_dirs])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cls, t = _cast(vol, origins, dirs)
    for i in range(len(origins)):
        voxel, d = kernel_first_hit(occupied, origins[i], direction=dirs[i])
        assert cls[i] == vol[voxel], i
        if cls[i] != FREE:
            assert t[i] == d, i  # bit-identical exit distance of the hit voxel
        else:
            assert t[i] == pytest.approx(d, rel=1e-12), i  # grid exit of a ray without hit: round-off only


def test_tie_breaking_like_the_kernel():
    # A diagonal ray from a voxel corner crosses the x and y faces at the same time; the kernel then steps y
    # (its `tMaxX < tMaxY` is false), so it visits (10, 11, 4), not (11, 10, 4).
    vol = empty_volume((20, 20, 8))
    vol[11, 10, 4] = 4
    vol[10, 11, 4] = 7
    origin = np.array([[10.0, 10.0, 4.5]])
    direction = np.array([[1.0, 1.0, 0.0]]) / math.sqrt(2)
    cls, _ = _cast(vol, origin, direction)
    voxel, _ = kernel_first_hit(vol != FREE, origin[0], direction=direction[0])
    assert voxel == (10, 11, 4) and cls[0] == 7


def test_reference_ray_rounding_matches_kernel_on_the_lidar_pattern():
    vol = empty_volume()
    vol[:, :, :2] = 11
    vol[120:124, 90:110, 2:10] = 4
    vol[60:64, :, :] = 15
    origin = np.array([[0.98, 0.0, 1.84]])
    directions = lidar_ray_directions()[::23]  # 611 rays spread over all pitches and azimuths
    origin_vox, unit = _reference_rays(origin, directions.astype(np.float64), GRID)
    cls, t = _cast(vol, origin_vox, unit)
    lower = np.asarray(GRID.lower, dtype=np.float32).astype(np.float64)
    scale = np.float64(np.float32(0.4))
    o32 = ((origin[0] - lower) / scale).astype(np.float32)
    for i, ray in enumerate(directions.astype(np.float64)):
        e32 = ((ray + origin[0] - lower) / scale).astype(np.float32)
        voxel, d = kernel_first_hit(vol != FREE, o32, end=e32)
        assert cls[i] == vol[voxel], i
        assert t[i] == d if cls[i] != FREE else t[i] == pytest.approx(d, rel=1e-12), i


def test_lidar_ray_pattern():
    dirs = lidar_ray_directions()
    assert dirs.shape == (14040, 3) and dirs.dtype == np.float32
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6)
    pitch = np.degrees(np.arcsin(dirs[::360, 2]))
    assert pitch[0] == pytest.approx(-45.0, abs=1e-4) and pitch[1] == pytest.approx(-26.565, abs=1e-3)
    assert 12.0 < pitch[-1] < 13.0 and np.all(np.diff(pitch) > 0)
    assert np.allclose(dirs[:360, 1], np.cos(np.radians(45)) * np.sin(np.radians(np.arange(360))), atol=1e-6)


def wall_scene(x_index, cls=15, thickness=4):
    vol = empty_volume()
    vol[x_index:x_index + thickness, :, :] = cls
    return vol


AXIS_RAYS = np.array([[1.0, 0.0, 0.0]])
ORIGINS = np.array([[0.98, 0.0, 1.84], [-3.02, 2.1, 1.84], [4.9, -6.3, 0.5]])


def test_rayiou_is_one_for_identical_volumes():
    gt = wall_scene(150)
    gt[:, :, 0] = 11
    gt[80:90, 120:125, 1:5] = 4
    res = ray_iou([(gt, gt, ORIGINS)])
    assert res["rayiou"] == 1.0
    assert res["rayiou@1"] == res["rayiou@2"] == res["rayiou@4"] == 1.0
    assert res["rays_cast"] == 3 * 14040 and 0 < res["rays_with_gt_hit"] < res["rays_cast"]
    assert res["iou_per_class"]["car"] == [1.0, 1.0, 1.0]
    assert all(math.isnan(v) for v in res["iou_per_class"]["bus"])  # absent: NaN, skipped


@pytest.mark.parametrize("shift_voxels, expected", [(3, [0.0, 1.0, 1.0]), (6, [0.0, 0.0, 1.0]),
                                                    (-3, [0.0, 1.0, 1.0]), (0, [1.0, 1.0, 1.0])])
def test_shifted_wall_counts_by_threshold(shift_voxels, expected):
    # gt wall face at x = 20 m; the prediction's is 0.4 m × shift further: a hit 1.2 m off counts at 2 and 4 m,
    # not at 1 m; 2.4 m off only at 4 m
    gt, pred = wall_scene(150), wall_scene(150 + shift_voxels)
    metric = RayIoUMetric(directions=AXIS_RAYS)
    metric.update(pred, gt, ORIGINS)
    res = metric.compute()
    assert res["rays_with_gt_hit"] == 3
    assert res["iou_per_class"]["manmade"] == expected
    assert [res["rayiou@1"], res["rayiou@2"], res["rayiou@4"]] == expected
    assert res["rayiou"] == pytest.approx(np.mean(expected))


def test_wrong_class_missed_hit_and_hits_where_gt_has_none():
    gt = wall_scene(150, cls=15)
    # right place, wrong class: FN for manmade and FP for vegetation at every threshold
    res = ray_iou([(wall_scene(150, cls=16), gt, ORIGINS)], directions=AXIS_RAYS)
    assert res["iou_per_class"]["manmade"] == [0.0] * 3 and res["iou_per_class"]["vegetation"] == [0.0] * 3
    assert res["rayiou"] == 0.0
    # no predicted hit at all: FN only
    res = ray_iou([(empty_volume(), gt, ORIGINS)], directions=AXIS_RAYS)
    assert res["iou_per_class"]["manmade"] == [0.0] * 3 and res["rayiou"] == 0.0
    # rays whose gt has no hit (−x) are dropped, so a predicted wall there is not a false positive
    pred = gt.copy()
    pred[10:14] = 16
    res = ray_iou([(pred, gt, ORIGINS)], directions=np.array([[1.0, 0, 0], [-1.0, 0, 0]]))
    assert res["rays_with_gt_hit"] == 3 and res["rayiou"] == 1.0
    assert all(math.isnan(v) for v in res["iou_per_class"]["vegetation"])


def test_counting_follows_the_reference_formula():
    metric = RayIoUMetric()
    # ray: (pred class, pred distance, gt class, gt distance)
    rays = [(4, 10.0, 4, 10.5),   # car TP at every threshold
            (4, 11.5, 4, 10.0),   # car, 1.5 m off: TP at 2 and 4 m; else FP + FN for car
            (17, 40.0, 4, 12.0),  # car missed (no predicted hit): FN
            (11, 5.0, 4, 5.0),    # car predicted as road: FN car, FP road
            (11, 3.0, 11, 3.0)]   # road TP
    p_cls, p_d, g_cls, g_d = (np.array(v) for v in zip(*rays))
    metric.add_rays(p_cls, p_d, g_cls, g_d)
    metric.samples = 1
    res = metric.compute()
    # car: gt 4 rays, pred 2 rays; TP@1 = 1, TP@2 = TP@4 = 2 → IoU = TP / (4 + 2 − TP)
    assert res["iou_per_class"]["car"] == pytest.approx([1 / 5, 2 / 4, 2 / 4])
    # road: gt 1, pred 2, TP 1 → 1/2
    assert res["iou_per_class"]["driveable_surface"] == pytest.approx([0.5, 0.5, 0.5])
    assert res["rayiou@1"] == pytest.approx((0.2 + 0.5) / 2)
    assert res["rayiou"] == pytest.approx(np.mean([0.2, 0.5, 0.5, 0.5, 0.5, 0.5]))
    with pytest.raises(ValueError, match="ground-truth hit"):
        metric.add_rays(np.array([4]), np.array([1.0]), np.array([17]), np.array([1.0]))


def test_merge_and_bad_inputs():
    gt, pred = wall_scene(150), wall_scene(153)
    a, b, both = (RayIoUMetric(directions=AXIS_RAYS) for _ in range(3))
    a.update(pred, gt, ORIGINS[:1])
    b.update(gt, gt, ORIGINS[1:])
    both.update(pred, gt, ORIGINS[:1])
    both.update(gt, gt, ORIGINS[1:])
    a.merge(b)
    assert to_json_ready(a.compute()) == to_json_ready(both.compute())
    # gt 3 rays, pred 3 rays; TP@1 = 2 (the identical sample), TP@2 = TP@4 = 3
    assert a.compute()["iou_per_class"]["manmade"] == [2 / 4, 1.0, 1.0]
    with pytest.raises(ValueError, match="origins"):
        both.update(gt, gt, np.zeros((0, 3)))
    with pytest.raises(ValueError, match="pred"):
        both.update(np.full_like(gt, 255), gt, ORIGINS)
    with pytest.raises(ValueError, match="shape"):
        both.update(gt[:100], gt[:100], ORIGINS)
    with pytest.raises(ValueError, match="no samples"):
        RayIoUMetric().compute()


def test_scene_ray_origins_follow_the_reference_selection():
    lidar2ego = make_transform(np.eye(3), LIDAR_IN_EGO)
    # ego drives along +x at 5 m per keyframe, 20 keyframes; the current one (index 6) is yawed like the others
    yaw = np.radians(30)
    rot = make_transform(yaw_to_quaternion(yaw), [0, 0, 0])[:3, :3]
    poses = [make_transform(rot, [100 + 5 * f * np.cos(yaw), 50 + 5 * f * np.sin(yaw), 0]) for f in range(20)]
    origins = scene_ray_origins([lidar2ego] * 20, poses, current=6)
    # in the current ego frame frame f sits at x = 5 (f − 6) + 0.98; |x| < 39 keeps f = 0 … 13 (14 frames)
    kept_x = np.array([5.0 * (f - 6) + 0.98 for f in range(20) if abs(5.0 * (f - 6) + 0.98) < 39])
    assert len(kept_x) == 14
    pick = np.round(np.linspace(0, 13, 8)).astype(int)
    assert origins.shape == (8, 3)
    assert np.allclose(origins[:, 0], kept_x[pick])
    assert np.allclose(origins[:, 1:], [0.0, 1.84])
    few = scene_ray_origins([lidar2ego] * 3, poses[:3], current=0)
    assert np.allclose(few, [[0.98, 0, 1.84], [5.98, 0, 1.84], [10.98, 0, 1.84]])
    with pytest.raises(ValueError, match="current"):
        scene_ray_origins([lidar2ego] * 3, poses[:3], current=3)


@pytest.mark.skipif(not LABELS.exists(), reason=f"shared Occ3D sample not found at {LABELS}")
def test_real_sample_eight_origins():
    gt = np.load(LABELS)["semantics"]
    origins = LIDAR_IN_EGO + np.array([[dx, 0.0, 0.0] for dx in (-28, -20, -12, -4, 0, 4, 12, 20)])
    metric = RayIoUMetric()
    metric.update(gt, gt, origins)
    assert metric.compute()["rayiou"] == 1.0
    shifted = RayIoUMetric()
    shifted.update(np.roll(gt, 3, axis=0), gt, origins)  # 1.2 m forward
    res = shifted.compute()
    assert res["rayiou@1"] < res["rayiou@2"] <= res["rayiou@4"] < 1.0
