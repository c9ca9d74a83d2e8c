"""The eval-mode (exported) computations checked against the training path's: sorted segment sums against
``index_add``, the z-sliced trunk convolutions against Conv3d + BatchNorm, the slabs' skip rows against a dense
grid, the slabs' widths."""
import numpy as np
import pytest
import torch
from torch import nn

from occflownet.model.decoder import SLAB_BYTES, ResBlock3d, conv_z, slab_width, z_slices
from occflownet.model.lift import POOL_BLOCK, BlockedPrefix, LiftSplat, run_ends, scatter_pool
from test_model_lift import _rig, fine_grid


def test_run_ends_known_answers():
    assert run_ends(torch.tensor([0, 0, 3, 5, 5, 5, 9])).tolist() == [1, 2, 5, 6]
    assert run_ends(torch.tensor([4, 4, 4])).tolist() == [2]
    assert run_ends(torch.tensor([7])).tolist() == [0]
    assert run_ends(torch.tensor([1, 2, 3])).tolist() == [0, 1, 2]
    assert run_ends(torch.zeros(0, dtype=torch.int64)).tolist() == []


def _sorted_values(rows=300_000, channels=4, seed=0):
    """Lifted-feature-like values float32 [rows, C] (probability × feature, in [0, 1)) and sorted run keys."""
    g = torch.Generator().manual_seed(seed)
    values = torch.rand(rows, channels, generator=g) * torch.rand(rows, 1, generator=g)
    keys = torch.sort(torch.randint(0, rows // 7, (rows,), generator=g)).values    # runs of ~7 rows
    return values, keys


def test_blocked_prefix_sums_match_a_float64_reference_over_300000_rows():
    values, keys = _sorted_values()
    assert values.shape[0] % POOL_BLOCK == 0
    prefix = BlockedPrefix(values)
    reference = torch.cumsum(values.double(), 0)                                   # [K, C] float64
    pos = torch.tensor([0, 1, POOL_BLOCK - 1, POOL_BLOCK, 12_345, 150_000, values.shape[0] - 1])
    # the prefixes (up to ~75,000) carry the float32 rounding of each block's total, ~1e-9 of their size
    assert torch.allclose(prefix.at(pos), reference[pos], rtol=1e-8, atol=1e-6)
    ends = run_ends(keys)
    sums = prefix.run_sums(ends)
    expected = scatter_pool(values.double(), keys, int(keys[-1]) + 1)[keys[ends]]   # float64 sums per run
    assert sums.dtype == torch.float32 and sums.shape == expected.shape
    assert torch.allclose(sums.double(), expected, rtol=0, atol=2e-6)
    # what the blocks are for: one float32 cumulative sum over all rows is far less accurate
    plain = torch.cumsum(values, 0)
    plain_sums = plain[ends] - torch.cat([plain[:1] * 0, plain[ends[:-1]]])
    assert (plain_sums.double() - expected).abs().max() > 1e-3


def _lift_inputs(depths, channels=3, seed=0, h=6, w=10):
    K, T = _rig(h, w)
    T[..., :3, 3] += torch.tensor([0.013, 0.007, 0.0])       # no frustum point exactly on a voxel face
    g = torch.Generator().manual_seed(seed)
    depth_prob = torch.softmax(2 * torch.randn(1, 6, len(depths), h, w, generator=g), 2)
    context = torch.rand(1, 6, h, w, channels, generator=g)
    fine = torch.rand(1, 6, h, w, channels + 1, generator=g)
    return depth_prob, context, fine, K, T


# depth bins 1 cm apart (every pixel's points share a voxel, neighbouring pixels often too) and spread ones
DEPTH_SETS = {"repeated": [6.0 + 0.01 * i for i in range(16)], "spread": np.linspace(1.5, 44.5, 12).tolist()}


@pytest.mark.parametrize("stride", [1, 2, 4])
@pytest.mark.parametrize("with_fine", [True, False])
@pytest.mark.parametrize("depths", sorted(DEPTH_SETS))
def test_sorted_pooling_equals_the_training_index_add(stride, with_fine, depths):
    lift = LiftSplat(DEPTH_SETS[depths], stride)
    depth_prob, context, fine, K, T = _lift_inputs(DEPTH_SETS[depths])
    fine = fine if with_fine else None
    with torch.no_grad():
        trunk_t, fine_t = lift.train()(depth_prob, context, fine, K, T)
        trunk_e, fine_e = lift.eval()(depth_prob, context, fine, K, T)
    assert (trunk_t.abs().sum(-1) > 0).sum() > 10                                   # points land in the grid
    # the same sums in another order (sorted segment sums): equal to float32 rounding
    assert torch.allclose(trunk_e, trunk_t, rtol=1e-5, atol=1e-6)
    assert (fine_e is None) == (fine_t is None) == (not with_fine)
    if with_fine:
        rows, sums = fine_e
        assert bool((rows[1:] > rows[:-1]).all())                                  # unique, ascending
        assert torch.allclose(fine_grid(fine_e, 1, stride), fine_grid(fine_t, 1, stride), rtol=1e-5, atol=1e-6)


def _conv_bn(c_in, c_out, k, seed):
    g = torch.Generator().manual_seed(seed)
    conv = nn.Conv3d(c_in, c_out, k, padding=k // 2, bias=False)
    bn = nn.BatchNorm3d(c_out)
    with torch.no_grad():
        conv.weight.copy_(torch.randn(conv.weight.shape, generator=g) * 0.3)
        for t in (bn.weight, bn.bias, bn.running_mean):
            t.copy_(torch.randn(c_out, generator=g))
        bn.running_var.copy_(torch.rand(c_out, generator=g) + 0.5)
    return conv, bn.eval()


@pytest.mark.parametrize("k, z", [(3, 4), (3, 8), (3, 1), (1, 4)])
def test_conv_z_equals_conv3d_and_batchnorm(k, z):
    conv, bn = _conv_bn(5, 6, k, seed=k + z)
    x = torch.randn(2, 5, 7, 9, z, generator=torch.Generator().manual_seed(3))     # [B, C, X, Y, Z]
    with torch.no_grad():
        expected = bn(conv(x)).permute(0, 4, 1, 2, 3)                              # [B, Z, O, X, Y]
        got = conv_z(x.permute(0, 4, 1, 2, 3), *z_slices(conv, bn))
    assert got.shape == expected.shape == (2, z, 6, 7, 9)
    assert torch.allclose(got, expected, rtol=1e-5, atol=1e-5)


def test_the_eval_trunk_equals_the_conv3d_modules():
    from occflownet.model.decoder import VoxelDecoder
    torch.manual_seed(0)
    decoder = VoxelDecoder(4, 2, 8, 2, 6, (5,), (5,))
    for block in decoder.blocks:
        assert isinstance(block, ResBlock3d)
    for m in decoder.modules():                                                     # non-trivial statistics
        if isinstance(m, nn.BatchNorm3d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    trunk = torch.randn(2, 5, 6, 4, 4)                                              # [B, Xc, Yc, Zc, C]
    decoder.eval()
    with torch.no_grad():
        got = decoder.trunk_rows(trunk)
        x = decoder.blocks(decoder.stem(trunk.permute(0, 4, 1, 2, 3)))
    assert torch.allclose(got, x.permute(0, 2, 3, 4, 1).reshape(-1, 8), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("batch", [1, 2])
def test_slab_rows_are_the_rows_of_each_slab_in_its_own_grid(batch):
    """Every row lands in exactly one slab, at the row of the slab's own grid [B·n·per] that holds the same
    (sample, plane, voxel), with its own value; the last slab is narrower (7 planes, slabs of 3)."""
    from occflownet.model.decoder import SlabRows
    planes, per, width = 7, 12, 3
    g = torch.Generator().manual_seed(batch)
    rows = torch.randperm(batch * planes * per, generator=g)[:40]                   # unique, any order
    values = torch.randn(40, 2, generator=g)
    dense = torch.zeros(batch * planes * per, 2)
    dense[rows] = values
    dense = dense.reshape(batch, planes, per, 2)
    split = SlabRows(rows, values, planes, per, width)
    seen = 0
    for x0 in range(0, planes, width):
        n = min(width, planes - x0)
        local, got = split.within(x0)
        slab = torch.zeros(batch * n * per, 2)
        slab[local] = got
        assert torch.equal(slab.reshape(batch, n, per, 2), dense[:, x0:x0 + n])  # same voxels, same values
        assert len(local.unique()) == len(local)
        seen += len(local)
    assert seen == 40


def test_slab_width():
    assert slab_width(50, 12_800, 32) == SLAB_BYTES // (4 * 32 * 12_800)
    assert slab_width(100, 6_400, 64) == SLAB_BYTES // (4 * 64 * 6_400)
    assert slab_width(3, 10, 8) == 3                                                # never more than the planes
    assert slab_width(50, 10 ** 8, 64) == 1                                         # at least one plane
