"""Preview picture of one keyframe: the six images (FRONT_LEFT FRONT FRONT_RIGHT / BACK_LEFT BACK BACK_RIGHT) with
the LiDAR points projected and coloured by class, and a top-down view of the ground truth (highest occupied voxel's
class colour; voxels outside mask_camera dimmed), plus a class legend.
"""
from __future__ import annotations

import numpy as np

from occflownet.config import CAMERAS, CLASS_COLORS, CLASS_NAMES, FREE, NUM_CLASSES, map_lidarseg
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


def topdown(semantics: np.ndarray, mask_camera: np.ndarray | None = None, scale: int = 2) -> np.ndarray:
    """RGB uint8 [X*scale, Y*scale, 3] top-down view: x (forward) up, y (left) to the left."""
    occ = semantics != FREE
    k = np.where(occ.any(axis=2), semantics.shape[2] - 1 - np.argmax(occ[:, :, ::-1], axis=2), 0)
    top = np.take_along_axis(semantics, k[..., None], axis=2)[..., 0]
    img = np.where(occ.any(axis=2)[..., None], CLASS_COLORS[top], 20).astype(np.float32)
    if mask_camera is not None:
        seen = np.take_along_axis(mask_camera, k[..., None], axis=2)[..., 0] > 0
        img[~seen] *= 0.4
    img = img[::-1, ::-1]  # row 0 = largest x (ahead), column 0 = largest y (left)
    img = np.repeat(np.repeat(img, scale, 0), scale, 1).astype(np.uint8)
    c = img.shape[0] // 2
    img[c - 3:c + 3, c - 2:c + 2] = 255  # the ego
    return img


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
    top = topdown(kf.semantics, kf.mask_camera, scale=1)
    side = 2 * H
    top = cv2.resize(top, (side, side), interpolation=cv2.INTER_NEAREST)
    canvas = np.full((2 * H + 44, 3 * W + side, 3), 30, np.uint8)
    canvas[:2 * H, :3 * W] = cams
    canvas[:2 * H, 3 * W:] = top
    x = 5
    for c in range(NUM_CLASSES):
        label = CLASS_NAMES[c].replace("_", " ").replace("construction vehicle", "constr. veh.")
        y = 2 * H + (14 if c < 9 else 34)
        if c == 9:
            x = 5
        cv2.rectangle(canvas, (x, y - 9), (x + 10, y + 1), tuple(int(v) for v in CLASS_COLORS[c]), -1)
        cv2.putText(canvas, label, (x + 14, y), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (230, 230, 230), 1, cv2.LINE_AA)
        x += 20 + 8 * len(label)
    return canvas
