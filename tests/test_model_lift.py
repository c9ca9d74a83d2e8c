import numpy as np
import pytest
import torch

from occflownet.occ3d import GRID
from occflownet.geometry import rotation_z
from occflownet.model.decoder import unblock
from occflownet.model.lift import LiftSplat, frustum_points, invert_3x3, scatter_pool, voxel_rows
from occflownet.contract import calibration_arrays
from occflownet.rig import default_rig


def fine_grid(fine_points: tuple[torch.Tensor, torch.Tensor], batch: int, stride: int) -> torch.Tensor:
    """Dense full-resolution pooled features [B, X, Y, Z, C] from LiftSplat's (rows, features), to inspect them."""
    rows, feats = fine_points
    cx, cy, cz = (n // stride for n in GRID.shape)
    dense = scatter_pool(feats, rows, batch * cx * cy * cz * stride ** 3)
    return unblock(dense.reshape(batch, cx, cy, cz, stride ** 3, -1), stride)


def _rig(h=6, w=10):
    """Feature-map intrinsics for an h×w map (a rescaled default rig) and the rig's cam2ego, batch 1."""
    K, T = calibration_arrays(default_rig(w * 16, h * 16))
    K[:, :2] /= 16.0
    return torch.from_numpy(K)[None], torch.from_numpy(T)[None]


def test_invert_3x3():
    m = torch.randn(4, 3, 3, dtype=torch.float64) + 3 * torch.eye(3, dtype=torch.float64)
    assert torch.allclose(invert_3x3(m) @ m, torch.eye(3, dtype=torch.float64).expand(4, 3, 3), atol=1e-12)


def test_frustum_points_reproject_to_their_pixels_and_depths():
    K, T = _rig()
    depths = torch.tensor([2.0, 7.5, 30.0])
    pts = frustum_points(K, T, depths, 6, 10)                               # [1, 6, 3, 6, 10, 3] ego
    assert pts.shape == (1, 6, 3, 6, 10, 3)
    ego2cam = torch.linalg.inv(T[0].double())                                # [6, 4, 4]
    homog = torch.cat([pts[0].double(), torch.ones(*pts.shape[1:-1], 1, dtype=torch.float64)], -1)
    cam = torch.einsum("vij,vdhwj->vdhwi", ego2cam, homog)[..., :3]
    assert torch.allclose(cam[..., 2], depths.double()[None, :, None, None].expand(6, 3, 6, 10), atol=1e-4)
    pix = torch.einsum("vij,vdhwj->vdhwi", K[0].double(), cam)
    uv = pix[..., :2] / pix[..., 2:]
    assert torch.allclose(uv[..., 0], torch.arange(10.0, dtype=torch.float64).expand(6, 3, 6, 10), atol=1e-3)
    assert torch.allclose(uv[..., 1], torch.arange(6.0, dtype=torch.float64)[:, None].expand(6, 3, 6, 10),
                          atol=1e-3)


def test_voxel_rows_known_answers():
    pts = torch.tensor([[[-39.9, -39.9, -0.9], [0.1, 0.1, 0.1], [39.9, 39.9, 5.3], [40.1, 0.0, 0.0],
                         [0.0, 0.0, -1.2], [float("nan"), 0.0, 0.0]]])
    coarse, fine, valid = voxel_rows(pts, 2)
    assert valid.tolist() == [[1, 1, 1, 0, 0, 0]]
    # (0.1, 0.1, 0.1) is voxel (100, 100, 2) → coarse (50, 50, 1), sub (0, 0, 0)
    assert coarse[0, 1].item() == (50 * 100 + 50) * 8 + 1
    assert fine[0, 1].item() == coarse[0, 1].item() * 8
    assert coarse[0, 2].item() == (99 * 100 + 99) * 8 + 7 and fine[0, 2].item() == coarse[0, 2].item() * 8 + 7
    c1, f1, _ = voxel_rows(pts, 1)
    assert f1[0, 1].item() == (100 * 200 + 100) * 16 + 2 == c1[0, 1].item()


def test_scatter_pool_adds_repeated_rows():
    feats = torch.arange(12.0).reshape(6, 2)
    rows = torch.tensor([3, 3, 3, 0, 3, 1])
    out = scatter_pool(feats, rows, 5)
    assert out.tolist() == [[6, 7], [10, 11], [0, 0], [0 + 2 + 4 + 8, 1 + 3 + 5 + 9], [0, 0]]


def test_lift_puts_a_certain_depth_into_the_right_voxel_and_drops_outside_points():
    K, T = _rig(h=6, w=10)
    depths = [5.0, 60.0]                                                    # 60 m is outside the grid
    lift = LiftSplat(depths, stride=1)
    depth_prob = torch.zeros(1, 6, 2, 6, 10)
    depth_prob[0, 0, 0, 3, 5] = 1.0                                         # front camera, one pixel, 5 m
    depth_prob[0, 1, 1] = 1.0                                               # front-right camera, all at 60 m
    context = torch.ones(1, 6, 6, 10, 3)
    grid, fine = lift(depth_prob, context, None, K, T)
    assert fine is None and grid.shape == (1, 200, 200, 16, 3)
    assert grid.sum().item() == pytest.approx(3.0)                          # only the 5 m point survives
    p = frustum_points(K, T, torch.tensor(depths), 6, 10)[0, 0, 0, 3, 5].numpy()
    i, j, k = GRID.index_of(p)
    assert grid[0, i, j, k].tolist() == [1.0, 1.0, 1.0]


def test_fine_points_pool_to_the_same_mass_as_the_trunk():
    K, T = _rig()
    lift = LiftSplat(np.linspace(1.5, 44.5, 12).tolist(), stride=4)
    g = torch.Generator().manual_seed(0)
    depth_prob = torch.softmax(torch.randn(1, 6, 12, 6, 10, generator=g), 2)
    ctx = torch.rand(1, 6, 6, 10, 2, generator=g)
    trunk, fine_points = lift(depth_prob, ctx, ctx, K, T)                   # same features in both paths
    dense = fine_grid(fine_points, 1, 4)                                    # [1, 200, 200, 16, 2]
    assert trunk.shape == (1, 50, 50, 4, 2) and dense.shape == (1, 200, 200, 16, 2)
    pooled = dense.reshape(1, 50, 4, 50, 4, 4, 4, 2).sum((2, 4, 6))
    assert torch.allclose(pooled, trunk, atol=1e-5)


def rotated_pooling(lift, depth_prob, context, K, T):
    """Pooled grid with the rig as given and with every cam2ego turned by +90° about ego z."""
    turn = torch.from_numpy(rotation_z(np.pi / 2)).float()
    turn[:2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])                 # exact
    return lift(depth_prob, context, None, K, T)[0], lift(depth_prob, context, None, K, turn @ T)[0]


def assert_rotated(grid, grid_rot):
    """grid_rot must equal grid turned 90° about the grid centre (x → y): up to voxel discretisation."""
    expected = torch.rot90(grid, 1, dims=(1, 2))
    diff = (grid_rot - expected).abs().sum() / grid.abs().sum()
    assert diff < 1e-3, diff
    assert not torch.allclose(grid_rot, grid, atol=1e-3)                    # the rotation is not trivial


def test_turning_the_rig_turns_the_pooled_features():
    K, T = _rig()
    T[..., :3, 3] += torch.tensor([0.013, 0.007, 0.0])   # off the symmetric positions: no point on a voxel face
    lift = LiftSplat(np.linspace(1.5, 38.5, 20).tolist(), stride=1)
    g = torch.Generator().manual_seed(1)
    depth_prob = torch.softmax(3 * torch.randn(1, 6, 20, 6, 10, generator=g), 2)
    context = torch.rand(1, 6, 6, 10, 4, generator=g)
    assert_rotated(*rotated_pooling(lift, depth_prob, context, K, T))
