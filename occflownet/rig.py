"""The default six-camera rig: nuScenes-like placement and fields of view (rounded, idealised: level cameras).

The synthetic world uses it; a model records the rig it was trained on as the default calibration of its ONNX
file. Frames: ``cam2ego`` maps the OpenCV camera frame (x right, y down, z forward) into the ego frame
(x forward, y left, z up). Intrinsics are for an image of ``width × height`` pixels (nuScenes: 1600 × 900).
Parsing and validating calibration JSON is the contract's (:mod:`occflownet.contract`); this module only makes
the training rig.
"""
from __future__ import annotations

import numpy as np

from occflownet.contract.calibration import calibration_json
from occflownet.occ3d import CAMERAS

# name: (position in the ego frame [m], yaw of the optical axis about +z [deg], focal length at 1600 px width)
_RIG_1600 = {
    "CAM_FRONT": ((1.70, 0.00, 1.51), 0.0, 1266.0),
    "CAM_FRONT_RIGHT": ((1.55, -0.49, 1.50), -55.0, 1260.0),
    "CAM_FRONT_LEFT": ((1.52, 0.49, 1.51), 55.0, 1260.0),
    "CAM_BACK": ((0.03, 0.00, 1.58), 180.0, 809.0),
    "CAM_BACK_LEFT": ((1.04, 0.48, 1.56), 110.0, 1260.0),
    "CAM_BACK_RIGHT": ((1.02, -0.48, 1.56), -110.0, 1260.0),
}
NUSCENES_SIZE = (1600, 900)

# Camera axes expressed in the ego frame for a camera looking along +x: columns are cam x, y, z.
_CAM_TO_EGO_AXES = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def cam2ego(position, yaw_deg: float) -> np.ndarray:
    """4×4 camera→ego transform of a level camera at ``position`` looking along yaw ``yaw_deg``."""
    a = np.radians(yaw_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = rz @ _CAM_TO_EGO_AXES
    T[:3, 3] = position
    return T


def intrinsic(focal_1600: float, width: int, height: int) -> np.ndarray:
    """3×3 pinhole intrinsics scaled from the 1600-px nuScenes focal length to ``width × height``."""
    s = width / NUSCENES_SIZE[0]
    return np.array([[focal_1600 * s, 0.0, width / 2.0], [0.0, focal_1600 * s, height / 2.0], [0.0, 0.0, 1.0]])


def default_rig(width: int = 1600, height: int = 900) -> dict:
    """The default rig as calibration JSON (docs/contracts.md), plus its ``image_size`` [width, height]."""
    rig = [_RIG_1600[name] for name in CAMERAS]
    return calibration_json([intrinsic(f, width, height) for _, _, f in rig],
                            [cam2ego(pos, yaw) for pos, yaw, _ in rig], (width, height))
