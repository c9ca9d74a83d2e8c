"""Side-by-side pictures (occflownet.eval.picture): the camera view colours the first occupied voxel's class."""
from __future__ import annotations

import numpy as np

from occflownet.occ3d import CLASS_COLORS, FREE, GRID
from occflownet.eval.picture import camera_view, side_by_side


def _front_camera():
    # OpenCV camera at the ego origin, 1 m up, looking along +x (z_cam = x_ego, x_cam = -y_ego, y_cam = -z_ego)
    cam2ego = np.eye(4)
    cam2ego[:3, :3] = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cam2ego[2, 3] = 1.0
    K = np.array([[200.0, 0.0, 40.0], [0.0, 200.0, 30.0], [0.0, 0.0, 1.0]])  # narrow: ±1.2 m high at 8 m
    return K, cam2ego


def test_a_wall_ahead_fills_the_view_with_its_class():
    grid = np.full(GRID.shape, FREE, np.uint8)
    grid[120:122, :, :] = 15                            # a manmade wall 8 m ahead, across the whole grid
    K, cam2ego = _front_camera()
    image = np.full((60, 80, 3), 100, np.uint8)
    view = camera_view(grid, image, K, cam2ego, step=2)
    assert view.shape == (30, 40, 3)
    assert np.all(view == CLASS_COLORS[15])
    empty = camera_view(np.full(GRID.shape, FREE, np.uint8), image, K, cam2ego, step=2)
    assert np.all(empty == 45)                           # nothing hit: the image, dimmed
    pic = side_by_side(grid, grid, image, K, cam2ego, panel_width=200)
    assert pic.dtype == np.uint8 and pic.shape[1] == 600
