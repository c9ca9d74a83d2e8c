"""Where the free stretch in front of a ray's point ends: known answers on hand-made points, the trilinear footprint
it promises, and both rules against the synthetic world's labels."""
import numpy as np
import pytest
import torch

from occflownet.data.free_stretch import (FREE_BEFORE_MIN, free_segment_ends, near_point_voxels,
                                          point_clearance_ends)
from occflownet.occ3d import FREE, GRID, NUM_CLASSES
from occflownet.render.volume_render import RenderConfig, render_rays


def _centre(ijk):
    return np.asarray(GRID.lower) + (np.asarray(ijk) + 0.5) * GRID.voxel_size


def test_near_point_voxels_is_the_point_voxels_and_their_26_neighbours():
    near = near_point_voxels(np.array([_centre((100, 100, 8)), _centre((0, 199, 15)), [500.0, 0.0, 0.0]]))
    assert near[99:102, 99:102, 7:10].all()
    assert near[0:2, 198:200, 14:16].all()                      # at the grid's corner: clipped, no wrap-around
    assert near.sum() == 27 + 8                                  # the point outside the grid adds nothing
    assert not near[102, 100, 8] and not near[100, 100, 10]


def test_head_on_ray_ends_where_it_enters_the_voxel_before_the_point():
    wall = np.array([[10.1, y, z] for y in np.arange(-3.0, 3.0, 0.1) for z in np.arange(-0.5, 3.0, 0.1)])
    origins, directions = np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]])
    ends = point_clearance_ends(origins, directions, np.array([10.1]), near_point_voxels(wall))
    # the wall's points lie in x voxel [10.0, 10.4): the voxel before it starts at 9.6 m
    assert ends.dtype == np.float32 and ends[0] == pytest.approx(9.6, abs=1e-5)
    assert ends[0] > free_segment_ends(10.1)                    # the fraction rule stops at 7.48 m


def test_a_ray_grazing_other_points_ends_where_it_first_comes_near_them():
    # a ray 0.3 m above a row of points that starts at x = 2 m: the row's voxels begin at 2.0 m, their neighbours at
    # 1.6 m, long before the ray's own point at 20 m (the fraction rule would run on to 15.4 m, along the row)
    row = np.array([[x, 0.0, 0.7] for x in np.arange(2.05, 20.0, 0.1)])
    origins, directions = np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]])
    ends = point_clearance_ends(origins, directions, np.array([20.0]),
                                near_point_voxels(np.vstack([row, [[20.0, 0.0, 1.0]]])))
    assert ends[0] == pytest.approx(1.6, abs=1e-5)


def test_a_ray_that_meets_no_point_runs_to_its_depth():
    ends = point_clearance_ends(np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]]), np.array([12.0]),
                               near_point_voxels(np.array([[-20.0, -20.0, 2.0]])))
    assert ends[0] == pytest.approx(12.0)


def test_stretches_render_free_through_a_volume_dense_at_the_points():
    """The promise of the one-voxel neighbourhood: the trilinear lookup of every sample up to the end reads no voxel
    that holds a point, so rays of many directions render exactly transparent up to their ends."""
    rng = np.random.default_rng(0)
    points = rng.uniform([-30, -30, -0.8], [30, 30, 5.0], size=(400, 3))
    origins = np.tile([[0.0, 0.0, 1.5]], (400, 1))
    directions = points - origins
    depths = np.linalg.norm(directions, axis=1)
    directions /= depths[:, None]
    ends = point_clearance_ends(origins, directions, depths, near_point_voxels(points))
    assert np.all(ends <= depths) and np.all(ends >= 0)
    density = torch.from_numpy(near_point_voxels(points, GRID) & False).float()
    ijk = GRID.index_of(points)
    density[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = 1.0                # σ only in the voxels that hold a point
    keep = ends >= FREE_BEFORE_MIN
    assert keep.sum() > 200
    out = render_rays(density, torch.zeros(*density.shape, NUM_CLASSES), torch.from_numpy(origins[keep]).float(),
                      torch.from_numpy(directions[keep]).float(), RenderConfig(), torch.Generator().manual_seed(0),
                      far=torch.from_numpy(ends[keep]))
    assert float(out.weight_sum.max()) == 0.0
    full = render_rays(density, torch.zeros(*density.shape, NUM_CLASSES), torch.from_numpy(origins[keep]).float(),
                       torch.from_numpy(directions[keep]).float(), RenderConfig(), torch.Generator().manual_seed(0),
                       far=torch.from_numpy(depths[keep] + 0.5).float())
    assert float(full.weight_sum.median()) > 0.1                 # the points do stop the light beyond the ends


def test_both_rules_render_free_through_the_labels(prepared_synth_root):
    """The stretch of each ray up to its end renders transparent through the ground truth (σ = 1 at labelled voxels)
    on the synthetic world; a fixed 0.6 m margin would not do (rays that meet the road at a shallow angle run inside
    its voxel layer for metres before their point), and the points rule ends the stretches of rays to walls far
    closer to their points than the fraction rule at no more crossings."""
    from occflownet.data.index import load_index
    from occflownet.data.loaders import load_occupancy
    from occflownet.data.rays import RayBuilder, RayConfig

    root, _ = prepared_synth_root
    synth_index = load_index(root)
    position = len(synth_index) // 2
    labels = load_occupancy(root, synth_index[position].occupancy_path).semantics
    density = torch.from_numpy(labels != FREE).float()
    logits = torch.zeros(*density.shape, NUM_CLASSES)
    pick = None

    def stretches(rule):
        nonlocal pick
        rays = RayBuilder(synth_index, root, RayConfig(horizon=0, free_stretch=rule)).rays(position)
        if pick is None:
            pick = np.random.default_rng(0).choice(len(rays), 3000, replace=False)
        return rays.take(pick)

    def opacity(rays, ends):
        keep = ends >= FREE_BEFORE_MIN
        out = render_rays(density, logits, torch.from_numpy(rays.origins[keep]), torch.from_numpy(rays.directions[keep]),
                          RenderConfig(), torch.Generator().manual_seed(0), far=torch.from_numpy(ends[keep]))
        return out.weight_sum, keep.mean()

    fraction, points = stretches("fraction"), stretches("points")
    walls = np.isin(points.labels, (15, 16))             # manmade, vegetation
    np.testing.assert_array_equal(fraction.depths, points.depths)      # exact: the same rays (the rule sets ends only)
    np.testing.assert_allclose(fraction.free_ends, free_segment_ends(fraction.depths), rtol=1e-6)
    ours, share = opacity(fraction, fraction.free_ends)
    fixed, _ = opacity(fraction, fraction.depths - 0.6)
    near, _ = opacity(points, points.free_ends)
    assert share > 0.85                                  # measured: 90 % of the rays have a free stretch
    # measured: 4.8 % of the stretches render more than half opaque (15.7 % with the fixed margin), median 0
    assert float(ours.median()) < 0.02 and float((ours > 0.5).float().mean()) < 0.1
    assert float((fixed > 0.5).float().mean()) > 2 * float((ours > 0.5).float().mean())
    # the points rule: no stretch more than half opaque (measured 0 of 3,000), and 75 % of the rays have one
    assert float((near > 0.5).float().mean()) < 0.01 and float(near.median()) == 0.0
    assert (points.free_ends >= FREE_BEFORE_MIN).mean() > 0.6
    assert np.all(points.free_ends <= points.depths)


def test_near_point_masks_spare_what_the_beyond_grid_rays_graze(prepared_synth_root):
    """With the points rule the free rays leave out the voxels near a LiDAR point of their frame
    (``RayBuilder.near_points``): far fewer labelled voxels are then crossed by the beyond-grid rays."""
    from occflownet.data.index import load_index
    from occflownet.data.loaders import load_occupancy
    from occflownet.data.rays import RayBuilder, RayConfig
    from occflownet.voxel_walk import walk_rays

    root, _ = prepared_synth_root
    synth_index = load_index(root)
    position = len(synth_index) // 2
    occupied = load_occupancy(root, synth_index[position].occupancy_path).semantics != FREE
    builder = RayBuilder(synth_index, root, RayConfig(horizon=0, beyond_grid=True, free_stretch="points"))
    free = builder.free_rays(position)
    near = builder.near_points(position, position)
    assert near.shape == occupied.shape and near is builder.near_points(position, position)      # cached

    def crossing(volume):
        walk = walk_rays(volume.astype(np.uint8), free.origins, free.directions, lower=GRID.lower,
                         voxel_size=GRID.voxel_size)
        return (walk.code != 0).mean()

    # measured: 32 % of them cross a labelled voxel, 2.8 % one outside those near a point
    assert len(free) > 100 and crossing(occupied & ~near) < 0.5 * crossing(occupied)
