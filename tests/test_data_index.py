"""The sample index read straight from nuScenes JSON tables: content, splits, errors, save/load."""
import json
import shutil

import numpy as np
import pytest
from nuscenes_fixture import (CAMERA_DELAY_US, LIDAR2EGO, MOVERS, SCENES, VERSION, ego_pose, fixture_world,  # noqa: F401
                              mover_box, write_fixture)

from occflownet.occ3d import CAMERAS, category_to_occ3d
from occflownet.data.builder import _splits, build_index
from occflownet.data.index import FORMAT_VERSION, index_dir, load_index, save_index
from occflownet.data.tables import DatasetError
from occflownet.geometry import invert
from occflownet.rig import default_rig


@pytest.fixture()
def tables_root(tmp_path):
    """A fresh fixture root without images (tables, LiDAR, lidarseg): safe to break."""
    return write_fixture(tmp_path / "root", write_images=False)


def _edit_table(fx, name, edit):
    path = fx.root / fx.version / f"{name}.json"
    records = json.loads(path.read_text())
    records = edit(records)
    path.write_text(json.dumps(records))


def test_index_content_matches_the_fixture(fixture_world):
    fx = fixture_world
    index = build_index(fx.root)
    assert index.version == VERSION and len(index) == sum(n for _, n, _ in SCENES)
    assert index.scene_names == ["scene-a", "scene-b"]
    # written in reverse time order; the index sorts each scene by time
    assert index.tokens == fx.sample_tokens["scene-a"] + fx.sample_tokens["scene-b"]
    s = index[3]
    assert (s.scene_name, s.index_in_scene) == ("scene-a", 3)
    assert s.scene_sample_tokens == tuple(fx.sample_tokens["scene-a"])
    lidar_us = fx.lidar_time(0, 3)
    assert s.timestamp == s.lidar.timestamp == lidar_us
    np.testing.assert_allclose(s.ego2global, ego_pose(0, lidar_us), atol=1e-9)
    np.testing.assert_allclose(s.lidar.sensor2ego, LIDAR2EGO, atol=1e-4)
    assert s.lidar.path.endswith(".pcd.bin") and s.lidarseg_path.endswith(f"{s.lidar.token}_lidarseg.bin")
    assert s.occupancy_path == f"gts/scene-a/{s.token}/labels.npz"
    assert index[5].occupancy_path is None  # scene-b has no gts directory
    rig = default_rig(1600, 900)
    assert [c.name for c in s.cameras] == list(CAMERAS)
    for c, cam in enumerate(s.cameras):
        assert cam.timestamp == lidar_us + CAMERA_DELAY_US[c]
        assert (cam.width, cam.height) == (1600, 900) and cam.path.startswith(f"samples/{cam.name}/")
        np.testing.assert_allclose(cam.intrinsic, rig["cameras"][cam.name]["intrinsic"])
        np.testing.assert_allclose(cam.sensor2ego, rig["cameras"][cam.name]["cam2ego"], atol=1e-9)
        # each camera carries the ego pose at its own timestamp, not the LiDAR's
        np.testing.assert_allclose(cam.ego2global, ego_pose(0, cam.timestamp), atol=1e-9)
    assert s.intrinsics.shape == (6, 3, 3) and s.cam2ego.shape == (6, 4, 4)
    assert s.image_sizes.tolist() == [[1600, 900]] * 6


def test_boxes_global_and_in_ego_frame(fixture_world):
    fx = fixture_world
    index = build_index(fx.root)
    s = index[2]
    assert list(s.boxes.category_names) == [m[1] for m in MOVERS]
    assert list(s.boxes.labels) == [category_to_occ3d(m[1]) for m in MOVERS]
    assert s.boxes.sizes.tolist() == [list(m[3]) for m in MOVERS]
    ego = s.boxes_in_ego()
    for b, mover in enumerate(MOVERS):
        truth = invert(s.ego2global) @ mover_box(mover, 2 * 0.5)  # box → current ego
        np.testing.assert_allclose(ego.transforms()[b], truth, atol=1e-6)
        np.testing.assert_allclose(ego.yaws[b], np.arctan2(truth[1, 0], truth[0, 0]), atol=1e-9)
    # the same instance keeps its token across keyframes
    assert list(index[3].boxes.instance_tokens) == list(s.boxes.instance_tokens)
    # contains(): the box centre and a point just outside its length
    car = ego.transforms()[0]
    inside = car[:3, 3]
    outside = (car @ [MOVERS[0][3][1] / 2 + 0.05, 0, 0, 1])[:3]
    assert ego.contains(np.stack([inside, outside]))[0].tolist() == [True, False]
    assert ego.contains(outside[None], margin=0.1)[0].tolist() == [True]


def test_temporal_neighbours_stay_inside_the_scene(fixture_world):
    index = build_index(fixture_world.root)
    assert index.neighbours(0, 3) == [(0, 0), (1, 1), (2, 2), (3, 3)]
    assert index.neighbours(2, 3) == [(-2, 0), (-1, 1), (0, 2), (1, 3), (2, 4)]
    assert index.neighbours(4, 1) == [(-1, 3), (0, 4)]
    assert index.neighbours(5, 3) == [(0, 5), (1, 6)]  # scene-b: never borrows scene-a's frames
    assert index.neighbours(6, 0) == [(0, 6)]


def test_splits_all_named_and_errors(tables_root):
    fx = tables_root
    assert build_index(fx.root).available_splits() == ["all"]
    (fx.root / fx.version / "splits.json").write_text(json.dumps({"train": ["scene-a"], "val": ["scene-b"]}))
    index = build_index(fx.root)
    assert index.available_splits() == ["all", "train", "val"]
    assert index.split_positions("train").tolist() == [0, 1, 2, 3, 4]
    assert index.split_positions("val").tolist() == [5, 6]
    assert index.split_positions("all").tolist() == list(range(7))
    with pytest.raises(KeyError, match="unknown split 'test'.*all, train, val"):
        index.split_positions("test")
    (fx.root / fx.version / "splits.json").write_text(json.dumps({"train": ["scene-zzz"]}))
    with pytest.raises(DatasetError, match="split 'train' names scenes this root does not have: scene-zzz"):
        build_index(fx.root)


def test_mini_has_builtin_splits(tmp_path):
    names = [f"scene-{n}" for n in ("0061", "0103", "0553", "0655", "0757", "0796", "0916", "1077", "1094", "1100")]
    splits = _splits(tmp_path, "v1.0-mini", names)
    assert splits["mini_train"] == splits["train"] == ["scene-0061", "scene-0553", "scene-0655", "scene-0757",
                                                       "scene-0796", "scene-1077", "scene-1094", "scene-1100"]
    assert splits["mini_val"] == splits["val"] == ["scene-0103", "scene-0916"]
    assert splits["all"] == names
    assert set(_splits(tmp_path, "v1.0-trainval", names)) == {"all"}
    # a mini root lacking some mini scenes is an error naming them
    fx = write_fixture(tmp_path / "mini", version="v1.0-mini", write_images=False)
    _edit_table(fx, "scene", lambda rs: [{**r, "name": {"scene-a": "scene-0061", "scene-b": "scene-0103"}[r["name"]]}
                                         for r in rs])
    with pytest.raises(DatasetError, match="split 'mini_train' names scenes this root does not have: scene-0553, "):
        build_index(fx.root)


def test_missing_table_field_token_and_channel_are_named(tables_root):
    fx = tables_root
    (fx.root / fx.version / "instance.json").unlink()
    with pytest.raises(DatasetError, match="table 'instance' is missing"):
        build_index(fx.root)

    fx = write_fixture(fx.root.parent / "b", write_images=False)
    _edit_table(fx, "sample_data", lambda rs: [{k: v for k, v in r.items() if k != "ego_pose_token"}
                                               if r["filename"].startswith("samples/LIDAR") else r for r in rs])
    with pytest.raises(DatasetError, match="table 'sample_data': record .* lacks field 'ego_pose_token'"):
        build_index(fx.root)

    fx = write_fixture(fx.root.parent / "c", write_images=False)
    _edit_table(fx, "ego_pose", lambda rs: rs[1:])
    with pytest.raises(DatasetError, match="refers to ego_pose token .* which table 'ego_pose' lacks"):
        build_index(fx.root)

    fx = write_fixture(fx.root.parent / "d", write_images=False)
    victim = fx.sample_tokens["scene-b"][1]
    _edit_table(fx, "sample_data", lambda rs: [r for r in rs if not (r["sample_token"] == victim
                                                                     and "CAM_BACK_LEFT" in r["filename"])])
    with pytest.raises(DatasetError, match=f"sample {victim} \\(scene scene-b\\) has no keyframe .* CAM_BACK_LEFT"):
        build_index(fx.root)

    with pytest.raises(DatasetError, match="version directory not found .table directories in .*: v1.0-fixture"):
        build_index(fx.root, "v1.0-trainval")


def test_missing_files_are_reported(tables_root):
    fx = tables_root
    with pytest.raises(DatasetError, match=r"(?s)42 file\(s\) .* missing.*samples/CAM_"):
        build_index(fx.root, verify_files=True)  # the images were not written
    index = build_index(fx.root)  # without verification the tables alone suffice
    assert len(index.missing_files(fx.root)) == 42
    # an existing gts/<scene> directory demands every keyframe's labels
    (fx.root / "gts" / "scene-b").mkdir(parents=True)
    with pytest.raises(DatasetError, match="Occ3D labels missing for sample"):
        build_index(fx.root)


def test_save_load_round_trip_and_stale_index(tables_root):
    fx = tables_root
    with pytest.raises(DatasetError, match="no sample index .* run `occflownet prepare"):
        load_index(fx.root, fx.version)
    index = build_index(fx.root)
    save_index(index, fx.root)
    loaded = load_index(fx.root)  # version found automatically
    assert loaded.tokens == index.tokens and loaded.splits == index.splits
    for key, value in index.arrays.items():      # exact: written and read back (copies)
        np.testing.assert_array_equal(loaded.arrays[key], value, err_msg=key)
    a, b = index[4], loaded[4]
    assert a.token == b.token and a.cameras[2].path == b.cameras[2].path
    np.testing.assert_array_equal(a.boxes.translations, b.boxes.translations)
    meta = json.loads((index_dir(fx.root, fx.version) / "index.json").read_text())
    assert meta["format_version"] == FORMAT_VERSION and meta["num_samples"] == 7 and "package_version" in meta
    # a regenerated root (tables changed, added or removed) is detected
    seg = fx.root / fx.version / "lidarseg.json"
    seg_text = seg.read_text()
    seg.unlink()
    with pytest.raises(DatasetError, match="lidarseg.json changed since the index was written"):
        load_index(fx.root, fx.version)
    seg.write_text(seg_text)
    assert len(load_index(fx.root, fx.version)) == 7
    _edit_table(fx, "category", lambda rs: rs + [{"token": "x", "name": "new", "description": "", "index": 9}])
    with pytest.raises(DatasetError, match="category.json changed since the index was written"):
        load_index(fx.root, fx.version)
    meta["format_version"] = 999
    (index_dir(fx.root, fx.version) / "index.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="index format 999"):
        load_index(fx.root, fx.version, check_tables=False)


def test_index_positions_and_errors(fixture_world):
    index = build_index(fixture_world.root)
    token = fixture_world.sample_tokens["scene-b"][0]
    assert index.position_of(token) == 5 and index[-1].position == 6
    with pytest.raises(KeyError, match="not in the index"):
        index.position_of("nope")
    with pytest.raises(IndexError):
        index[7]


def test_copy_of_root_builds_identically(fixture_world, tmp_path):
    """Index content is a pure function of the tables (prepare is idempotent)."""
    shutil.copytree(fixture_world.root / VERSION, tmp_path / VERSION)
    a, b = build_index(fixture_world.root), build_index(tmp_path)
    for key in a.arrays:
        if key != "occupancy_path":  # the copy has no gts/
            np.testing.assert_array_equal(a.arrays[key], b.arrays[key], err_msg=key)
