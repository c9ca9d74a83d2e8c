import numpy as np
import torch

from occflownet import geometry, occ3d
from occflownet.occ3d import GRID


def test_grid_matches_occ3d():
    assert GRID.shape == (200, 200, 16)
    for axis in range(3):
        extent = GRID.upper[axis] - GRID.lower[axis]
        assert np.isclose(extent / GRID.voxel_size, GRID.shape[axis])
    assert np.allclose(GRID.centers(0)[[0, -1]], [-39.8, 39.8])
    assert np.allclose(GRID.centers(2)[[0, -1]], [-0.8, 5.2])


def test_index_of_voxel_centres_round_trip():
    ijk = np.stack(np.meshgrid(*[np.arange(0, s, 7) for s in GRID.shape], indexing="ij"), -1).reshape(-1, 3)
    centres = np.asarray(GRID.lower) + (ijk + 0.5) * GRID.voxel_size
    assert np.array_equal(GRID.index_of(centres), ijk)
    assert GRID.contains(centres).all()
    assert not GRID.contains(np.array([[40.0, 0, 0], [0, 0, -1.01], [0, 0, 5.4]])).any()


def test_index_of_torch_tensors_follow_the_same_rule():
    ijk = np.array([[0, 0, 0], [199, 199, 15], [100, 37, 4]])
    centres = np.asarray(GRID.lower) + (ijk + 0.5) * GRID.voxel_size
    for dtype in (torch.float32, torch.float64):
        got = GRID.index_of(torch.tensor(centres, dtype=dtype))
        assert got.dtype == torch.int64 and np.array_equal(got.numpy(), ijk)
    # on the lower corner, just outside / inside the faces, on the upper faces (indices may leave the grid)
    edges = np.array([[-40.0, -40.0, -1.0], [-40.01, 39.99, 5.4], [40.0, 0.0, -1.2]])
    expected = np.array([[0, 0, 0], [-1, 199, 16], [200, 100, -1]])
    assert np.array_equal(GRID.index_of(edges), expected)
    assert np.array_equal(GRID.index_of(torch.tensor(edges, dtype=torch.float64)).numpy(), expected)


def test_cells_of_equals_the_plain_rule_on_any_shape():
    # cells_of merges the last two axes to subtract the lower corner (a broadcast onnxruntime runs faster); the
    # values must be those of the plain per-point rule, bit for bit, non-finite points included
    gen = torch.Generator().manual_seed(0)
    lower = torch.tensor(GRID.lower)
    for shape in [(3,), (1, 3), (7, 3), (2, 5, 4, 3), (0, 3)]:
        points = (torch.rand(shape, generator=gen) - 0.5) * 100
        if points.numel() > 6:
            points.view(-1)[[1, 5]] = torch.tensor([float("inf"), float("nan")])
        got = GRID.cells_of(points)
        want = ((points - lower) / GRID.voxel_size).floor()
        assert got.shape == points.shape
        assert torch.equal(torch.nan_to_num(got, nan=-7.0), torch.nan_to_num(want, nan=-7.0))


def test_class_table():
    assert len(occ3d.CLASS_NAMES) == 18 and occ3d.CLASS_NAMES[occ3d.FREE] == "free"
    assert occ3d.CLASS_COLORS.shape == (18, 3)
    assert set(occ3d.DYNAMIC_CLASSES).isdisjoint(occ3d.STATIC_CLASSES)
    assert len(occ3d.DYNAMIC_CLASSES) + len(occ3d.STATIC_CLASSES) == occ3d.NUM_CLASSES


def test_lidarseg_mapping_known_answers():
    raw = np.array([9, 14, 15, 16, 17, 18, 21, 2, 3, 4, 6, 12, 22, 23, 24, 25, 26, 27, 28, 30, 0, 1, 5, 31])
    want = np.array([1, 2, 3, 3, 4, 5, 6, 7, 7, 7, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 0, 0, 0, 0])
    assert np.array_equal(occ3d.map_lidarseg(raw), want)
    assert occ3d.category_to_occ3d("vehicle.car") == 4
    assert occ3d.category_to_occ3d("human.pedestrian.adult") == 7
    assert occ3d.category_to_occ3d("not.a.category") == 0


def test_quaternion_round_trip_and_inverse():
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= np.sign(q[0])
        assert np.allclose(geometry.matrix_to_quaternion(geometry.quaternion_to_matrix(q)), q)
        T = geometry.make_transform(q, rng.normal(size=3))
        assert np.allclose(geometry.invert(T) @ T, np.eye(4))
        p = rng.normal(size=(5, 3))
        assert np.allclose(geometry.transform_points(geometry.invert(T), geometry.transform_points(T, p)), p)


def test_yaw_quaternion_rotates_x_to_y():
    R = geometry.quaternion_to_matrix(geometry.yaw_to_quaternion(np.pi / 2))
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(geometry.rotation_z(np.pi / 2)[:3, :3], R)


def test_default_rig_projects_forward_point_to_front_camera_centre():
    from occflownet.contract import calibration_arrays
    from occflownet.rig import default_rig

    K, T = calibration_arrays(default_rig(800, 450))
    p_ego = np.array([20.0, 0.0, 1.51, 1.0])
    p_cam = np.linalg.inv(T[0]) @ p_ego
    uv = K[0] @ p_cam[:3]
    assert np.allclose(uv[:2] / uv[2], [400, 225], atol=0.5)
    # CAM_BACK looks backwards: a point behind the car has positive depth there.
    assert (np.linalg.inv(T[3]) @ np.array([-20.0, 0, 1.5, 1]))[2] > 0


def test_calibration_errors_are_clear():
    import pytest

    from occflownet.contract import calibration_arrays
    from occflownet.rig import default_rig

    calib = default_rig()
    del calib["cameras"]["CAM_BACK"]
    with pytest.raises(KeyError, match="CAM_BACK"):
        calibration_arrays(calib)
    calib = default_rig()
    calib["cameras"]["CAM_FRONT"]["intrinsic"] = [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    with pytest.raises(ValueError, match="singular"):
        calibration_arrays(calib)
