"""The synthetic dataset's nuScenes layout: tables, token references, files, chains, calibration, labels."""
import json

import cv2
import numpy as np

from occflownet.occ3d import CAMERAS, FREE, LIDAR, LIDARSEG_NAMES
from occflownet.geometry import quaternion_to_matrix
from occflownet.rig import default_rig
from occflownet.synth.generate import DEFAULT_SWEEPS

TABLES = ("category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose", "log",
          "scene", "sample", "sample_data", "sample_annotation", "map")


def load(root, version):
    return {name: json.loads((root / version / f"{name}.json").read_text()) for name in (*TABLES, "lidarseg")}


def test_all_tables_and_splits_exist(synth_root, synth_params):
    root, version = synth_root
    t = load(root, version)
    assert all(isinstance(t[name], list) and t[name] for name in TABLES)
    splits = json.loads((root / version / "splits.json").read_text())
    assert splits == {"train": ["scene-0001"], "val": ["scene-0001"]}
    assert len(t["sample"]) == synth_params["frames"]
    frames = synth_params["frames"]
    sweeps = [sd for sd in t["sample_data"] if not sd["is_key_frame"]]
    assert len(t["sample_data"]) == 7 * frames + DEFAULT_SWEEPS * (frames - 1)
    assert len(sweeps) == DEFAULT_SWEEPS * (frames - 1) and all(sd["filename"].startswith("sweeps/LIDAR_TOP/")
                                                                 for sd in sweeps)
    assert len(t["ego_pose"]) == len(t["sample_data"])
    for table in TABLES:
        tokens = [r["token"] for r in t[table]]
        assert len(tokens) == len(set(tokens)), f"duplicate tokens in {table}"


def test_every_token_reference_resolves(synth_root):
    root, version = synth_root
    t = load(root, version)
    ids = {name: {r["token"]: r for r in t[name]} for name in t}
    refs = {"instance": {"category_token": "category", "first_annotation_token": "sample_annotation",
                         "last_annotation_token": "sample_annotation"},
            "calibrated_sensor": {"sensor_token": "sensor"},
            "scene": {"log_token": "log", "first_sample_token": "sample", "last_sample_token": "sample"},
            "sample": {"scene_token": "scene", "prev": "sample", "next": "sample"},
            "sample_data": {"sample_token": "sample", "ego_pose_token": "ego_pose",
                            "calibrated_sensor_token": "calibrated_sensor", "prev": "sample_data",
                            "next": "sample_data"},
            "sample_annotation": {"sample_token": "sample", "instance_token": "instance",
                                  "visibility_token": "visibility", "prev": "sample_annotation",
                                  "next": "sample_annotation"},
            "lidarseg": {"sample_data_token": "sample_data"}}
    for table, fields in refs.items():
        for r in t[table]:
            for field, target in fields.items():
                if field in ("prev", "next") and r[field] == "":
                    continue
                assert r[field] in ids[target], f"{table}.{field} {r[field]} does not resolve"
    for ann in t["sample_annotation"]:
        assert all(a in ids["attribute"] for a in ann["attribute_tokens"])
    logs = {lg for m in t["map"] for lg in m["log_tokens"]}
    assert logs == set(ids["log"])
    for m in t["map"]:
        assert (root / m["filename"]).is_file()
    assert sorted(c["index"] for c in t["category"]) == list(range(len(LIDARSEG_NAMES)))
    assert {c["name"] for c in t["category"]} == set(LIDARSEG_NAMES)


def chain(records, first):
    out, tok = [], first
    while tok:
        out.append(records[tok])
        tok = records[tok]["next"]
    return out


def test_prev_next_chains_and_counts(synth_root):
    root, version = synth_root
    t = load(root, version)
    samples = {r["token"]: r for r in t["sample"]}
    for scene in t["scene"]:
        seq = chain(samples, scene["first_sample_token"])
        assert len(seq) == scene["nbr_samples"] and seq[-1]["token"] == scene["last_sample_token"]
        assert all(a["next"] == b["token"] and b["prev"] == a["token"] for a, b in zip(seq, seq[1:]))
        assert np.all(np.diff([s["timestamp"] for s in seq]) == 500_000)  # 2 Hz keyframes
    sds = {r["token"]: r for r in t["sample_data"]}
    cs = {r["token"]: r for r in t["calibrated_sensor"]}
    sensors = {r["token"]: r["channel"] for r in t["sensor"]}
    by_channel = {}
    for sd in t["sample_data"]:
        by_channel.setdefault(sensors[cs[sd["calibrated_sensor_token"]]["sensor_token"]], []).append(sd)
    assert set(by_channel) == {*CAMERAS, LIDAR}
    for ch, recs in by_channel.items():
        firsts = [r for r in recs if r["prev"] == ""]
        assert len(firsts) == len(t["scene"])
        seq = chain(sds, firsts[0]["token"])
        assert len(seq) == len(recs) and np.all(np.diff([r["timestamp"] for r in seq]) > 0)
        keyframes = [r for r in seq if r["is_key_frame"]]
        in_order = chain(samples, t["scene"][0]["first_sample_token"])
        assert [r["sample_token"] for r in keyframes] == [s["token"] for s in in_order]
        for r in seq:                                       # a sweep belongs to the keyframe nearest in time
            gap = abs(samples[r["sample_token"]]["timestamp"] - r["timestamp"])
            assert gap == min(abs(smp["timestamp"] - r["timestamp"]) for smp in samples.values())
    anns = {r["token"]: r for r in t["sample_annotation"]}
    for inst in t["instance"]:
        seq = chain(anns, inst["first_annotation_token"])
        assert len(seq) == inst["nbr_annotations"] and seq[-1]["token"] == inst["last_annotation_token"]
        assert all(a["instance_token"] == inst["token"] for a in seq)
        assert np.all(np.diff([samples[a["sample_token"]]["timestamp"] for a in seq]) > 0)


def test_sensor_files_poses_and_calibration(synth_root, synth_params):
    root, version = synth_root
    t = load(root, version)
    W, H = synth_params["width"], synth_params["height"]
    rig = default_rig(W, H)
    cs = {r["token"]: r for r in t["calibrated_sensor"]}
    sensors = {r["token"]: r["channel"] for r in t["sensor"]}
    poses = {r["token"]: r for r in t["ego_pose"]}
    seg = {r["sample_data_token"]: r for r in t["lidarseg"]}
    lidar_sds = 0
    for sd in t["sample_data"]:
        calib = cs[sd["calibrated_sensor_token"]]
        ch = sensors[calib["sensor_token"]]
        folder = "samples" if sd["is_key_frame"] else "sweeps"
        assert sd["filename"].startswith(f"{folder}/{ch}/") and (root / sd["filename"]).is_file()
        assert poses[sd["ego_pose_token"]]["timestamp"] == sd["timestamp"]
        if ch == LIDAR and not sd["is_key_frame"]:
            assert sd["token"] not in seg                 # sweeps have no lidarseg, as in nuScenes
            assert np.fromfile(root / sd["filename"], dtype=np.float32).size % 5 == 0
        elif ch == LIDAR:
            lidar_sds += 1
            assert sd["filename"].endswith(".pcd.bin") and sd["fileformat"] == "pcd"
            pts = np.fromfile(root / sd["filename"], dtype=np.float32).reshape(-1, 5)
            labels = np.fromfile(root / seg[sd["token"]]["filename"], dtype=np.uint8)
            assert seg[sd["token"]]["filename"] == f"lidarseg/{version}/{sd['token']}_lidarseg.bin"
            assert len(labels) == len(pts) > 10_000
            assert labels.max() < len(LIDARSEG_NAMES)
            assert set(np.unique(pts[:, 4]).astype(int)) <= set(range(32))
            R = quaternion_to_matrix(calib["rotation"])
            assert np.allclose(R @ [1, 0, 0], [0, -1, 0], atol=1e-6)  # rotated like nuScenes: not identity
            assert np.allclose(calib["translation"], [0.94, 0.0, 1.84])
        else:
            img = cv2.imread(str(root / sd["filename"]))
            assert img.shape == (H, W, 3) and (sd["width"], sd["height"]) == (W, H)
            assert np.allclose(calib["camera_intrinsic"], rig["cameras"][ch]["intrinsic"])
            cam2ego = np.eye(4)
            cam2ego[:3, :3] = quaternion_to_matrix(calib["rotation"])
            cam2ego[:3, 3] = calib["translation"]
            assert np.allclose(cam2ego, rig["cameras"][ch]["cam2ego"], atol=1e-9)
    assert lidar_sds == len(t["lidarseg"]) == len(list((root / "lidarseg" / version).glob("*_lidarseg.bin")))
    # the ego moves: the poses of one sample's sensors differ (cameras fire at their own times)
    sample0 = t["sample"][0]["token"]
    trans = [poses[sd["ego_pose_token"]]["translation"] for sd in t["sample_data"] if sd["sample_token"] == sample0]
    assert len({tuple(np.round(p, 4)) for p in trans}) > 1


def test_annotations_are_global_boxes_with_sizes(synth_root):
    root, version = synth_root
    t = load(root, version)
    cats = {c["token"]: c["name"] for c in t["category"]}
    inst_cat = {i["token"]: cats[i["category_token"]] for i in t["instance"]}
    names = set(inst_cat.values())
    assert {"vehicle.car", "human.pedestrian.adult"} <= names
    for a in t["sample_annotation"]:
        w, l, h = a["size"]
        assert 0.1 < w < 4 and 0.2 < l < 15 and 0.3 < h < 5
        assert np.isclose(np.linalg.norm(a["rotation"]), 1.0)
        assert abs(a["translation"][2] - h / 2) < 1e-6  # boxes stand on the ground (z = 0)
        assert a["num_lidar_pts"] >= 0 and a["visibility_token"] in {"1", "2", "3", "4"}
    moving = [a for a in t["sample_annotation"] if a["next"]]
    shifts = [np.linalg.norm(np.subtract(next(b for b in t["sample_annotation"] if b["token"] == a["next"])
                                         ["translation"], a["translation"])) for a in moving[:200]]
    assert max(shifts) > 1.0 and min(shifts) < 1e-6  # some agents move, some are parked


def test_occ3d_labels_and_the_geometric_truth(synth_root, synth_params):
    """gts/ holds the label pipeline's files (and its settings); truth/ the geometry voxelised, never the benchmark."""
    root, version = synth_root
    t = load(root, version)
    scene = t["scene"][0]["name"]
    assert json.loads((root / "gts" / "labels.json").read_text())["format"] == 1
    for s in t["sample"]:
        with np.load(root / "gts" / scene / s["token"] / "labels.npz") as z:
            assert set(z.files) == {"semantics", "mask_lidar", "mask_camera"}
            for k in z.files:
                assert z[k].dtype == np.uint8 and z[k].shape == (200, 200, 16)
            assert z["semantics"].max() == 17 and set(np.unique(z["mask_camera"])) == {0, 1}
            assert 0.01 < z["mask_camera"].mean() <= z["mask_lidar"].mean() < 0.6
            assert not (z["mask_camera"] & ~z["mask_lidar"]).any()
            occupied = z["semantics"] != FREE
        with np.load(root / "truth" / scene / s["token"] / "semantics.npz") as z:
            truth = z["semantics"] != FREE
        assert truth.sum() > 2 * occupied.sum() and (truth[occupied]).mean() > 0.97   # LiDAR sees part of it
