"""Preview picture of one keyframe, drawn from the files of a root: the six images (FRONT_LEFT FRONT FRONT_RIGHT /
BACK_LEFT BACK BACK_RIGHT) with the keyframe's LiDAR points projected and coloured by class, and a top-down view of
its Occ3D labels (highest occupied voxel's class colour, :func:`occflownet.pictures.top_down`; voxels outside
mask_camera dimmed), plus a class legend.
"""
from __future__ import annotations

import numpy as np

from occflownet import pictures
from occflownet.occ3d import CAMERAS, CLASS_COLORS, NUM_CLASSES, map_lidarseg
from occflownet.data.loaders import load_lidar, load_lidarseg, load_occupancy, load_sample_images
from occflownet.data.records import SampleRecord
from occflownet.geometry import invert, transform_points

LAYOUT = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"))


def project_points(points: np.ndarray, lidar2cam: np.ndarray, K: np.ndarray, width: int, height: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LiDAR-frame points [N, 3] seen by a camera (``lidar2cam`` [4, 4] into its OpenCV frame, intrinsics K for a
    width × height image): (u [M], v [M], indices [M] into the points) of the points in front of the camera and
    inside the image."""
    pc = transform_points(lidar2cam, points)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pc @ np.asarray(K).T
        u, v = uv[:, 0] / z, uv[:, 1] / z
    ok = (z > 0.05) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    idx = np.nonzero(ok)[0]
    return u[idx], v[idx], idx


def lidar2camera(sample: SampleRecord, camera: int) -> np.ndarray:
    """[4, 4] LiDAR → camera ``camera`` of ``sample``: LiDAR → ego (LiDAR time) → global → ego (camera time) →
    camera, like nuScenes."""
    cam = sample.cameras[camera]
    return invert(cam.ego2global @ cam.sensor2ego) @ sample.lidar.ego2global @ sample.lidar.sensor2ego


def preview_sample(dataroot, sample: SampleRecord) -> np.ndarray:
    """RGB uint8 preview of keyframe ``sample`` of the root ``dataroot`` (its images, LiDAR, lidarseg, labels)."""
    import cv2

    images = load_sample_images(dataroot, sample)
    H, W = images.shape[1:3]
    scan = load_lidar(dataroot, sample.lidar.path)
    cls = map_lidarseg(load_lidarseg(dataroot, sample.lidarseg_path, len(scan)))
    tiles = {}
    for c, name in enumerate(CAMERAS):
        img = images[c].copy()
        cam = sample.cameras[c]
        u, v, idx = project_points(scan[:, :3].astype(np.float64), lidar2camera(sample, c), cam.intrinsic, cam.width,
                                   cam.height)
        iu, iv = u.astype(np.int64), v.astype(np.int64)
        for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
            img[np.minimum(iv + dv, H - 1), np.minimum(iu + du, W - 1)] = CLASS_COLORS[cls[idx]]
        cv2.putText(img, name, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles[name] = img
    cams = np.concatenate([np.concatenate([tiles[n] for n in row], axis=1) for row in LAYOUT], axis=0)
    labels = load_occupancy(dataroot, sample.occupancy_path)
    top = pictures.top_down(labels.semantics, scale=1, mask=labels.mask_camera, empty=(20, 20, 20),
                            ego=(255, 255, 255))
    side = 2 * H
    top = cv2.resize(top, (side, side), interpolation=cv2.INTER_NEAREST)
    legend = pictures.class_legend(3 * W + side, count=NUM_CLASSES, columns=9, background=30)
    canvas = np.full((2 * H + legend.shape[0], 3 * W + side, 3), 30, np.uint8)
    canvas[:2 * H, :3 * W] = cams
    canvas[:2 * H, 3 * W:] = top
    canvas[2 * H:] = legend
    return canvas
