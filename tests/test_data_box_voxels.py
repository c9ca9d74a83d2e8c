"""Box geometry: which voxel centres lie inside an (enlarged) nuScenes box."""
import numpy as np
import pytest

from occflownet.occ3d import GRID
from occflownet.geometry import quaternion_to_matrix, yaw_to_quaternion
from occflownet.data.box_voxels import enlarged_extent, voxel_centers, voxels_in_box

# The comparisons below are exact: they compare voxel indices (integers), which voxels_in_box and the brute force
# decide in float64 with a 1e-9 margin at the box faces, where CPUs' rounding differs by ~1e-14.
# (0.2, 0.2, 1.2) is a voxel centre: x, y centres are -39.8 + 0.4 n, z centres -0.8 + 0.4 n.
CENTRE = np.array([0.2, 0.2, 1.2])
CENTRE_IDX = np.array([100, 100, 5])


def _brute_force(center, size_wlh, rot, scale=1.15, add=0.4):
    """Every grid centre tested (640k points), for comparison."""
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in GRID.shape], indexing="ij"), -1).reshape(-1, 3)
    local = (voxel_centers(ijk) - center) @ rot  # rows: R^T (p - c)
    half = enlarged_extent(size_wlh, scale, add) / 2
    return ijk[np.all(np.abs(local) <= half + 1e-9, axis=1)]


def test_enlargement_is_official_and_reorders_wlh():
    # w=2 (box y), l=4 (box x), h=1.5 (box z); full edges become 1.15 * size + 0.4.
    assert np.allclose(enlarged_extent([2.0, 4.0, 1.5]), [4.0 * 1.15 + 0.4, 2.0 * 1.15 + 0.4, 1.5 * 1.15 + 0.4])


def test_axis_aligned_box_exact_count_and_set():
    vox = voxels_in_box(CENTRE, [2.0, 4.0, 1.5], 0.0)
    # half extents 2.5 (x), 1.35 (y), 1.0625 (z): |0.4 n| <= half → n in [-6, 6], [-3, 3], [-2, 2].
    assert vox.shape == (13 * 7 * 5, 3) and vox.dtype == np.int64
    expected = np.stack(np.meshgrid(np.arange(-6, 7), np.arange(-3, 4), np.arange(-2, 3), indexing="ij"),
                        -1).reshape(-1, 3) + CENTRE_IDX
    assert np.array_equal(vox, expected)  # sorted lexicographically like the meshgrid


def test_no_margin_and_yaw_90_swaps_axes():
    plain = voxels_in_box(CENTRE, [2.2, 4.2, 1.4], 0.0, margin_scale=1.0, margin_add=0.0)
    assert len(plain) == 11 * 5 * 3  # half 2.1, 1.1, 0.7
    turned = voxels_in_box(CENTRE, [2.2, 4.2, 1.4], np.pi / 2, margin_scale=1.0, margin_add=0.0)
    ext = turned.max(0) - turned.min(0) + 1
    assert list(ext) == [5, 11, 3]  # the length now lies along ego y
    # the three rotation forms agree
    q = yaw_to_quaternion(np.pi / 2)
    assert np.array_equal(voxels_in_box(CENTRE, [2.2, 4.2, 1.4], q, 1.0, 0.0), turned)
    assert np.array_equal(voxels_in_box(CENTRE, [2.2, 4.2, 1.4], quaternion_to_matrix(q), 1.0, 0.0), turned)


@pytest.mark.parametrize("yaw", [0.3, np.pi / 4, -2.0])
def test_rotated_box_matches_brute_force(yaw):
    center = np.array([12.33, -7.1, 0.9])
    size = [1.9, 4.6, 1.7]
    rot = quaternion_to_matrix(yaw_to_quaternion(yaw))
    assert np.array_equal(voxels_in_box(center, size, yaw), _brute_force(center, size, rot))


def test_tilted_box_matches_brute_force():
    # pitch + yaw (ego pitching on a slope makes box rotations non-planar in the ego frame)
    q = np.array([0.95, 0.05, 0.2, 0.22])
    center = np.array([-20.0, 15.0, 2.0])
    rot = quaternion_to_matrix(q)
    assert np.array_equal(voxels_in_box(center, [2.5, 10.0, 3.5], q), _brute_force(center, [2.5, 10.0, 3.5], rot))


def test_box_at_grid_edge_is_clipped_and_outside_is_empty():
    vox = voxels_in_box([39.9, 0.2, 1.2], [2.0, 4.0, 1.5], 0.0)
    assert len(vox) and vox[:, 0].max() == 199 and vox.min() >= 0
    assert len(vox) == 7 * 7 * 5  # x centres 37.4 (on the face, included) … 39.8; 40.2 lies outside the grid
    assert voxels_in_box([60.0, 0.0, 1.0], [2.0, 4.0, 1.5], 0.0).shape == (0, 3)


def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="size_wlh"):
        voxels_in_box(CENTRE, [-1.0, 2.0, 1.0], 0.0)
    with pytest.raises(ValueError, match="rotation"):
        voxels_in_box(CENTRE, [1.0, 2.0, 1.0], np.eye(2))
    with pytest.raises(ValueError, match="center"):
        voxels_in_box([np.nan, 0, 0], [1.0, 2.0, 1.0], 0.0)
