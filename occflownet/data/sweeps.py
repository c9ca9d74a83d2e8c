"""Every LiDAR sweep of a scene, keyframes and the sweeps between them (nuScenes ``sample_data`` with
``is_key_frame`` false), in time order: what the label pipeline accumulates.

nuScenes records a 20 Hz LiDAR and annotates every tenth sweep (the keyframe, 2 Hz); the other sweeps live under
``sweeps/LIDAR_TOP/`` and point (``sample_token``) to the keyframe nearest in time, which decides their scene here.
They have no lidarseg labels (nuScenes-lidarseg labels keyframes only); a lidarseg record for a sweep is used when a
root has one. The sample index (``builder``) holds keyframes only.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occflownet.occ3d import LIDAR
from occflownet.data.builder import channel_of_calibration, pose_matrix
from occflownet.data.index import SampleIndex
from occflownet.data.tables import Tables, field


@dataclass(frozen=True)
class LidarSweep:
    """One LiDAR sweep (keyframe or not). Poses float64 [4, 4]: LiDAR → ego, ego → global at the sweep's time."""

    token: str                  # sample_data token
    path: str                   # .pcd.bin relative to the dataroot (LiDAR frame, 5 float32 per point)
    timestamp: int              # µs
    sensor2ego: np.ndarray
    ego2global: np.ndarray
    keyframe: int | None        # position in the SampleIndex when this is a keyframe's sweep, else None
    lidarseg_path: str | None   # raw lidarseg labels, when the root labels this sweep

    @property
    def sensor2global(self) -> np.ndarray:
        return self.ego2global @ self.sensor2ego


def scene_sweeps(tables: Tables, index: SampleIndex, channel: str = LIDAR) -> dict[str, list[LidarSweep]]:
    """{scene name: its sweeps of ``channel`` in time order} for every scene of ``index`` (built from ``tables``).
    A scene's sweeps are the sample_data of the channel whose sample belongs to the scene; keyframe sweeps carry
    the position of their sample in the index."""
    channel_of_calib = channel_of_calibration(tables)
    scene_of_sample = {t: index.scene_names[int(s)] for t, s in zip(index.tokens, index.arrays["sample_scene"])}
    position_of = {t.decode(): p for p, t in enumerate(index.arrays["lidar_token"])}
    labelled = {}
    if tables.has("lidarseg"):
        labelled = {field(r, "lidarseg", "sample_data_token"): field(r, "lidarseg", "filename")
                    for r in tables.records["lidarseg"]}
    out: dict[str, list[LidarSweep]] = {name: [] for name in index.scene_names}
    for r in tables.records["sample_data"]:
        calib_token = field(r, "sample_data", "calibrated_sensor_token")
        if channel_of_calib.get(calib_token) != channel:
            continue
        scene = scene_of_sample.get(field(r, "sample_data", "sample_token"))
        if scene is None:
            continue                                  # a sample the index does not hold (cannot happen on a valid root)
        where = f"sample_data {r.get('token')} ({channel})"
        calib = tables.get("calibrated_sensor", calib_token, where)
        ego = tables.get("ego_pose", field(r, "sample_data", "ego_pose_token"), where)
        token = field(r, "sample_data", "token")
        out[scene].append(LidarSweep(
            token=token, path=field(r, "sample_data", "filename"), timestamp=int(field(r, "sample_data", "timestamp")),
            sensor2ego=pose_matrix(calib, "calibrated_sensor"), ego2global=pose_matrix(ego, "ego_pose"),
            keyframe=position_of.get(token), lidarseg_path=labelled.get(token)))
    for sweeps in out.values():
        sweeps.sort(key=lambda s: s.timestamp)
    return out
