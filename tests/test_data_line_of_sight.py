"""Line of sight through object boxes: slab tests with known answers, against dense sampling, and the ray filter
of RayBuilder (``RayConfig.box_line_of_sight``) on the fixture world with its moving car and pedestrian."""
import numpy as np
import pytest
from nuscenes_fixture import fixture_world  # noqa: F401

from occflownet.data.builder import build_index
from occflownet.data.line_of_sight import MARGIN, blocked_by_boxes, segment_box_hits
from occflownet.data.box_voxels import box_rotation
from occflownet.data.records import EgoBoxes
from occflownet.data.rays import RayBuilder, RayConfig


def _boxes(centers, sizes_wlh, yaws) -> EgoBoxes:
    yaws = np.asarray(yaws, dtype=np.float64)
    return EgoBoxes(instance_tokens=np.array([f"b{i}" for i in range(len(yaws))]),
                    labels=np.full(len(yaws), 4, dtype=np.uint8), centers=np.asarray(centers, dtype=np.float64),
                    sizes=np.asarray(sizes_wlh, dtype=np.float64), rotations=np.stack([box_rotation(y) for y in yaws]),
                    yaws=yaws)


# one car-sized box at x = 10 m: length 4 along x, width 2 along y, height 2 along z (nuScenes wlh = 2, 4, 2)
CAR = _boxes([[10.0, 0.0, 1.0]], [[2.0, 4.0, 2.0]], [0.0])


def test_segment_box_hits_known_answers():
    x = np.array([1.0, 0.0, 0.0])
    origins = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [13, 0, 1], [0, 1.1, 1], [0, 1.3, 1], [0, 0, 1]], float)
    directions = np.array([x, x, x, x, x, x, [0, 1, 0]])
    lengths = np.array([20.0, 7.0, 7.9, 5.0, 20.0, 20.0, np.inf])
    hit = np.zeros(len(origins), dtype=bool)
    hit[segment_box_hits(origins, directions, lengths, CAR, margin=0.2)[0]] = True
    # through the middle; stops at 7 m, 0.8 m short of the grown face at 7.8 m; reaches 7.9 m; starts beyond the
    # box, going away; parallel to the y slabs inside the margin (|y| 1.1 ≤ 1.2) and outside it (1.3); along y at x = 0
    np.testing.assert_array_equal(hit, [True, False, True, False, True, False, False])
    # a 45° turned box: a segment through its axis-aligned bounds' corner misses the box itself
    turned = _boxes([[0.0, 0.0, 0.0]], [[2.0, 2.0, 2.0]], [np.pi / 4])
    diagonal = np.array([[1.0, -1.0, 0.0]]) / np.sqrt(2.0)       # along x + y = 1.8, beside the face x + y = √2
    corner = segment_box_hits(np.array([[-2.1, 3.9, 0.0]]), diagonal, np.array([10.0]), turned, margin=0.0)[0]
    through = segment_box_hits(np.array([[-5.0, 0.5, 0.0]]), np.array([[1.0, 0.0, 0.0]]), np.array([10.0]), turned,
                               margin=0.0)[0]
    assert len(corner) == 0 and list(through) == [0]


def test_segment_box_hits_agree_with_dense_sampling():
    rng = np.random.default_rng(3)
    boxes = _boxes(rng.uniform(-8, 8, (6, 3)), rng.uniform(0.5, 5, (6, 3)), rng.uniform(-np.pi, np.pi, 6))
    origins = rng.uniform(-12, 12, (800, 3))
    directions = rng.normal(size=(800, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    lengths = rng.uniform(0, 25, 800)
    hits = segment_box_hits(origins, directions, lengths, boxes, margin=MARGIN)
    s = np.linspace(0, 1, 4001)
    points = origins[:, None] + (s[None, :, None] * lengths[:, None, None]) * directions[:, None]   # [R, S, 3]
    inside = boxes.contains(points.reshape(-1, 3), MARGIN).reshape(len(boxes), len(origins), len(s)).any(axis=2)
    for b in range(len(boxes)):
        got = np.zeros(len(origins), dtype=bool)
        got[hits[b]] = True
        assert (inside[b] <= got).all()              # every sampled crossing is found
        # and what the sampling misses only grazes the box (a sample step is at most 25 / 4000 m)
        slack = segment_box_hits(origins[got & ~inside[b]], directions[got & ~inside[b]],
                                 lengths[got & ~inside[b]], boxes.take([b]), margin=MARGIN - 0.01)[0]
        assert len(slack) == 0
    assert inside.any(axis=1).all() and inside.sum() > 40   # every box is crossed, 56 times in all


def test_blocked_by_boxes_spares_rays_that_end_on_the_object():
    x = np.array([[1.0, 0.0, 0.0]] * 4)
    origins = np.array([[0, 0, 1]] * 4, float)
    # ends on the car's near face; ends behind it; a free ray through it; ends in front of it
    lengths = np.array([8.05, 15.0, np.inf, 5.0])
    np.testing.assert_array_equal(blocked_by_boxes(origins, x, lengths, CAR), [False, True, True, False])
    none = CAR.take(np.zeros(0, dtype=np.int64))
    assert not blocked_by_boxes(origins, x, lengths, none).any()
    # a ray that ends in one box but crosses another first is blocked by the first
    two = EgoBoxes.concatenate([_boxes([[5.0, 0.0, 1.0]], [[1.0, 1.0, 1.0]], [0.0]), CAR])
    assert blocked_by_boxes(origins[:1], x[:1], lengths[:1], two).tolist() == [True]


@pytest.fixture(scope="module")
def index(fixture_world):
    return build_index(fixture_world.root)


def test_ray_builder_drops_exactly_the_rays_whose_sight_a_box_blocks(fixture_world, index):
    position, horizon = 2, 2
    plain = RayBuilder(index, fixture_world.root, RayConfig(horizon=horizon, beyond_grid=True))
    sight = RayBuilder(index, fixture_world.root, RayConfig(horizon=horizon, beyond_grid=True,
                                                            box_line_of_sight=True))
    all_rays, kept = plain.rays(position), sight.rays(position)
    dropped_total = 0
    for t, j in index.neighbours(position, horizon):
        a, k = all_rays.take(all_rays.time_offsets == t), kept.take(kept.time_offsets == t)
        boxes = sight.sight_boxes(position, j)
        # the keyframe's boxes (the car, the pedestrian) and, for t ≠ 0, those of frame j as well
        assert len(boxes) == (2 if t == 0 else 4)
        blocked = blocked_by_boxes(a.origins, a.directions, a.depths, boxes)
        # exact: the kept rays are copies of the plain ones, chosen by the same function on the same inputs
        np.testing.assert_array_equal(k.depths, a.depths[~blocked])
        np.testing.assert_array_equal(k.origins, a.origins[~blocked])
        dropped_total += int(blocked.sum())
        # no kept ray's segment, sampled every 5 cm, enters a box that does not hold its endpoint
        ends = k.endpoints().astype(np.float64)
        holds = boxes.contains(ends, MARGIN)
        for s in np.linspace(0, 1, 200)[:-1]:
            p = k.origins + (s * k.depths)[:, None] * k.directions
            assert not (boxes.contains(p, MARGIN - 0.01) & ~holds).any()
    assert dropped_total > 50
    # free rays go on past the grid: any box on their way removes them
    free_all, free_kept = plain.free_rays(position), sight.free_rays(position)
    assert 0 < len(free_kept) < len(free_all)
    assert not any(blocked_by_boxes(free_kept.origins[free_kept.time_offsets == t],
                                    free_kept.directions[free_kept.time_offsets == t],
                                    np.full(int((free_kept.time_offsets == t).sum()), np.inf),
                                    sight.sight_boxes(position, j)).any()
                   for t, j in index.neighbours(position, horizon))
    # cached masks give the same rays again (exact: copies)
    np.testing.assert_array_equal(sight.rays(position).depths, kept.depths)


def test_ray_builder_keeps_its_sight_results_within_its_byte_budget(fixture_world, index, monkeypatch):
    """Line-of-sight masks, free-stretch ends and near-point masks are computed once per keyframe pair and kept
    while they fit ``sight_bytes`` (the least recently used dropped first): a second pass over every keyframe
    recomputes nothing under the default budget, everything under a budget of one byte, with the same rays."""
    import occflownet.data.rays as rays_module

    calls = []
    blocked = rays_module.blocked_by_boxes
    monkeypatch.setattr(rays_module, "blocked_by_boxes", lambda *a: calls.append(1) or blocked(*a))
    config = RayConfig(horizon=1, beyond_grid=True, box_line_of_sight=True, free_stretch="points")
    positions = range(len(index))
    for budget, recomputed in ((rays_module.SIGHT_CACHE_BYTES, False), (1, True)):
        builder = RayBuilder(index, fixture_world.root, config, sight_bytes=budget)
        first = [(builder.rays(p), builder.free_rays(p)) for p in positions]
        calls.clear()
        second = [(builder.rays(p), builder.free_rays(p)) for p in positions]
        assert bool(calls) == recomputed
        assert len(builder._sight) == 1 if recomputed else builder._sight_total <= budget
        for (a, fa), (b, fb) in zip(first, second):
            np.testing.assert_array_equal(a.depths, b.depths)
            np.testing.assert_array_equal(a.free_ends, b.free_ends)
            np.testing.assert_array_equal(fa.directions, fb.directions)
