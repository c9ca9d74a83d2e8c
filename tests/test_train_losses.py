"""Losses (occflownet.train.losses): hand-computed values, LiDAR depth targets, modes."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from occflownet.occ3d import NUM_CLASSES
from occflownet.train.losses import (LossConfig, lidar_depth_loss, lidar_depth_targets, ray_losses, render_losses,
                               total_loss, voxel_losses)

LOG17 = math.log(NUM_CLASSES)


def _rendered():
    return SimpleNamespace(depth=torch.tensor([1.0, 3.0], requires_grad=True),
                           semantics=torch.zeros(2, NUM_CLASSES, requires_grad=True))


def test_render_losses_by_hand_with_and_without_class_weights():
    r = _rendered()
    gt, labels = torch.tensor([2.0, 3.0]), torch.tensor([0, 1])
    plain = render_losses(r.depth, r.semantics, gt, labels)
    assert plain["depth"].item() == pytest.approx(0.5)
    assert plain["semantics"].item() == pytest.approx(LOG17, rel=1e-6)
    omega = torch.ones(NUM_CLASSES)
    omega[0], omega[1] = 2.0, 0.5
    weighted = render_losses(r.depth, r.semantics, gt, labels, omega)
    assert weighted["depth"].item() == pytest.approx((2.0 * 1.0 + 0.5 * 0.0) / 2)
    assert weighted["semantics"].item() == pytest.approx(1.25 * LOG17, rel=1e-6)
    terms = ray_losses(r, gt, labels, omega, LossConfig())
    assert terms["render_depth"].item() == pytest.approx(0.05 * 1.0)
    assert terms["render_semantics"].item() == pytest.approx(1.25 * LOG17, rel=1e-6)
    terms["render_depth"].backward()
    assert r.depth.grad[0].item() == pytest.approx(0.05 * 2.0 * 2 * (1.0 - 2.0) / 2)


def test_render_losses_reject_bad_labels_and_handle_no_rays():
    r = _rendered()
    with pytest.raises(ValueError, match="labels_gt"):
        render_losses(r.depth, r.semantics, torch.tensor([2.0, 3.0]), torch.tensor([0, 17]))
    empty = render_losses(torch.zeros(0), torch.zeros(0, NUM_CLASSES), torch.zeros(0), torch.zeros(0, dtype=torch.long))
    assert empty["depth"].item() == 0 and empty["semantics"].item() == 0


# A front camera at ego (1, 0, 1.5) looking along +x (OpenCV: x right, y down, z forward), and a rear one.
FRONT = torch.tensor([[0.0, 0.0, 1.0, 1.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]])
REAR = torch.tensor([[0.0, 0.0, -1.0, -1.0], [1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0]])
K_FEAT = torch.tensor([[10.0, 0.0, 7.0], [0.0, 10.0, 4.0], [0.0, 0.0, 1.0]])  # feature map 16 x 10
CENTERS = 1.25 + 0.5 * torch.arange(88.0)  # LSS bins [1, 45) m, 0.5 m wide


def _lidar_case():
    points = torch.tensor([
        [6.1, 0.0, 1.5],    # z-depth 5.1 → pixel (u=7, v=4), nearest centre 5.25 → bin 8
        [10.0, 0.0, 1.5],   # same pixel, farther: the nearest point wins
        [5.1, -0.41, 1.5],  # z-depth 4.1, u = 7 + 10 * 0.41 / 4.1 = 8 → pixel (8, 4), bin 6
        [60.0, 0.0, 1.5],   # beyond the last bin: no target
        [-5.2, 0.0, 1.5],   # behind the front camera; 4.2 m in front of the rear one: pixel (7, 4), bin 6
    ])
    k = K_FEAT.expand(1, 2, 3, 3)
    cam2ego = torch.stack([FRONT, REAR])[None]
    return k, cam2ego, [points]


def test_lidar_depth_targets_land_in_the_right_bin_and_pixel():
    k, cam2ego, points = _lidar_case()
    target = lidar_depth_targets(k, cam2ego, points, (10, 16), CENTERS)
    assert target.shape == (1, 2, 10, 16)
    hits = {(int(c), int(v), int(u)): int(target[0, c, v, u]) for c, v, u in torch.nonzero(target[0] >= 0)}
    assert hits == {(0, 4, 7): 8, (0, 4, 8): 6, (1, 4, 7): 6}


def test_lidar_depth_loss_equals_hand_computed_bce():
    k, cam2ego, points = _lidar_case()
    d = CENTERS.numel()
    prob = torch.full((1, 2, d, 10, 16), 1.0 / d, requires_grad=True)
    loss = lidar_depth_loss(prob, k, cam2ego, points, CENTERS)
    per_pixel = -(math.log(1.0 / d) + (d - 1) * math.log(1.0 - 1.0 / d))
    assert loss.item() == pytest.approx(per_pixel, rel=1e-5)
    loss.backward()
    assert torch.count_nonzero(prob.grad.sum(2)) == 3  # only the three target pixels get a gradient
    none = lidar_depth_loss(prob, k, cam2ego, [torch.zeros(0, 3)], CENTERS)
    assert none.item() == 0


def test_voxel_losses_by_hand_with_mask():
    density = torch.tensor([0.8, 0.3]).view(1, 2, 1, 1)
    logits = torch.zeros(1, 2, 1, 1, NUM_CLASSES)
    gt = torch.tensor([4, 17], dtype=torch.uint8).view(1, 2, 1, 1)
    terms = voxel_losses(density, logits, gt)
    assert terms["voxel_density"].item() == pytest.approx(-(math.log(0.8) + math.log(0.7)) / 2, rel=1e-6)
    assert terms["voxel_semantics"].item() == pytest.approx(LOG17, rel=1e-6)
    mask = torch.tensor([False, True]).view(1, 2, 1, 1)
    masked = voxel_losses(density, logits, gt, mask)
    assert masked["voxel_density"].item() == pytest.approx(-math.log(0.7), rel=1e-6)
    assert masked["voxel_semantics"].item() == 0
    scaled = voxel_losses(density, logits, gt, cfg=LossConfig(voxel_density_weight=2.0, voxel_semantic_weight=0.5))
    assert scaled["voxel_density"].item() == pytest.approx(2 * terms["voxel_density"].item())
    with pytest.raises(ValueError, match="semantics_gt"):
        voxel_losses(density, logits, torch.full((1, 2, 1, 1), 18))


def test_total_loss_modes():
    r = _rendered()
    k, cam2ego, points = _lidar_case()
    prob = torch.full((1, 2, 88, 10, 16), 1.0 / 88)
    vox = dict(density=torch.tensor([0.8, 0.3]).view(1, 2, 1, 1), logits=torch.zeros(1, 2, 1, 1, NUM_CLASSES),
               semantics_gt=torch.tensor([4, 17]).view(1, 2, 1, 1))
    ray = dict(rendered=r, depth_gt=torch.tensor([2.0, 3.0]), labels_gt=torch.tensor([0, 1]))
    lidar = dict(depth_prob=prob, feature_intrinsics=k, cam2ego=cam2ego, points_ego=points, depth_bin_centers=CENTERS)
    both = total_loss(LossConfig(mode="2d+3d"), **ray, **vox, **lidar)
    assert set(both) == {"render_depth", "render_semantics", "voxel_density", "voxel_semantics", "lidar_depth", "total"}
    assert both["total"].item() == pytest.approx(sum(v.item() for n, v in both.items() if n != "total"))
    assert set(total_loss(LossConfig(mode="3d"), **vox)) == {"voxel_density", "voxel_semantics", "total"}
    assert set(total_loss(LossConfig(lidar_depth_weight=0.0), **ray, **lidar)) == {
        "render_depth", "render_semantics", "total"}
    with pytest.raises(ValueError, match="needs depth_gt"):
        total_loss(LossConfig(mode="2d"), rendered=r, labels_gt=torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="needs density"):
        total_loss(LossConfig(mode="2d+3d"), **ray)
    with pytest.raises(ValueError, match="mode"):
        LossConfig(mode="4d")
    assert np.isfinite(both["total"].item())


def test_free_space_loss_is_zero_for_transparent_beams_and_grows_with_opacity():
    from occflownet.train.losses import LossConfig, free_space_loss, total_loss

    assert float(free_space_loss(torch.zeros(5))) == 0.0
    half = float(free_space_loss(torch.full((4,), 0.5)))
    assert abs(half - np.log(2.0)) < 1e-6
    assert float(free_space_loss(torch.ones(3))) == pytest.approx(-np.log(1e-4), rel=1e-3)  # clamped, finite
    assert float(free_space_loss(torch.zeros(0))) == 0.0
    opacity = torch.full((4,), 0.5, requires_grad=True)
    terms = total_loss(LossConfig(mode="3d", free_space_weight=2.0, lidar_depth_weight=0.0),
                       density=torch.zeros(1, 200, 200, 16), logits=torch.zeros(1, 200, 200, 16, 17),
                       semantics_gt=torch.full((1, 200, 200, 16), 17, dtype=torch.uint8), free_opacity=opacity)
    assert float(terms["free_space"].detach()) == pytest.approx(2 * np.log(2.0), rel=1e-6)
    terms["total"].backward()
    assert torch.all(opacity.grad > 0)


def test_normalized_render_semantics_ignores_how_much_light_stops():
    # the raw mixture Σ w_i s_i of a half-transparent ray has logits scaled by 0.5: its CE is higher than the one
    # of the same logits at full opacity; normalized, both are the CE of the logits themselves
    logits = torch.zeros(1, NUM_CLASSES)
    logits[0, 3] = 4.0
    labels = torch.tensor([3])
    ce = float(torch.nn.functional.cross_entropy(logits, labels))
    for opacity in (0.5, 1.0):
        rendered = SimpleNamespace(depth=torch.tensor([2.0]), semantics=opacity * logits,
                                   weight_sum=torch.tensor([opacity]))
        raw = ray_losses(rendered, torch.tensor([2.0]), labels, cfg=LossConfig())["render_semantics"]
        norm = ray_losses(rendered, torch.tensor([2.0]), labels,
                          cfg=LossConfig(render_semantics="normalized"))["render_semantics"]
        assert float(norm) == pytest.approx(ce, rel=1e-5)
        assert (float(raw) > ce + 0.1) == (opacity < 1.0)
    with pytest.raises(ValueError, match="render_semantics"):
        LossConfig(render_semantics="softmax")


def test_free_prior_charges_every_voxel_by_its_opacity():
    from occflownet.train.losses import free_prior_loss

    density = torch.zeros(1, 2, 2, 2)
    assert float(free_prior_loss(density)) == 0.0
    density[0, 0, 0, 0] = 0.5
    assert float(free_prior_loss(density)) == pytest.approx(np.log(2.0) / 8, rel=1e-6)
    vox = dict(density=density, logits=torch.zeros(1, 2, 2, 2, NUM_CLASSES),
               semantics_gt=torch.full((1, 2, 2, 2), 17, dtype=torch.uint8))
    cfg = LossConfig(mode="3d", free_prior_weight=0.1)
    with pytest.raises(ValueError, match="prior_density"):
        total_loss(cfg, **vox)
    prior = density.clone().requires_grad_()
    terms = total_loss(cfg, **vox, prior_density=prior)
    assert float(terms["free_prior"]) == pytest.approx(0.1 * np.log(2.0) / 8, rel=1e-6)
    terms["free_prior"].backward()
    assert float(prior.grad[0, 0, 0, 0]) > float(prior.grad[0, 1, 1, 1]) > 0
    assert "free_prior" not in total_loss(LossConfig(mode="3d"), **vox)
