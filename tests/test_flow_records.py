"""Flow precompute: box transforms in the current ego frame, filtering, compact records, save/load, moves."""
import numpy as np
import pytest
import torch

from occflownet.occ3d import GRID, NUM_CLASSES
from occflownet.data.flow import (FLOW_FORMAT_VERSION, FlowRecord, box_flows, boxes_from_annotations, flow_moves,
                                  load_flow_records, save_flow_records)
from occflownet.geometry import (make_transform, matrix_to_quaternion, quaternion_to_matrix, transform_points,
                                 yaw_to_quaternion)
from occflownet.data.box_voxels import voxels_in_box
from occflownet.render.occupancy_flow import PackedMoves, warp_volumes

CAR, BARRIER, PED = 4, 1, 7
# current ego: at global (100, 50, 0), yawed +90° (ego x points along global +y, ego y along global -x)
EGO = make_transform(yaw_to_quaternion(np.pi / 2), [100.0, 50.0, 0.0])


def _boxes(rows):
    """rows: (token, label, ego-frame centre, size wlh, yaw in the ego frame) → global box arrays."""
    out = {"instance_token": [], "label": [], "center": [], "size_wlh": [], "rotation": []}
    for token, label, centre, size, yaw in rows:
        pose = EGO @ make_transform(yaw_to_quaternion(yaw), centre)
        out["instance_token"].append(token)
        out["label"].append(label)
        out["center"].append(pose[:3, 3])
        out["size_wlh"].append(size)
        out["rotation"].append(matrix_to_quaternion(pose[:3, :3]))
    return {k: np.asarray(v) for k, v in out.items()}


def _moved_globally(boxes, token, dx_global):
    moved = {k: v.copy() for k, v in boxes.items()}
    row = list(moved["instance_token"]).index(token)
    moved["center"][row, 0] += dx_global
    return moved


def test_global_x_move_with_ego_yawed_90_is_a_move_along_ego_minus_y():
    now = _boxes([("car-a", CAR, [10.0, 0.0, 1.0], [1.9, 4.5, 1.6], 0.0)])
    then = _moved_globally(now, "car-a", 2.0)
    rec = box_flows("s0", now, {1: then}, EGO)
    assert rec.offset.tolist() == [1] and rec.move_box.tolist() == [0] and rec.label.tolist() == [CAR]
    T = rec.transform[0].astype(np.float64)
    assert np.allclose(T[:3, :3], np.eye(3), atol=1e-6)
    # global +x = −(ego y) for an ego yawed +90°: the car moves 2 m to the ego's right
    assert np.allclose(T[:3, 3], [0.0, -2.0, 0.0], atol=1e-5)
    assert np.allclose(rec.center[0], [10.0, 0.0, 1.0], atol=1e-5)
    assert np.allclose(rec.size_wlh[0], [1.9, 4.5, 1.6])
    assert np.allclose(quaternion_to_matrix(rec.rotation[0]), np.eye(3), atol=1e-6)


def test_transform_maps_the_box_at_0_onto_the_box_at_t():
    now = _boxes([("ped", PED, [-5.0, 8.0, 0.5], [0.7, 0.8, 1.8], 0.4)])
    then = _boxes([("ped", PED, [-3.5, 9.0, 0.6], [0.7, 0.8, 1.8], 1.3)])
    rec = box_flows("s1", now, {-2: then}, EGO)
    T = rec.transform[0].astype(np.float64)
    corners = np.array([[x, y, z] for x in (-0.4, 0.4) for y in (-0.35, 0.35) for z in (-0.9, 0.9)])
    at0 = transform_points(make_transform(yaw_to_quaternion(0.4), [-5.0, 8.0, 0.5]), corners)
    att = transform_points(make_transform(yaw_to_quaternion(1.3), [-3.5, 9.0, 0.6]), corners)
    assert np.allclose(transform_points(T, at0), att, atol=1e-4)
    assert rec.offset.tolist() == [-2]


def test_static_classes_out_of_range_and_unmatched_boxes_are_skipped():
    now = _boxes([("car-a", CAR, [10.0, 0.0, 1.0], [1.9, 4.5, 1.6], 0.0),
                  ("barrier", BARRIER, [12.0, 3.0, 0.5], [0.5, 2.0, 1.0], 0.0),
                  ("others", 0, [12.0, -3.0, 0.5], [0.5, 2.0, 1.0], 0.0),
                  ("far-car", CAR, [45.0, 0.0, 1.0], [1.9, 4.5, 1.6], 0.0),
                  ("lonely-car", CAR, [-10.0, 5.0, 1.0], [1.9, 4.5, 1.6], 0.0),
                  ("ped", PED, [3.0, 3.0, 0.8], [0.7, 0.8, 1.8], 0.0)])
    t1 = {k: v[[0, 1, 2, 3]] for k, v in now.items()}  # lonely-car and ped absent at t = 1
    t2 = {k: v[[5, 1, 3]] for k, v in now.items()}  # only ped (dynamic, in range) matches at t = 2
    t3 = {k: v[[1, 2]] for k, v in now.items()}  # nothing dynamic at t = 3
    rec = box_flows("s2", now, {1: t1, 2: t2, 3: t3}, EGO)
    assert rec.box_index.tolist() == [0, 5]  # car-a and ped; lonely-car has no match anywhere
    assert list(zip(rec.offset.tolist(), rec.move_box.tolist())) == [(1, 0), (2, 1)]
    assert rec.offsets == [1, 2]
    assert np.allclose(rec.transform, np.eye(4), atol=1e-5)  # nothing moved


def test_empty_and_bad_inputs():
    empty = {"instance_token": [], "label": [], "center": np.zeros((0, 3)), "size_wlh": np.zeros((0, 3)),
             "rotation": np.zeros((0, 4))}
    assert len(box_flows("e", empty, {1: empty}, EGO).offset) == 0
    now = _boxes([("car-a", CAR, [10.0, 0.0, 1.0], [1.9, 4.5, 1.6], 0.0)])
    with pytest.raises(ValueError, match="size_wlh"):
        box_flows("b", {k: v for k, v in now.items() if k != "size_wlh"}, {}, EGO)
    with pytest.raises(ValueError, match="t = 0"):
        box_flows("b", now, {0: now}, EGO)
    with pytest.raises(ValueError, match="ego2global_now"):
        box_flows("b", now, {}, np.eye(3))
    dup = {k: np.concatenate([v, v]) for k, v in now.items()}
    with pytest.raises(ValueError, match="unique"):
        box_flows("b", dup, {}, EGO)


def test_boxes_from_annotations():
    anns = [{"instance_token": "i1", "translation": [1, 2, 3], "size": [1.9, 4.5, 1.6], "rotation": [1, 0, 0, 0],
             "category_name": "vehicle.car"},
            {"instance_token": "i2", "translation": [4, 5, 6], "size": [0.7, 0.8, 1.8], "rotation": [1, 0, 0, 0],
             "label": PED}]
    boxes = boxes_from_annotations(anns)
    assert boxes["label"].tolist() == [CAR, PED] and boxes["center"].shape == (2, 3)
    with pytest.raises(ValueError, match="annotation 0"):
        boxes_from_annotations([{"instance_token": "x"}])


def _record():
    now = _boxes([("car-a", CAR, [10.0, 0.0, 1.0], [1.9, 4.5, 1.6], 0.3),
                  ("ped", PED, [3.0, 3.0, 0.8], [0.7, 0.8, 1.8], 0.0)])
    return box_flows("tok", now, {-1: _moved_globally(now, "car-a", -2.0), 1: _moved_globally(now, "car-a", 2.0),
                                  2: _moved_globally(now, "ped", 1.0)}, EGO)


def test_save_load_round_trip_and_version(tmp_path):
    rec = _record()
    path = tmp_path / "one.flow"
    save_flow_records(path, [rec])
    assert path.exists()  # written under the exact name given
    back, = load_flow_records(path).values()
    assert back.sample_token == "tok" and back.version == FLOW_FORMAT_VERSION
    for key, value in rec.arrays().items():      # exact: written and read back
        assert np.array_equal(getattr(back, key), value) and getattr(back, key).dtype == value.dtype
    other = FlowRecord("empty")
    save_flow_records(tmp_path / "all.npz", [rec, other])
    many = load_flow_records(tmp_path / "all.npz")
    assert set(many) == {"tok", "empty"} and len(many["empty"].offset) == 0
    assert np.array_equal(many["tok"].transform, rec.transform)
    # a record of a few boxes takes a few hundred bytes, not the official ~260 KB
    assert path.stat().st_size < 4000
    # version mismatch and foreign files are named errors
    data = dict(np.load(path))
    data["version"] = np.int32(FLOW_FORMAT_VERSION + 1)
    np.savez(tmp_path / "future.npz", **data)
    with pytest.raises(ValueError, match="version"):
        load_flow_records(tmp_path / "future.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz"):
        load_flow_records(tmp_path / "junk.npz")
    with pytest.raises(ValueError, match="unique"):
        save_flow_records(tmp_path / "dup.npz", [rec, rec])


def test_flow_moves_lists_box_voxels_per_requested_frame():
    rec = _record()
    moves = flow_moves(rec, offsets=[-1, 0, 1])  # t = 2 not requested
    car = voxels_in_box(rec.center[0], rec.size_wlh[0], rec.rotation[0])
    ped = voxels_in_box(rec.center[1], rec.size_wlh[1], rec.rotation[1])
    # both boxes are annotated at t = -1 and t = 1 (the pedestrian standing still)
    assert moves["volume"].tolist() == [0, 0, 2, 2] and moves["classes"].tolist() == [CAR, PED, CAR, PED]
    assert np.array_equal(moves["voxels"], np.concatenate([car, ped, car, ped]))
    assert np.array_equal(moves["box"], np.repeat([0, 1, 2, 3], [len(car), len(ped), len(car), len(ped)]))
    assert np.allclose(moves["transforms"][[1, 3]], np.eye(4), atol=1e-5)
    assert np.allclose(moves["transforms"][2][:3, 3], [0.0, -2.0, 0.0], atol=1e-5)
    assert moves["transforms"].shape == (4, 4, 4)
    empty = flow_moves(rec, offsets=[3])
    assert empty["voxels"].shape == (0, 3) and empty["transforms"].shape == (0, 4, 4)


def test_record_drives_the_warp_to_the_box_at_t():
    """box_flows → flow_moves → warp_volumes: a car filling its box at 0 lands in its box at t (nearest)."""
    now = _boxes([("car-a", CAR, [10.2, 0.2, 1.2], [2.0, 4.0, 1.6], 0.0)])
    then = _moved_globally(now, "car-a", 2.0)  # ego frame: 2 m towards -y = 5 cells
    rec = box_flows("s", now, {1: then}, EGO)
    body = voxels_in_box([10.2, 0.2, 1.2], [2.0, 4.0, 1.6], 0.0, margin_scale=1.0, margin_add=0.0)
    density = torch.zeros(1, *GRID.shape)
    logits = torch.zeros(1, *GRID.shape, NUM_CLASSES)
    density[0][tuple(torch.as_tensor(body).T)] = 0.9
    logits[0][tuple(torch.as_tensor(body).T) + (CAR,)] = 3.0
    moves = PackedMoves.from_arrays(**flow_moves(rec, offsets=[0, 1]))
    out_d, _ = warp_volumes(density, logits, torch.tensor([0, 0]), moves, mover="nearest")
    assert torch.equal(out_d[0], density[0])                         # exact: nothing moves, a copy
    occupied = {tuple(v) for v in torch.nonzero(out_d[1] > 0.5).tolist()}
    body_t = voxels_in_box([10.2, -1.8, 1.2], [2.0, 4.0, 1.6], 0.0, margin_scale=1.0, margin_add=0.0)
    assert occupied == {tuple(v) for v in body_t.tolist()}


def test_precompute_flow_in_started_workers_writes_what_the_serial_loop_writes(prepared_synth_root, tmp_path,
                                                                               monkeypatch):
    import shutil

    from occflownet.data import flow
    from occflownet.data.index import load_index

    root, version = prepared_synth_root
    index = load_index(root, version)
    copies = {}
    for name, parallel_from in (("serial", 10 ** 9), ("workers", 0)):
        monkeypatch.setattr(flow, "PARALLEL_FROM", parallel_from)
        copy = tmp_path / name
        shutil.copytree(root / "occflownet", copy / "occflownet")    # flow_path lies beside the index
        copies[name] = np.load(flow.precompute_flow(index, copy, horizon=2, workers=2))
    serial, workers = copies["serial"], copies["workers"]
    assert sorted(serial.files) == sorted(workers.files) and len(serial["sample_token"]) == len(index)
    assert len(serial["offset"]) > 0                                 # moving boxes: the records are not empty
    for key in serial.files:              # exact: the same function on the same inputs, in other processes
        np.testing.assert_array_equal(serial[key], workers[key], err_msg=key)
