"""Training-time occupancy-flow warp: known moves, movers, selection, clearing, gradients, batching."""
from typing import NamedTuple

import numpy as np
import pytest
import torch

from occflownet.occ3d import GRID, Grid, NUM_CLASSES
from occflownet.geometry import make_transform, rotation_z
from occflownet.data.box_voxels import voxels_in_box
from occflownet.render.occupancy_flow import PackedMoves, idw_neighbours, warp_volumes

CAR, PED = 4, 7
CENTRE = np.array([0.2, 0.2, 1.2])  # a voxel centre, index (100, 100, 5)


class BoxMove(NamedTuple):
    """One box's move into one frame: voxels int [M, 3] (``voxels_in_box``), transform [4, 4] ego→ego, class."""

    voxels: object
    transform: object
    cls: int


def pack_moves(frames) -> PackedMoves:
    """Per output volume n, a list of BoxMoves → PackedMoves (through ``PackedMoves.from_arrays``, as training)."""
    moves = [(n, np.asarray(m.voxels).reshape(-1, 3), m.transform, m.cls) for n, ms in enumerate(frames) for m in ms]
    return PackedMoves.from_arrays(
        np.concatenate([v for _, v, _, _ in moves]) if moves else np.zeros((0, 3)),
        np.concatenate([np.full(len(v), k) for k, (_, v, _, _) in enumerate(moves)]) if moves else np.zeros(0),
        np.array([t for _, _, t, _ in moves]).reshape(-1, 4, 4), [c for _, _, _, c in moves], [n for n, *_ in moves])


def _scene(blocks):
    """Empty volume (σ = 0, logits = 0) with solid blocks: [(lo_idx, hi_idx_exclusive, class, sigma)]."""
    density = torch.zeros(GRID.shape)
    logits = torch.zeros(*GRID.shape, NUM_CLASSES)
    for lo, hi, cls, sigma in blocks:
        sl = tuple(slice(a, b) for a, b in zip(lo, hi))
        density[sl] = sigma
        logits[sl + (cls,)] = 4.0
    return density, logits


def warp_volume(density, logits, boxes, mover="idw"):
    """One volume [X, Y, Z] (+ logits [X, Y, Z, C]) warped into one frame by ``warp_volumes``."""
    d, l = warp_volumes(density[None], logits[None], torch.zeros(1, dtype=torch.long), pack_moves([boxes]), mover)
    return d[0], l[0]


def _occupied(density):
    return {tuple(v) for v in torch.nonzero(density > 0.5).tolist()}


def _translation(dx, dy=0.0, dz=0.0):
    return make_transform(np.eye(3), [dx, dy, dz])


CAR_BLOCK = ((95, 98, 3), (106, 103, 8))  # 11 x 5 x 5 cells around the centre voxel (100, 100, 5)
CAR_BOX = voxels_in_box(CENTRE, [2.0, 4.4, 2.0], 0.0)  # encloses the block


@pytest.mark.parametrize("mover", ["nearest", "idw"])
def test_translation_of_2m_moves_voxels_by_5_cells(mover):
    density, logits = _scene([(*CAR_BLOCK, CAR, 0.9)])
    d_t, l_t = warp_volume(density, logits, [BoxMove(CAR_BOX, _translation(2.0), CAR)], mover=mover)
    before = _occupied(density)
    assert _occupied(d_t) == {(i + 5, j, k) for i, j, k in before}
    assert torch.allclose(d_t[100:111, 98:103, 3:8], torch.full((11, 5, 5), 0.9), atol=1e-6)
    assert (l_t[100:111, 98:103, 3:8].argmax(-1) == CAR).all()
    # the input is untouched (the warp returns a copy)
    assert _occupied(density) == before


@pytest.mark.parametrize("mover", ["nearest", "idw"])
def test_yaw_90_about_box_centre_rotates_the_voxels(mover):
    # an L-shaped car: a bar along x plus a stub along +y at the front, so the rotation is visible
    density, logits = _scene([((97, 100, 4), (104, 101, 6), CAR, 0.8), ((103, 101, 4), (104, 103, 6), CAR, 0.8)])
    box = voxels_in_box(CENTRE, [5.0, 5.0, 2.0], 0.0)
    pivot = make_transform(np.eye(3), CENTRE)
    T = pivot @ rotation_z(np.pi / 2) @ np.linalg.inv(pivot)
    d_t, _ = warp_volume(density, logits, [BoxMove(box, T, CAR)], mover=mover)
    # +90° about z through voxel (100, 100): (i, j) → (100 - (j - 100), 100 + (i - 100))
    expected = {(200 - j, i, k) for i, j, k in _occupied(density)}
    assert _occupied(d_t) == expected
    assert torch.allclose(d_t[d_t > 0.5], torch.tensor(0.8), atol=1e-6)


def test_idw_weights_are_a_partition_of_unity_and_inverse_distance():
    torch.manual_seed(0)
    pts = torch.rand(500, 3, dtype=torch.float64) * torch.tensor([70.0, 70.0, 5.0]) + torch.tensor([-35.0, -35.0, -0.5])
    idx, w = idw_neighbours(pts)
    assert idx.shape == (500, 8, 3) and w.shape == (500, 8)
    assert (w >= 0).all() and torch.allclose(w.sum(-1), torch.ones(500, dtype=torch.float64))
    centres = torch.tensor(GRID.lower, dtype=torch.float64) + (idx.double() + 0.5) * GRID.voxel_size
    # the 8 centres bracket the point (it lies in their cell)
    assert ((centres.min(1).values <= pts) & (pts <= centres.max(1).values)).all()
    inv = 1 / torch.linalg.vector_norm(pts[:, None] - centres, dim=-1)
    assert torch.allclose(w, inv / inv.sum(-1, keepdim=True))
    # exactly on a centre: weight 1 there
    on = torch.tensor([[0.2, 0.2, 1.2]], dtype=torch.float64)
    idx, w = idw_neighbours(on)
    hit = w[0].argmax()
    assert w[0, hit] == 1.0 and w[0].sum() == 1.0 and idx[0, hit].tolist() == [100, 100, 5]


def test_nearest_round_trip_is_exact_for_cell_shifts():
    density, logits = _scene([(*CAR_BLOCK, CAR, 0.7), ((20, 20, 0), (30, 25, 2), 11, 0.95)])
    shift = np.array([3, -2, 1]) * GRID.voxel_size
    T = _translation(*shift)
    d_t, l_t = warp_volume(density, logits, [BoxMove(CAR_BOX, T, CAR)], mover="nearest")
    assert not torch.equal(d_t, density)
    back_box = voxels_in_box(CENTRE + shift, [2.0, 4.4, 2.0], 0.0)
    d_b, l_b = warp_volume(d_t, l_t, [BoxMove(back_box, np.linalg.inv(T), CAR)], mover="nearest")
    # exact: whole-voxel moves land on voxel centres, far from any face, so values are copied, not mixed
    assert torch.equal(d_b, density) and torch.equal(l_b, logits)


def test_idw_round_trip_error_is_bounded():
    density, logits = _scene([(*CAR_BLOCK, CAR, 0.7)])
    shift = np.array([0.5, -0.3, 0.0])  # 1.25 and 0.75 cells: every value is spread over several targets
    T = _translation(*shift)
    d_t, l_t = warp_volume(density, logits, [BoxMove(CAR_BOX, T, CAR)], mover="idw")
    back_box = voxels_in_box(CENTRE + shift, [2.0, 4.4, 2.0], 0.0)
    d_b, _ = warp_volume(d_t, l_t, [BoxMove(back_box, np.linalg.inv(T), CAR)], mover="idw")
    block = (slice(95, 106), slice(98, 103), slice(3, 8))
    inner = (slice(97, 104), slice(100, 101), slice(5, 6))  # two cells from the block's faces
    # interior: a fully covered target takes the weighted mean of equal values → exactly restored
    assert torch.allclose(d_b[inner], torch.tensor(0.7), atol=1e-5)
    # edges are blurred by the two splats; bound the damage
    err = (d_b - density).abs()
    assert err.max() <= 0.6 and err[block].mean() < 0.2
    assert d_b.min() >= 0 and d_b.max() <= 0.7 + 1e-6  # convex combinations only: σ stays in range
    assert abs(float(d_b.sum() - density.sum())) / float(density.sum()) < 0.05
    # occupancy (σ > 0.5) after the round trip lies within the original block, and keeps most of it
    back, orig = _occupied(d_b), _occupied(density)
    assert back <= orig and len(back) > 0.55 * len(orig)


def test_only_voxels_of_the_box_class_move_and_sources_are_cleared():
    # the box holds a car block and, in its margin, a pedestrian block; a car elsewhere is outside the box
    density, logits = _scene([((98, 99, 4), (103, 102, 6), CAR, 0.9), ((98, 102, 4), (100, 103, 6), PED, 0.6),
                              ((150, 150, 4), (152, 152, 6), CAR, 0.9)])
    d_t, l_t = warp_volume(density, logits, [BoxMove(CAR_BOX, _translation(0.0, -4.0), CAR)], mover="nearest")
    # exact: voxels that no box moves are copies
    assert torch.equal(d_t[98:100, 102:103, 4:6], density[98:100, 102:103, 4:6])  # pedestrian stays
    assert torch.equal(l_t[98:100, 102:103, 4:6], logits[98:100, 102:103, 4:6])
    assert torch.equal(d_t[150:152, 150:152], density[150:152, 150:152])  # car outside the box stays
    assert (d_t[98:103, 99:102, 4:6] == 0).all() and (l_t[98:103, 99:102, 4:6] == 0).all()  # vacated
    assert torch.allclose(d_t[98:103, 89:92, 4:6], torch.tensor(0.9))  # 4 m = 10 cells towards -y
    # a box of another class moves nothing
    d_p, l_p = warp_volume(density, logits, [BoxMove(CAR_BOX, _translation(0.0, -4.0), 10)], mover="nearest")
    assert torch.equal(d_p, density) and torch.equal(l_p, logits)


def test_moves_leaving_the_grid_are_dropped_not_clamped():
    density, logits = _scene([((196, 100, 4), (199, 101, 5), CAR, 0.9)])
    box = voxels_in_box([39.0, 0.2, 0.8], [1.0, 2.0, 1.0], 0.0)
    for mover in ("nearest", "idw"):
        d_t, _ = warp_volume(density, logits, [BoxMove(box, _translation(2.0), CAR)], mover=mover)
        assert _occupied(d_t) == set()  # gone, not piled up on the border slice
        assert float(d_t[199].max()) < 0.5


def test_overlapping_boxes_move_a_voxel_once():
    # two cars side by side (y rows 98..100 and 101..102); their enlarged boxes overlap on rows 100 and 101
    density, logits = _scene([((98, 98, 4), (103, 101, 5), CAR, 0.9), ((98, 101, 4), (103, 103, 5), CAR, 0.9)])
    box_a = voxels_in_box([0.2, -0.2, 0.8], [1.2, 2.0, 0.4], 0.0, margin_scale=1.0, margin_add=0.8)
    box_b = voxels_in_box([0.2, 0.8, 0.8], [0.8, 2.0, 0.4], 0.0, margin_scale=1.0, margin_add=0.8)
    overlap = {tuple(v) for v in box_a.tolist()} & {tuple(v) for v in box_b.tolist()} & _occupied(density)
    assert {j for _, j, _ in overlap} == {100, 101}  # car voxels that both boxes select
    moves = [BoxMove(box_a, _translation(0.0, -8.0), CAR), BoxMove(box_b, _translation(0.0, 8.0), CAR)]
    d_t, _ = warp_volume(density, logits, moves, mover="nearest")
    # each car moved away with its own box; nothing duplicated
    assert len(_occupied(d_t)) == len(_occupied(density))
    assert _occupied(d_t) == {(i, j - 20, k) for i, j, k in _occupied(density) if j <= 100} | \
        {(i, j + 20, k) for i, j, k in _occupied(density) if j >= 101}


def test_batched_warp_matches_single_warps_and_plain_copies():
    torch.manual_seed(1)
    d0, l0 = _scene([(*CAR_BLOCK, CAR, 0.9)])
    d1, l1 = _scene([((40, 40, 2), (45, 43, 4), PED, 0.8)])
    density, logits = torch.stack([d0, d1]), torch.stack([l0, l1])
    ped_box = voxels_in_box([-21.8, -22.6, 0.0], [1.6, 2.4, 1.2], 0.0)
    frames = [[], [BoxMove(CAR_BOX, _translation(1.2), CAR)], [], [BoxMove(ped_box, _translation(0.0, 0.4), PED)]]
    source = torch.tensor([0, 0, 1, 1])
    # exact: the moves are whole voxels (1.2 m, 0.4 m), so every moved centre snaps onto a centre (weight 1) and the
    # batched and the single warps copy the same values; frames without moves are copies
    for mover in ("idw", "nearest"):
        d_n, l_n = warp_volumes(density, logits, source, pack_moves(frames), mover=mover)
        assert d_n.shape == (4, *GRID.shape) and l_n.shape == (4, *GRID.shape, NUM_CLASSES)
        assert torch.equal(d_n[0], d0) and torch.equal(d_n[2], d1)
        for n, (src, moves) in enumerate(zip(source.tolist(), frames)):
            d_s, l_s = warp_volume(density[src], logits[src], moves, mover=mover)
            assert torch.equal(d_n[n], d_s) and torch.equal(l_n[n], l_s)
    # PackedMoves.concat shifts volumes and box rows
    joined = PackedMoves.concat([pack_moves(frames[:2]), pack_moves(frames[2:])], [0, 2])
    d_j, _ = warp_volumes(density, logits, source, joined)
    assert torch.equal(d_j, warp_volumes(density, logits, source, pack_moves(frames))[0])


SMALL = Grid(lower=(0.0, 0.0, 0.0), upper=(2.4, 2.4, 1.6), voxel_size=0.4, shape=(6, 6, 4))


@pytest.mark.parametrize("mover", ["idw", "nearest"])
def test_gradients_flow_from_the_warped_copy_to_the_original(mover):
    torch.manual_seed(2)
    density = torch.rand(1, *SMALL.shape, dtype=torch.float64) * 0.5
    logits = torch.randn(1, *SMALL.shape, 3, dtype=torch.float64)
    logits[0, 1:3, 1:3, 1:3, 2] = 10.0  # an object of class 2
    density[0, 1:3, 1:3, 1:3] = 0.9
    box = np.array([[i, j, k] for i in range(0, 4) for j in range(0, 4) for k in range(0, 4)])
    T = make_transform(rotation_z(0.3)[:3, :3], [0.55, 0.35, 0.1])
    moves = pack_moves([[BoxMove(box, T, 2)]])

    def f(d, l):
        out_d, out_l = warp_volumes(d, l, torch.zeros(1, dtype=torch.long), moves, mover=mover, grid=SMALL)
        return out_d, out_l

    d = density.clone().requires_grad_()
    l = logits.clone().requires_grad_()
    out_d, out_l = f(d, l)
    (out_d.sum() + out_l.sum()).backward()
    assert d.grad[0, 1:3, 1:3, 1:3].abs().sum() > 0  # moved voxels receive gradient through their new place
    assert l.grad[0, 1:3, 1:3, 1:3].abs().sum() > 0
    assert torch.autograd.gradcheck(f, (density.clone().requires_grad_(), logits.clone().requires_grad_()))


def test_bad_inputs_are_rejected():
    density, logits = _scene([])
    with pytest.raises(ValueError, match="mover"):
        warp_volume(density, logits, [], mover="bilinear")
    with pytest.raises(ValueError, match="density"):
        warp_volumes(density[None, :100], logits[None, :100], torch.zeros(1, dtype=torch.long), pack_moves([[]]))
    with pytest.raises(ValueError, match="volume"):
        warp_volumes(density[None], logits[None], torch.zeros(1, dtype=torch.long),
                     pack_moves([[], [BoxMove(CAR_BOX, np.eye(4), CAR)]]))
    with pytest.raises(ValueError, match="inside the grid"):
        warp_volume(density, logits, [BoxMove(np.array([[200, 0, 0]]), np.eye(4), CAR)])
