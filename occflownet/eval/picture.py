"""Side-by-side pictures of a prediction and its ground truth, for a person to judge at a glance.

Top row: one camera's image, the ground-truth grid seen from that camera, the predicted grid seen from that camera
(each pixel coloured by the class of the first occupied voxel along its ray, ``first_hits``: an exact voxel walk,
no model needed; pixels whose ray meets nothing in the grid show the camera image dimmed). Bottom row: top-down
views of the ground truth and the prediction (``pictures.top_down``: highest occupied voxel per column). Grids are uint8
[200, 200, 16] ([x, y, z], ego frame of the keyframe, 17 = free); the camera's ``cam2ego`` maps the OpenCV camera
frame to that ego frame and ``intrinsic`` is for the image as given.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from occflownet.contract import calibration_json
from occflownet.occ3d import CLASS_COLORS, FREE, GRID
from occflownet.eval.ray_iou import first_hits
from occflownet.pictures import class_legend, top_down


def camera_view(occupancy: np.ndarray, image: np.ndarray, intrinsic: np.ndarray, cam2ego: np.ndarray,
                step: int = 2) -> np.ndarray:
    """uint8 [H // step, W // step, 3]: the grid seen from a camera (class colours of the first occupied voxel
    through every ``step``-th pixel centre), the dimmed image ``image`` [H, W, 3] where the ray hits nothing."""
    h, w = image.shape[:2]
    v, u = np.mgrid[0:h - step + 1:step, 0:w - step + 1:step]
    pix = np.stack([u + 0.5 * step, v + 0.5 * step, np.ones_like(u, dtype=float)], -1).reshape(-1, 3)
    rays = pix @ np.linalg.inv(np.asarray(intrinsic, dtype=np.float64)).T
    T = np.asarray(cam2ego, dtype=np.float64)
    dirs = rays @ T[:3, :3].T
    cls, _ = first_hits(np.asarray(occupancy, dtype=np.uint8), T[:3, 3], dirs, GRID)
    small = image[v, u].reshape(-1, 3).astype(np.float32)
    out = np.where((cls != FREE)[:, None], CLASS_COLORS[np.minimum(cls, FREE)], 0.45 * small)
    return out.reshape(v.shape[0], v.shape[1], 3).astype(np.uint8)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    import cv2

    out = np.ascontiguousarray(img.copy())
    cv2.rectangle(out, (0, 0), (8 + 9 * len(text), 20), (0, 0, 0), -1)
    cv2.putText(out, text, (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _fit(img: np.ndarray, width: int) -> np.ndarray:
    import cv2

    height = int(round(img.shape[0] * width / img.shape[1]))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_NEAREST)


def side_by_side(prediction: np.ndarray, ground_truth: np.ndarray, image: np.ndarray, intrinsic: np.ndarray,
                 cam2ego: np.ndarray, camera: str = "CAM_FRONT", panel_width: int = 400) -> np.ndarray:
    """uint8 RGB picture: [image | ground truth from the camera | prediction from the camera] over
    [ground truth top-down | prediction top-down] (see the module docstring)."""
    for name, grid in (("prediction", prediction), ("ground_truth", ground_truth)):
        if np.shape(grid) != GRID.shape:
            raise ValueError(f"{name} must be a grid of shape {GRID.shape}, got {np.shape(grid)}")
    top = [_label(_fit(image, panel_width), camera),
           _label(_fit(camera_view(ground_truth, image, intrinsic, cam2ego), panel_width), "ground truth"),
           _label(_fit(camera_view(prediction, image, intrinsic, cam2ego), panel_width), "prediction")]
    row1 = np.concatenate(top, axis=1)
    bev = [_label(_fit(top_down(g, scale=2), panel_width), t)
           for g, t in ((ground_truth, "ground truth, top-down"), (prediction, "prediction, top-down"))]
    row2 = np.concatenate(bev + [np.full_like(bev[0], 255)], axis=1)
    legend = class_legend(row1.shape[1])
    return np.concatenate([row1, row2, legend], axis=0)


def sample_side_by_side(dataroot, sample, prediction: np.ndarray, camera: int = 0) -> np.ndarray:
    """:func:`side_by_side` of a keyframe (``sample``: a SampleRecord of the index of ``dataroot``):
    ``prediction`` uint8 [200, 200, 16] against its Occ3D labels, seen from camera ``camera`` (index in
    ``occ3d.CAMERAS``)."""
    from occflownet.occ3d import CAMERAS
    from occflownet.data.loaders import load_occupancy, load_sample_images

    images = load_sample_images(dataroot, sample)
    labels = load_occupancy(dataroot, sample.occupancy_path)
    return side_by_side(prediction, labels.semantics, images[camera], sample.intrinsics[camera],
                        sample.cam2current_ego()[camera], CAMERAS[camera])


def sample_viewer(dataroot, sample, prediction: np.ndarray, path) -> Path:
    """The 3D viewer file (:mod:`occflownet.viewer`) of a keyframe: its Occ3D labels (with ``mask_camera``) beside
    ``prediction`` uint8 [200, 200, 16], the six camera images as thumbnails and their frusta (intrinsics and
    camera → keyframe-ego transforms of the index) → ``path``."""
    from occflownet import viewer
    from occflownet.data.loaders import load_occupancy

    dataroot = Path(dataroot)
    labels = load_occupancy(dataroot, sample.occupancy_path)
    calib = calibration_json(sample.intrinsics, sample.cam2current_ego())
    images = {c.name: (dataroot / c.path).read_bytes() for c in sample.cameras}
    grids = [viewer.ViewGrid("ground truth", labels.semantics, labels.mask_camera),
             viewer.ViewGrid("prediction", prediction)]
    return viewer.write_viewer(path, grids, calib, images, title=f"{sample.scene_name} {sample.token}",
                               subtitle=f"{dataroot}: Occ3D labels beside the prediction")
