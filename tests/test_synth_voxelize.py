"""The geometric truth of the synthetic world: voxelisation of boxes and the ground against known answers (the
benchmark labels come from the label pipeline: tests/test_labels_*.py)."""
import numpy as np

from occflownet.occ3d import FREE, Grid
from occflownet.synth.voxelize import voxelize
from occflownet.synth.world import Boxes, GroundRaster, World


def small_world(boxes: Boxes) -> World:
    raster = GroundRaster(np.full((200, 200), 11, np.uint8), np.zeros((200, 200), np.uint8), -10.0, -10.0, 0.1)
    return World("t", np.eye(4), raster, boxes, [], np.zeros(2), 0.0, np.array([0.0, 0.0, 1.0]))


def box(center, half, yaw, raw=28):
    return Boxes(np.array([center], float), np.array([half], float), np.array([yaw], float),
                 np.array([raw], np.uint8), np.ones((1, 3), np.float32), np.zeros(1, np.int8),
                 np.ones(1, np.float32), np.full(1, -1, np.int32))


def test_voxelize_axis_aligned_and_rotated_boxes():
    grid = Grid(lower=(-4.0, -4.0, -1.0), upper=(4.0, 4.0, 2.2), voxel_size=0.4, shape=(20, 20, 8))
    # axis-aligned box x in [0.1, 0.7], y in [-0.3, 0.3], z in [0, 1]: voxels i 10..11, j 9..10, k 2..4
    world = small_world(box((0.4, 0.0, 0.5), (0.3, 0.3, 0.5), 0.0, raw=17))
    sem = voxelize(world, world.static, np.eye(4), grid)
    car = np.argwhere(sem == 4)
    assert {tuple(v) for v in car} == {(i, j, k) for i in (10, 11) for j in (9, 10) for k in (2, 3, 4)}
    assert (sem[:, :, 2][sem[:, :, 2] != 4] == 11).all() and (sem[:, :, [0, 1, 5, 6, 7]] != 11).all()
    # a 2.2 x 2.2 x 1.4 m box (x, y in [-1.1, 1.1]: i, j 7..12; z in [0.4, 1.8]: k 3..6): Occ3D-like surface
    # labels, the 4 x 4 x 2 voxels wholly inside stay free
    world = small_world(box((0.0, 0.0, 1.1), (1.1, 1.1, 0.7), 0.0, raw=17))
    sem = voxelize(world, world.static, np.eye(4), grid)
    assert (sem == 4).sum() == 6 * 6 * 4 - 4 * 4 * 2 and (sem[7:13, 7:13, 3:7] == 4).sum() == 112
    assert (sem[8:12, 8:12, 4:6] == FREE).all()
    # rotated box: every voxel holding a point of the box's surface is marked; every marked voxel touches the
    # surface (it overlaps the box and is not wholly inside it)
    yaw = 0.7
    world = small_world(box((0.3, -0.2, 0.9), (1.3, 0.4, 0.6), yaw, raw=17))
    sem = voxelize(world, world.static, np.eye(4), grid)
    rng = np.random.default_rng(0)
    local = rng.uniform(-1, 1, (20000, 3))
    face = rng.integers(0, 3, len(local))
    local[np.arange(len(local)), face] = np.sign(local[np.arange(len(local)), face])   # onto one of the 6 faces
    local *= [1.3, 0.4, 0.6]
    c, s = np.cos(yaw), np.sin(yaw)
    pts = np.stack([c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1], local[:, 2]], 1)
    pts += [0.3, -0.2, 0.9]
    ijk = grid.index_of(pts)
    assert (sem[ijk[:, 0], ijk[:, 1], ijk[:, 2]] == 4).all()
    marked = np.argwhere(sem == 4)
    centres = np.asarray(grid.lower) + (marked + 0.5) * 0.4 - [0.3, -0.2, 0.9]
    lx, ly = c * centres[:, 0] + s * centres[:, 1], -s * centres[:, 0] + c * centres[:, 1]
    reach = 0.2 * np.sqrt(2)  # half the voxel's xy diagonal
    assert (np.abs(lx) < 1.3 + reach).all() and (np.abs(ly) < 0.4 + reach).all()
    assert len(marked) < 1.6 * len({tuple(v) for v in ijk})
