"""File loaders (images, LiDAR, lidarseg, Occ3D) and projection of a real nuScenes LiDAR sweep into its cameras."""
import json
from pathlib import Path

import numpy as np
import pytest
from nuscenes_fixture import fixture_world  # noqa: F401

from occflownet.occ3d import CAMERAS, GRID
from occflownet.data.builder import build_index
from occflownet.data.loaders import (load_image, load_lidar, load_lidarseg, load_occupancy, load_sample_images)
from occflownet.data.rays import project_points
from occflownet.data.tables import DatasetError
from occflownet.geometry import invert, transform_points
from occflownet.contract import calibration_arrays

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
OCC3D = SHARED / "occ3d-sample" / "labels.npz"
FRAME = SHARED / "nuscenes-frame"


@pytest.mark.skipif(not OCC3D.is_file(), reason=f"real Occ3D sample not found at {OCC3D}")
def test_real_occ3d_labels_load():
    occ = load_occupancy(OCC3D.parent, OCC3D.name)
    for a in (occ.semantics, occ.mask_lidar, occ.mask_camera):
        assert a.shape == (200, 200, 16) and a.dtype == np.uint8
    assert occ.semantics.max() == 17 and set(np.unique(occ.mask_camera)) == {0, 1}
    # a real keyframe is mostly free space, with driveable surface under the ego
    assert (occ.semantics == 17).mean() > 0.5
    assert (occ.semantics[95:105, 95:105] == 11).any()


def test_occupancy_errors_name_the_problem(tmp_path):
    good = np.zeros((200, 200, 16), np.uint8)
    np.savez(tmp_path / "nokey.npz", semantics=good, mask_lidar=good)
    with pytest.raises(DatasetError, match="nokey.npz: lacks array 'mask_camera'"):
        load_occupancy(tmp_path, "nokey.npz")
    np.savez(tmp_path / "shape.npz", semantics=good[:, :, :8], mask_lidar=good, mask_camera=good)
    with pytest.raises(DatasetError, match="'semantics' has shape \\(200, 200, 8\\)"):
        load_occupancy(tmp_path, "shape.npz")
    np.savez(tmp_path / "dtype.npz", semantics=good, mask_lidar=good.astype(bool), mask_camera=good)
    with pytest.raises(DatasetError, match="'mask_lidar' has dtype bool"):
        load_occupancy(tmp_path, "dtype.npz")
    np.savez(tmp_path / "range.npz", semantics=good + 18, mask_lidar=good, mask_camera=good)
    with pytest.raises(DatasetError, match="holds class 18"):
        load_occupancy(tmp_path, "range.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError, match="junk.npz: cannot read"):
        load_occupancy(tmp_path, "junk.npz")
    with pytest.raises(DatasetError, match="missing.npz: Occ3D labels file is missing"):
        load_occupancy(tmp_path, "missing.npz")


def test_lidar_and_lidarseg_loaders(tmp_path):
    pts = np.arange(20, dtype=np.float32).reshape(4, 5)
    pts.tofile(tmp_path / "ok.pcd.bin")
    np.testing.assert_array_equal(load_lidar(tmp_path, "ok.pcd.bin"), pts)       # exact: read back
    np.arange(7, dtype=np.float32).tofile(tmp_path / "bad.pcd.bin")
    with pytest.raises(DatasetError, match="bad.pcd.bin: 7 float32 values is not a multiple of 5"):
        load_lidar(tmp_path, "bad.pcd.bin")
    with pytest.raises(DatasetError, match="gone.pcd.bin: LiDAR file is missing"):
        load_lidar(tmp_path, "gone.pcd.bin")
    np.array([1, 2, 3], np.uint8).tofile(tmp_path / "seg.bin")
    assert load_lidarseg(tmp_path, "seg.bin", 3).tolist() == [1, 2, 3]
    with pytest.raises(DatasetError, match="seg.bin: 3 labels for a sweep of 4 points"):
        load_lidarseg(tmp_path, "seg.bin", 4)


def test_images_are_rgb_and_sized(fixture_world):
    index = build_index(fixture_world.root)
    images = load_sample_images(fixture_world.root, index[0])
    assert images.shape == (6, 900, 1600, 3) and images.dtype == np.uint8
    # the fixture paints camera c with RGB (40c, 255-40c, 128); JPEG is lossy
    for c in range(6):
        assert np.abs(images[c].mean(axis=(0, 1)) - [40 * c, 255 - 40 * c, 128]).max() < 3
    with pytest.raises(DatasetError, match="image is 1600x900, the tables say 800x450"):
        load_image(fixture_world.root, index[0].cameras[0].path, (800, 450))


@pytest.fixture(scope="module")
def real_frame():
    if not (FRAME / "calib.json").is_file():
        pytest.skip(f"real nuScenes frame not found at {FRAME}")
    calib = json.loads((FRAME / "calib.json").read_text())
    K, cam2ego = calibration_arrays(calib)
    sweep = load_lidar(FRAME, "lidar.bin")
    ego = transform_points(np.asarray(calib["lidar2ego"]), sweep[:, :3])
    return K.astype(np.float64), cam2ego.astype(np.float64), ego, calib["image_size"]


def _projection_checks(K, world_to_cams, cam2ego, ego, size):
    """Per-camera hit counts, fraction of ground hits below the horizon row, 99th pct azimuth off the optical axis."""
    hits = project_points(ego, world_to_cams, K, np.array([size] * 6))
    azimuth = np.degrees(np.arctan2(ego[:, 1], ego[:, 0]))
    ground = np.abs(ego[:, 2]) < 0.3
    out = []
    for c in range(6):
        m = hits.camera == c
        axis = cam2ego[c, :3, 2]  # optical axis in the ego frame
        yaw = np.degrees(np.arctan2(axis[1], axis[0]))
        off = np.abs((azimuth[hits.point_index[m]] - yaw + 180) % 360 - 180)
        below = hits.uv[m & ground[hits.point_index], 1] > K[c, 1, 2]
        out.append((int(m.sum()), float(below.mean()), float(np.percentile(off, 99))))
    return hits, out


def test_real_lidar_projects_into_every_real_camera(real_frame):
    K, cam2ego, ego, size = real_frame
    assert size == [1600, 900]
    hits, checks = _projection_checks(K, np.stack([invert(T) for T in cam2ego]), cam2ego, ego, size)
    seen = np.unique(hits.point_index)
    # ~58% of a nuScenes sweep falls into some camera (cameras see ±~20° vertically, the LiDAR +10°/-30°)
    assert 0.45 < len(seen) / len(ego) < 0.7
    assert GRID.contains(ego).mean() > 0.85
    for name, (count, below, off) in zip(CAMERAS, checks):
        assert count > 2000, name
        assert below > 0.99, name          # ground points lie below the principal row: cameras upright
        assert off < 50, name              # points seen lie within the camera's horizontal field of view
    # overlapping neighbours: some points are seen by two cameras, none by more than three
    per_point = np.bincount(hits.point_index)
    assert (per_point == 2).sum() > 300 and per_point.max() <= 3
    # negative control: using cam2ego where its inverse belongs breaks the checks
    _, wrong = _projection_checks(K, cam2ego, cam2ego, ego, size)
    assert sum(below > 0.99 and off < 50 for _, below, off in wrong) == 0
