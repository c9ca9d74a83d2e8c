"""End to end: boxes → flow record → warped per-frame volumes → rendered rays of adjacent frames.

A hand-built scene (no synthetic world needed): a car-class block that crosses the road laterally between
keyframes, a manmade wall behind it. Rays of frames t = ±1 aimed at where the car *was* at that time must render
'car' through the warped volume and 'manmade' through the unwarped one, and the reverse for rays aimed at the
car's place at t = 0 (the vacated place shows the background).
"""
import numpy as np
import pytest
import torch

from occflownet.occ3d import GRID, NUM_CLASSES
from occflownet.data.flow import box_flows, flow_moves
from occflownet.geometry import make_transform, matrix_to_quaternion, yaw_to_quaternion
from occflownet.data.box_voxels import voxels_in_box
from occflownet.render.occupancy_flow import PackedMoves, warp_volumes

render = pytest.importorskip("occflownet.render.volume_render", reason="volume renderer not available")

CAR, MANMADE = 4, 15
EGO = make_transform(yaw_to_quaternion(0.7), [300.0, -120.0, 0.5])  # current ego pose (arbitrary)
CAR_WLH = [1.8, 4.2, 1.5]
# car centre in the current ego frame at t = -1, 0, +1 (crossing towards -y; 4.8 m = 12 cells, 4.7 m is not
# a whole number of cells, so the IDW mover really interpolates for t = -1)
CAR_AT = {-1: np.array([12.2, 4.9, 0.6]), 0: np.array([12.2, 0.2, 0.6]), 1: np.array([12.2, -4.6, 0.6])}
FRAMES = [-1, 0, 1]


def _global_boxes(t):
    pose = EGO @ make_transform(np.eye(3), CAR_AT[t])
    return {"instance_token": ["car-1"], "label": [CAR], "center": [pose[:3, 3]], "size_wlh": [CAR_WLH],
            "rotation": [matrix_to_quaternion(pose[:3, :3])]}


def _scene():
    density = torch.zeros(1, *GRID.shape)
    logits = torch.zeros(1, *GRID.shape, NUM_CLASSES)
    body = torch.as_tensor(voxels_in_box(CAR_AT[0], CAR_WLH, 0.0, margin_scale=1.0, margin_add=0.0))
    density[0][tuple(body.T)] = 1.0
    logits[0][tuple(body.T) + (CAR,)] = 5.0
    wall = (slice(175, 178), slice(None), slice(None))  # x ≈ 30 m, across the whole grid
    density[0][wall] = 1.0
    logits[0][wall + (MANMADE,)] = 5.0
    return density, logits


def _rays_towards(target, origin, n=12, seed=0):
    """n rays from origin to points scattered over the car body (±0.6 m, ±0.3 m) around target."""
    g = np.random.default_rng(seed)
    ends = target + g.uniform([-0.6, -0.4, -0.3], [0.6, 0.4, 0.3], size=(n, 3))
    d = ends - origin
    return (torch.tensor(np.repeat(origin[None], n, 0), dtype=torch.float32),
            torch.tensor(d / np.linalg.norm(d, axis=1, keepdims=True), dtype=torch.float32))


@pytest.mark.parametrize("mover", ["idw", "nearest"])
def test_adjacent_frame_rays_see_the_car_where_it_was(mover):
    rec = box_flows("sample", _global_boxes(0), {t: _global_boxes(t) for t in (-1, 1)}, EGO)
    moves = PackedMoves.from_arrays(**flow_moves(rec, FRAMES))
    density, logits = _scene()
    warped_d, warped_l = warp_volumes(density, logits, torch.zeros(len(FRAMES), dtype=torch.long), moves, mover)
    plain_d, plain_l = density.expand(3, *GRID.shape), logits.expand(3, *GRID.shape, NUM_CLASSES)
    cfg = render.RenderConfig()
    origin = np.array([0.5, 0.0, 0.9])  # the camera of each adjacent frame (its place matters little here)
    for t in (-1, 1):
        n = FRAMES.index(t)
        for target, warped_class, plain_class in ((CAR_AT[t], CAR, MANMADE), (CAR_AT[0], MANMADE, CAR)):
            o, d = _rays_towards(target, origin, seed=n)
            index = torch.full((len(o),), n, dtype=torch.long)
            gen = torch.Generator().manual_seed(0)
            out_w = render.render_rays(warped_d, warped_l, o, d, cfg, generator=gen, batch_index=index)
            gen = torch.Generator().manual_seed(0)
            out_p = render.render_rays(plain_d, plain_l, o, d, cfg, generator=gen, batch_index=index)
            assert (out_w.semantics.argmax(-1) == warped_class).all(), (t, target, mover)
            assert (out_p.semantics.argmax(-1) == plain_class).all(), (t, target, mover)
            if warped_class == CAR:  # the (normalised) depth is the car's, not the wall's
                hit_w, hit_p = out_w.depth / out_w.weight_sum, out_p.depth / out_p.weight_sum
                assert (hit_w < 14.0).all() and (hit_p > 28.0).all(), (hit_w, hit_p)
    # frame 0 is an untouched copy (exact)
    assert torch.equal(warped_d[1], density[0]) and torch.equal(warped_l[1], logits[0])


def test_gradient_of_an_adjacent_frame_ray_reaches_the_cars_voxels_at_t0():
    rec = box_flows("sample", _global_boxes(0), {1: _global_boxes(1)}, EGO)
    moves = PackedMoves.from_arrays(**flow_moves(rec, [1]))
    density, logits = _scene()
    density.requires_grad_()
    logits.requires_grad_()
    warped_d, warped_l = warp_volumes(density, logits, torch.zeros(1, dtype=torch.long), moves, "idw")
    o, d = _rays_towards(CAR_AT[1], np.array([0.5, 0.0, 0.9]))
    out = render.render_rays(warped_d, warped_l, o, d, render.RenderConfig(),
                             generator=torch.Generator().manual_seed(0),
                             batch_index=torch.zeros(len(o), dtype=torch.long))
    torch.nn.functional.cross_entropy(out.semantics, torch.full((len(o),), CAR)).backward()
    body = torch.as_tensor(voxels_in_box(CAR_AT[0], CAR_WLH, 0.0, margin_scale=1.0, margin_add=0.0))
    assert logits.grad[0][tuple(body.T)].abs().sum() > 0  # supervision at t = 1 trains the prediction at t = 0
    assert density.grad[0][tuple(body.T)].abs().sum() > 0
