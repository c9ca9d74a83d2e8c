"""Run inside a separate venv with nuscenes-devkit==1.2.0 (see test_synth_devkit.py): load a synthetic root with the
official devkit and exercise the lookups a nuScenes user relies on. Prints one JSON line with counts.

usage: python synth_devkit_check.py ROOT VERSION
"""
import json
import os
import sys

import numpy as np
from nuscenes.nuscenes import NuScenes
from nuscenes.utils.data_classes import LidarPointCloud
from nuscenes.utils.geometry_utils import points_in_box

root, version = sys.argv[1], sys.argv[2]
nusc = NuScenes(version=version, dataroot=root, verbose=False)
assert hasattr(nusc, "lidarseg") and len(nusc.lidarseg) == len(nusc.sample), "lidarseg not loaded"
out = {"samples": 0, "sample_data": 0, "boxes": 0, "points": 0, "box_points_ok": 0, "box_points_checked": 0,
       "projected": 0, "classes": []}
names = set()
for sample in nusc.sample:
    out["samples"] += 1
    assert set(sample["data"]) == {"CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT",
                                   "CAM_BACK_RIGHT", "LIDAR_TOP"}, sample["data"].keys()
    for channel, sd_token in sample["data"].items():
        path, boxes, intrinsic = nusc.get_sample_data(sd_token)
        assert os.path.isfile(path), path
        out["sample_data"] += 1
        if channel.startswith("CAM"):
            assert intrinsic is not None and np.asarray(intrinsic).shape == (3, 3)
    lidar_token = sample["data"]["LIDAR_TOP"]
    seg = nusc.get("lidarseg", lidar_token)
    labels = np.fromfile(os.path.join(root, seg["filename"]), dtype=np.uint8)
    path, boxes, _ = nusc.get_sample_data(lidar_token)  # boxes in the LiDAR frame
    pc = LidarPointCloud.from_file(path)
    assert pc.points.shape[1] == len(labels), "one lidarseg byte per point"
    out["points"] += len(labels)
    names |= {nusc.lidarseg_idx2name_mapping[int(i)] for i in np.unique(labels)}
    for box in boxes:
        ann = nusc.get("sample_annotation", box.token)
        inside = int(points_in_box(box, pc.points[:3], wlh_factor=1.02).sum())
        out["boxes"] += 1
        if ann["num_lidar_pts"] >= 5:
            out["box_points_checked"] += 1
            out["box_points_ok"] += int(inside >= ann["num_lidar_pts"])
    pts, coloring, _ = nusc.explorer.map_pointcloud_to_image(lidar_token, sample["data"]["CAM_FRONT"])
    out["projected"] += int(pts.shape[1])
out["classes"] = sorted(names)
print(json.dumps(out))
