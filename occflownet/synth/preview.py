"""Preview picture of one keyframe: the six images (FRONT_LEFT FRONT FRONT_RIGHT / BACK_LEFT BACK BACK_RIGHT) with
the LiDAR points projected and coloured by class, and a top-down view of the ground truth (highest occupied voxel's
class colour, :func:`occflownet.pictures.top_down`; voxels outside mask_camera dimmed), plus a class legend.
"""
from __future__ import annotations

import numpy as np

from occflownet import pictures
from occflownet.occ3d import CAMERAS, CLASS_COLORS, NUM_CLASSES, map_lidarseg
from occflownet.geometry import invert, transform_points

LAYOUT = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"))


def project_lidar(kf, rig, camera: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LiDAR points of keyframe ``kf`` in camera ``camera``: (u [M], v [M], z-depth [M]) for points in front
    of the camera and inside the image, plus their indices into the scan. Goes LiDAR → ego (LiDAR time) → global
    → ego (camera time) → camera, like nuScenes."""
    pts = kf.scan.points[:, :3].astype(np.float64)
    T = invert(kf.camera_ego2global[camera] @ rig.cam2ego[camera]) @ kf.lidar_ego2global @ rig.lidar2ego
    pc = transform_points(T, pts)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pc @ rig.intrinsics[camera].T
        u, v = uv[:, 0] / z, uv[:, 1] / z
    ok = (z > 0.05) & (u >= 0) & (u < rig.width) & (v >= 0) & (v < rig.height)
    idx = np.nonzero(ok)[0]
    return u[idx], v[idx], idx


def preview_image(kf, rig) -> np.ndarray:
    """RGB uint8 preview of keyframe ``kf`` (a ``frame.Keyframe``) rendered with ``rig`` (a ``frame.SensorRig``)."""
    import cv2

    W, H = rig.width, rig.height
    raw_cls = map_lidarseg(kf.scan.raw)
    tiles = {}
    for c, name in enumerate(CAMERAS):
        img = kf.cameras[c].rgb.copy()
        u, v, idx = project_lidar(kf, rig, c)
        iu, iv = u.astype(np.int64), v.astype(np.int64)
        col = CLASS_COLORS[raw_cls[idx]]
        for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
            img[np.minimum(iv + dv, H - 1), np.minimum(iu + du, W - 1)] = col
        cv2.putText(img, name, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles[name] = img
    cams = np.concatenate([np.concatenate([tiles[n] for n in row], axis=1) for row in LAYOUT], axis=0)
    top = pictures.top_down(kf.semantics, scale=1, mask=kf.mask_camera, empty=(20, 20, 20), ego=(255, 255, 255))
    side = 2 * H
    top = cv2.resize(top, (side, side), interpolation=cv2.INTER_NEAREST)
    legend = pictures.class_legend(3 * W + side, count=NUM_CLASSES, columns=9, background=30)
    canvas = np.full((2 * H + legend.shape[0], 3 * W + side, 3), 30, np.uint8)
    canvas[:2 * H, :3 * W] = cams
    canvas[:2 * H, 3 * W:] = top
    canvas[2 * H:] = legend
    return canvas
