"""Rays from LiDAR points through camera pixels, checked against the fixture's known geometry."""
import numpy as np
import pytest
from nuscenes_fixture import (EGO_BODY_POINTS, MOVERS, ego_pose, fixture_world, mover_box,  # noqa: F401
                              visible_hits)
from scipy.spatial import cKDTree

from occflownet.occ3d import DYNAMIC_FILTER_CLASSES, GRID, map_lidarseg
from occflownet.data.builder import build_index
from occflownet.data.free_space import FreeSpaceConfig
from occflownet.data.rays import (RayBatch, RayBuilder, RayConfig, pixel_rounding_bound, project_points,
                                  sample_rays)
from occflownet.data.tables import DatasetError
from occflownet.geometry import invert, transform_points


@pytest.fixture(scope="module")
def index(fixture_world):
    return build_index(fixture_world.root)


def _truth_points(fx, scene, k, current):
    """Ground-truth points of keyframe k in the current ego frame of keyframe ``current``, and their Occ3D labels."""
    pts, raw = fx.points_global(scene, k)
    to_current = invert(ego_pose(scene, fx.lidar_time(scene, current)))
    return transform_points(to_current, pts), map_lidarseg(raw)


def test_ray_fields_shapes_and_dtypes(fixture_world, index):
    rays = RayBuilder(index, fixture_world.root).rays(2)
    n = len(rays)
    assert n > 5000
    expected = {"origins": (np.float32, (n, 3)), "directions": (np.float32, (n, 3)), "depths": (np.float32, (n,)),
                "labels": (np.uint8, (n,)), "time_offsets": (np.int8, (n,)), "cameras": (np.int8, (n,)),
                "pixels": (np.float32, (n, 2))}
    for name, (dtype, shape) in expected.items():
        a = getattr(rays, name)
        assert a.dtype == dtype and a.shape == shape, name
    np.testing.assert_allclose(np.linalg.norm(rays.directions, axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(rays.pixels % 1.0, 0.5)  # pixel centres (exact: integers + 0.5 in binary)
    assert (rays.pixels >= 0).all() and (rays.pixels[:, 0] < 1600).all() and (rays.pixels[:, 1] < 900).all()
    assert set(np.unique(rays.cameras)) == set(range(6))
    assert (rays.depths > 0.05).all() and rays.labels.max() <= 16


def test_origins_are_camera_centres_at_each_cameras_own_time(fixture_world, index):
    fx = fixture_world
    rays = RayBuilder(index, fx.root).rays(2)
    to_current = invert(ego_pose(0, fx.lidar_time(0, 2)))
    for t in (-2, 0, 1):
        sample = index[2 + t]
        for c, cam in enumerate(sample.cameras):
            truth = transform_points(to_current @ ego_pose(0, cam.timestamp) @ cam.sensor2ego, np.zeros(3))
            got = rays.origins[(rays.time_offsets == t) & (rays.cameras == c)]
            assert len(got) > 0
            np.testing.assert_allclose(got, np.broadcast_to(truth, got.shape), atol=1e-4)


def test_endpoints_reproduce_lidar_points_in_the_current_frame(fixture_world, index):
    """origin + depth · direction lands on the true point (current ego frame) within the pixel-centre bound;
    the label is the point's; the depth is the Euclidean distance (not the z-depth)."""
    fx = fixture_world
    bound = pixel_rounding_bound(index[0].intrinsics)
    rays = RayBuilder(index, fx.root, RayConfig(dynamic_filter=False)).rays(2)
    ends = rays.endpoints().astype(np.float64)
    for t in range(-2, 3):
        m = rays.time_offsets == t
        truth, labels = _truth_points(fx, 0, 2 + t, current=2)
        d2, i2 = cKDTree(truth).query(ends[m], k=2)
        dist, second, nearest = d2[:, 0], d2[:, 1], i2[:, 0]
        tolerance = rays.depths[m] * bound + 1e-4
        assert (dist <= tolerance).all(), (t, (dist / rays.depths[m]).max(), bound)
        np.testing.assert_array_equal(rays.labels[m], labels[nearest])
        sure = second > 3 * tolerance  # the nearest true point is certainly the ray's own
        assert sure.mean() > 0.95
        np.testing.assert_allclose(rays.depths[m][sure],
                                   np.linalg.norm(truth[nearest[sure]] - rays.origins[m][sure], axis=1), rtol=1e-5)
        assert GRID.contains(truth[nearest]).all()
    assert bound < 1e-3  # ≤ 0.71 px at the smallest focal length (809 px)


def test_a_static_point_seen_from_several_keyframes_lands_in_one_place(fixture_world, index):
    fx = fixture_world
    rays = RayBuilder(index, fx.root).rays(2)
    ends = rays.endpoints()
    truth, _ = _truth_points(fx, 0, 2, current=2)
    target = int(np.argmin(np.linalg.norm(truth[: len(fx.static)] - [15.0, 0.0, 1.0], axis=1)))
    found = {}
    for t in (-2, -1, 0, 1, 2):
        m = rays.time_offsets == t
        d = np.linalg.norm(ends[m] - truth[target], axis=1)
        if d.min() < 0.05:
            found[t] = ends[m][np.argmin(d)]
    assert len(found) >= 3, found
    spread = np.ptp(np.stack(list(found.values())), axis=0)
    assert (spread < 0.05).all(), spread


def test_dynamic_filter_drops_exactly_dynamic_labels_in_other_frames(fixture_world, index):
    on = RayBuilder(index, fixture_world.root, RayConfig(dynamic_filter=True)).rays(2)
    off = RayBuilder(index, fixture_world.root, RayConfig(dynamic_filter=False)).rays(2)
    dynamic = np.isin(off.labels, DYNAMIC_FILTER_CLASSES)
    other_frame = off.time_offsets != 0
    assert (dynamic & other_frame).sum() > 500 and (dynamic & ~other_frame).sum() > 100
    assert (~dynamic & other_frame).sum() > 500
    expected = off.take(~(dynamic & other_frame))
    for name in ("origins", "directions", "depths", "labels", "time_offsets", "cameras", "pixels"):  # exact: copies
        np.testing.assert_array_equal(getattr(on, name), getattr(expected, name), err_msg=name)
    # the bicycle (Occ3D 2) is dynamic in the paper's tables but not in the filter set: it stays
    assert ((on.labels == 2) & (on.time_offsets != 0)).any()


def test_scene_edges_give_fewer_frames_never_duplicates(fixture_world, index):
    builder = RayBuilder(index, fixture_world.root, RayConfig(horizon=3))
    assert sorted(set(builder.rays(0).time_offsets.tolist())) == [0, 1, 2, 3]
    assert sorted(set(builder.rays(4).time_offsets.tolist())) == [-3, -2, -1, 0]
    assert sorted(set(builder.rays(5).time_offsets.tolist())) == [0, 1]  # scene-b has two keyframes
    assert sorted(set(builder.rays(6).time_offsets.tolist())) == [-1, 0]
    one = RayBuilder(index, fixture_world.root, RayConfig(horizon=0)).rays(2)
    assert set(one.time_offsets.tolist()) == {0}
    full = builder.rays(2)
    np.testing.assert_array_equal(full.take(full.time_offsets == 0).depths, one.depths)   # exact: the same rays


def test_t0_rays_match_an_independent_projection(fixture_world, index):
    """Every (point, camera) hit of the keyframe's own sweep inside the grid makes one ray, nothing more."""
    rays = RayBuilder(index, fixture_world.root, RayConfig(horizon=0)).rays(1)
    assert len(rays) == visible_hits(fixture_world, 0, 1).sum()


def test_returns_from_the_ego_car_make_no_ray(fixture_world, index):
    def near_bonnet(config):
        ends = RayBuilder(index, fixture_world.root, config).rays(1).endpoints()
        return np.linalg.norm(ends[:, None] - EGO_BODY_POINTS[None, :2], axis=-1).min(axis=0)

    assert (near_bonnet(RayConfig(horizon=0)) > 0.5).all()
    assert (near_bonnet(RayConfig(horizon=0, ignored_raw_labels=())) < 0.01).all()


def test_visible_point_labels_count_distinct_points(fixture_world, index):
    builder = RayBuilder(index, fixture_world.root, RayConfig(horizon=0))
    labels = builder.visible_point_labels(1)
    rays = builder.rays(1)
    # distinct points ≤ rays (overlapping cameras see some points twice), and the same label set
    assert len(labels) < len(rays)
    assert set(np.unique(labels)) == set(np.unique(rays.labels))
    truth, truth_labels = _truth_points(fixture_world, 0, 1, current=1)
    inside = GRID.contains(truth)
    assert len(labels) <= inside.sum()
    assert np.all(np.bincount(labels, minlength=17) <= np.bincount(truth_labels[inside], minlength=17))


def test_sample_rays_is_seeded_and_fixed_size(fixture_world, index):
    rays = RayBuilder(index, fixture_world.root).rays(2)
    a = sample_rays(rays, 1000, np.random.default_rng(3))
    b = sample_rays(rays, 1000, np.random.default_rng(3))
    c = sample_rays(rays, 1000, np.random.default_rng(4))
    # exact: the same draw (seed 3) twice, copies of the same rays
    assert len(a) == 1000 and np.array_equal(a.depths, b.depths) and not np.array_equal(a.depths, c.depths)
    few = rays.take(np.arange(10))
    assert len(sample_rays(few, 50, np.random.default_rng(0))) == 50  # with replacement when too few
    with pytest.raises(ValueError, match="empty"):
        sample_rays(rays.take(np.zeros(len(rays), bool)), 5, np.random.default_rng(0))


def test_sqrt_balanced_sampling_shares_classes_by_the_root_of_their_counts():
    """A known answer: 90,000 rays of class 11 and 1,000 of class 4 (car). Uniform draws give the car 1,000 / 91,000
    = 1.1 % of a step's rays; sqrt-balanced draws each ray with probability ∝ 1/√n_c, so the classes' shares are
    √90000 : √1000 = 300 : 31.6, the car 9.5 % (2,000 draws without replacement take a fifth of the cars, which
    barely lowers it). Seeded like the uniform rule; an unknown rule is an error."""
    n = 91_000
    labels = np.r_[np.full(90_000, 11), np.full(1000, 4)].astype(np.uint8)
    rays = RayBatch(origins=np.zeros((n, 3), np.float32), directions=np.tile(np.float32([1, 0, 0]), (n, 1)),
                    depths=np.arange(n, dtype=np.float32), labels=labels, time_offsets=np.zeros(n, np.int8),
                    cameras=np.zeros(n, np.int8), pixels=np.zeros((n, 2), np.float32), free_ends=np.zeros(n, np.float32))
    uniform = sample_rays(rays, 2000, np.random.default_rng(0))
    balanced = sample_rays(rays, 2000, np.random.default_rng(0), "sqrt-balanced")
    assert np.mean(uniform.labels == 4) == pytest.approx(1000 / 91_000, abs=0.006)
    assert np.mean(balanced.labels == 4) == pytest.approx(np.sqrt(1000) / (np.sqrt(1000) + 300), abs=0.015)
    assert len(np.unique(balanced.depths)) == 2000                         # without replacement when there are enough
    again = sample_rays(rays, 2000, np.random.default_rng(0), "sqrt-balanced")
    assert np.array_equal(balanced.depths, again.depths)                       # exact: the same draw, copies
    with pytest.raises(ValueError, match="ray sampling"):
        sample_rays(rays, 10, np.random.default_rng(0), "weighted")


def test_transform_round_trips(fixture_world, index):
    s = index[3]
    ego = s.boxes_in_ego()
    back = s.ego2global @ ego.transforms()
    np.testing.assert_allclose(back[:, :3, 3], s.boxes.translations, atol=1e-9)
    other = index[1].boxes.in_frame(s.ego2global)  # keyframe 1's boxes in keyframe 3's ego frame
    np.testing.assert_allclose(s.ego2global @ other.transforms()[0], mover_box(MOVERS[0], 0.5), atol=1e-9)
    cam = s.cam2current_ego()
    for c, record in enumerate(s.cameras):
        np.testing.assert_allclose(s.ego2global @ cam[c], record.ego2global @ record.sensor2ego, atol=1e-9)
    pts = np.random.default_rng(0).normal(size=(50, 3)) * 20
    T = s.ego2global @ s.lidar.sensor2ego
    np.testing.assert_allclose(transform_points(invert(T), transform_points(T, pts)), pts, atol=1e-9)


def test_rays_need_lidarseg(fixture_world, index, tmp_path):
    arrays = dict(index.arrays)
    arrays["lidarseg_path"] = np.zeros_like(arrays["lidarseg_path"])
    bare = type(index)(index.version, arrays, index.splits)
    with pytest.raises(DatasetError, match=f"sample {index.tokens[0]} \\(scene scene-a\\) has no lidarseg labels"):
        RayBuilder(bare, fixture_world.root).rays(0)


def test_projection_rejects_points_behind_and_outside():
    K = np.array([[[100.0, 0, 50], [0, 100, 25], [0, 0, 1]]])
    eye = np.eye(4)[None]
    pts = np.array([[0, 0, 10.0], [0, 0, -10], [0, 0, 0.04], [6, 0, 10], [-4.9, -2.4, 10], [0, 2.6, 10]])
    hits = project_points(pts, eye, K, np.array([[100, 50]]))
    assert hits.point_index.tolist() == [0, 4]
    np.testing.assert_allclose(hits.uv, [[50, 25], [1, 1]])


def test_ray_batch_concatenate_and_take():
    def batch(n, t):
        return RayBatch(np.zeros((n, 3), np.float32), np.tile(np.float32([0, 0, 1]), (n, 1)), np.ones(n, np.float32),
                        np.zeros(n, np.uint8), np.full(n, t, np.int8), np.zeros(n, np.int8), np.zeros((n, 2), np.float32),
                        np.zeros(n, np.float32))
    both = RayBatch.concatenate([batch(3, 0), batch(2, 1)])
    assert len(both) == 5 and both.time_offsets.tolist() == [0, 0, 0, 1, 1]
    np.testing.assert_allclose(both.endpoints(), [[0, 0, 1]] * 5)
    assert len(both.take(both.time_offsets == 1)) == 2 and both.take(np.array([4])).time_offsets.tolist() == [1]


def _grid_exit_distance(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each ray (origin inside the grid box) at which it leaves the box (slab method)."""
    lo, hi = np.asarray(GRID.lower), np.asarray(GRID.upper)
    with np.errstate(divide="ignore"):
        far = np.where(directions > 0, (hi - origins) / directions, (lo - origins) / directions)
    return np.where(directions == 0, np.inf, far).min(axis=1)


def test_beyond_grid_free_rays_are_the_camera_rays_whose_point_lies_outside_the_grid(fixture_world, index):
    """Each beyond-grid ray is a camera ray (camera centre, pixel-centre direction) to a LiDAR point outside the
    current grid; the ray leaves the grid before it reaches the point, so the grid is free along it."""
    position, horizon = 2, 1
    plain = RayBuilder(index, fixture_world.root, RayConfig(horizon=horizon))
    assert len(plain.free_rays(position)) == 0   # neither free-space beams nor beyond-grid rays configured
    builder = RayBuilder(index, fixture_world.root, RayConfig(horizon=horizon, beyond_grid=True))
    free = builder.free_rays(position)
    to_current = invert(index.arrays["lidar_ego2global"][position])
    expected, endpoints = [], []
    for t, j in index.neighbours(position, horizon):
        f = builder.frame(j)
        points = transform_points(to_current, f.points)
        centers = transform_points(to_current, f.centers)
        outside = ~GRID.contains(points) & GRID.contains(centers)[f.cameras]
        expected.append((t, int(outside.sum())))
        endpoints.append(points[outside])
    counts = {t: int((free.time_offsets == t).sum()) for t, _ in expected}
    assert counts == dict(expected) and all(n > 20 for n in counts.values())
    np.testing.assert_allclose(np.linalg.norm(free.directions, axis=1), 1.0, atol=1e-5)
    # the pixel-centre ray points at its LiDAR point (within the pixel-rounding angle) and reaches it only after
    # leaving the grid
    endpoints = np.concatenate(endpoints)
    to_point = endpoints - free.origins
    distance = np.linalg.norm(to_point, axis=1)
    bound = pixel_rounding_bound(index[position].intrinsics)
    cos = np.einsum("ij,ij->i", to_point / distance[:, None], free.directions)
    assert (cos >= np.cos(bound) - 1e-6).all()
    assert (distance >= _grid_exit_distance(free.origins.astype(np.float64), free.directions) - 0.05).all()
    # with the free-space beams on as well, the beyond-grid rays are added to them
    both = RayBuilder(index, fixture_world.root, RayConfig(horizon=horizon, beyond_grid=True,
                                                           free_space=FreeSpaceConfig())).free_rays(position)
    assert len(both) >= len(free)


def test_beyond_grid_rays_cross_almost_no_labelled_voxel(prepared_synth_root):
    """On the synthetic world the labels are empty along the beyond-grid rays: they render nearly transparent
    through the ground-truth density, while the training rays of the same keyframe render opaque."""
    import torch
    from occflownet.occ3d import FREE, NUM_CLASSES
    from occflownet.data.index import load_index
    from occflownet.data.loaders import load_occupancy
    from occflownet.render.volume_render import RenderConfig, render_rays

    root, _ = prepared_synth_root
    synth_index = load_index(root)
    position = len(synth_index) // 2
    builder = RayBuilder(synth_index, root, RayConfig(horizon=0, beyond_grid=True))
    free = builder.free_rays(position)
    assert len(free) > 200
    labels = load_occupancy(root, synth_index[position].occupancy_path)
    density = torch.from_numpy(labels.semantics != FREE).float()
    logits = torch.zeros(*density.shape, NUM_CLASSES)
    out = render_rays(density, logits, torch.from_numpy(free.origins), torch.from_numpy(free.directions),
                      RenderConfig(), torch.Generator().manual_seed(0))
    cams = builder.rays(position)
    cam_out = render_rays(density, logits, torch.from_numpy(cams.origins[:2000]),
                          torch.from_numpy(cams.directions[:2000]), RenderConfig(), torch.Generator().manual_seed(0))
    assert float(cam_out.weight_sum.median()) > 0.9
    # measured: 27 % of them render more than half opaque here (17-32 % over this world's keyframes cross a labelled
    # voxel, mostly the top of a tree, bus or truck grazed on the way up to a point above the grid: the 0.4 m
    # voxelisation, as the in-grid rays of the same keyframes graze the road; 26-43 % of those cross a labelled
    # voxel more than 0.8 m before their point)
    assert float(out.weight_sum.median()) < 0.05 and float((out.weight_sum > 0.5).float().mean()) < 0.35
