"""Losses (occflownet.train.losses, train.step.LossComputer): hand-computed values, LiDAR depth targets, the terms
chosen from the configuration and the inputs computed for them."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from occflownet.occ3d import NUM_CLASSES
from occflownet.train.losses import (LossTerm, free_prior_loss, free_space_loss, image_semantics_loss, lidar_depth_loss,
                                     lidar_depth_targets, loss_terms, nearest_points, point_density_loss, step_data,
                                     render_depth_loss, render_semantics_loss, voxel_density_loss, voxel_scal_loss,
                                     voxel_semantics_loss, voxel_targets)
from occflownet.train.recipe import TrainConfig
from occflownet.train.recipes import recipe

LOG17 = math.log(NUM_CLASSES)


def _rendered():
    return SimpleNamespace(depth=torch.tensor([1.0, 3.0], requires_grad=True),
                           semantics=torch.zeros(2, NUM_CLASSES, requires_grad=True))


def _term(cfg: TrainConfig, name: str) -> LossTerm:
    return next(term for term in loss_terms(cfg) if term.name == name)


def test_render_losses_by_hand_with_and_without_class_weights():
    r = _rendered()
    gt, labels = torch.tensor([2.0, 3.0]), torch.tensor([0, 1])
    assert render_depth_loss(r, gt, labels).item() == pytest.approx(0.5)
    assert render_semantics_loss(r, labels).item() == pytest.approx(LOG17, rel=1e-6)
    omega = torch.ones(NUM_CLASSES)
    omega[0], omega[1] = 2.0, 0.5
    assert render_depth_loss(r, gt, labels, omega).item() == pytest.approx((2.0 * 1.0 + 0.5 * 0.0) / 2)
    assert render_semantics_loss(r, labels, omega).item() == pytest.approx(1.25 * LOG17, rel=1e-6)
    inputs = {"rendered": r, "ray_depths": gt, "ray_labels": labels, "class_weights": omega}
    depth = _term(TrainConfig(), "render_depth")
    assert depth.weight == 0.05 and depth.needs == ("rendered", "ray_depths", "ray_labels", "class_weights")
    assert depth(inputs).item() == pytest.approx(0.05 * 1.0)
    assert _term(TrainConfig(), "render_semantics")(inputs).item() == pytest.approx(1.25 * LOG17, rel=1e-6)
    depth(inputs).backward()
    assert r.depth.grad[0].item() == pytest.approx(0.05 * 2.0 * 2 * (1.0 - 2.0) / 2)
    assert _term(TrainConfig(render_depth_weight=0.2), "render_depth")(inputs).item() == pytest.approx(0.2)


def test_lidar_depth_weight_is_the_terms_weight():
    assert _term(TrainConfig(), "lidar_depth").weight == 0.05                       # official
    assert _term(TrainConfig(supervision="3d", lidar_depth_weight=1.5), "lidar_depth").weight == 1.5
    assert "lidar_depth" not in [t.name for t in loss_terms(TrainConfig(depth_loss=False))]
    with pytest.raises(ValueError, match="lidar_depth_weight"):
        TrainConfig(lidar_depth_weight=-1.0)


def test_render_losses_reject_bad_labels_and_handle_no_rays():
    r = _rendered()
    with pytest.raises(ValueError, match="labels_gt"):
        render_semantics_loss(r, torch.tensor([0, 17]))
    with pytest.raises(ValueError, match="depth_gt"):
        render_depth_loss(r, torch.tensor([2.0]), torch.tensor([0, 1]))
    empty = SimpleNamespace(depth=torch.zeros(0), semantics=torch.zeros(0, NUM_CLASSES), weight_sum=torch.zeros(0))
    none = torch.zeros(0, dtype=torch.long)
    assert render_depth_loss(empty, torch.zeros(0), none).item() == 0
    assert render_semantics_loss(empty, none).item() == 0


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


def test_image_semantics_targets_take_the_nearest_points_label():
    k, cam2ego, points = _lidar_case()
    labels = [torch.tensor([3, 5, 9, 4, 1], dtype=torch.uint8)]
    depth, label = nearest_points(k, cam2ego, points, (10, 16), labels)
    label = label.view(1, 2, 10, 16)
    hits = {(int(c), int(v), int(u)): int(label[0, c, v, u]) for c, v, u in torch.nonzero(label[0] >= 0)}
    # the 60 m point lands in pixel (0, 4, 7) too, behind the 5.1 m one: no bin, but no class of its own either
    assert hits == {(0, 4, 7): 3, (0, 4, 8): 9, (1, 4, 7): 1}
    assert depth.view(1, 2, 10, 16)[0, 0, 4, 7].item() == pytest.approx(5.1)
    tie = [torch.cat([points[0][:1], points[0][:1]])]                # two points at one depth: the smaller label
    _, label = nearest_points(k, cam2ego, tie, (10, 16), [torch.tensor([7, 2])])
    assert sorted(label[label >= 0].tolist()) == [2]
    with pytest.raises(ValueError, match="labels"):
        nearest_points(k, cam2ego, points, (10, 16), [torch.zeros(4)])


def test_image_semantics_loss_equals_hand_computed_ce():
    k, cam2ego, points = _lidar_case()
    labels = [torch.tensor([3, 5, 9, 4, 1])]
    logits = torch.zeros(1, 2, NUM_CLASSES, 10, 16, requires_grad=True)
    loss = image_semantics_loss(logits, k, cam2ego, points, labels)
    assert loss.item() == pytest.approx(LOG17, rel=1e-6)
    loss.backward()
    assert torch.count_nonzero(logits.grad.abs().sum(2)) == 3    # only the three pixels with a point
    assert logits.grad[0, 0, 3, 4, 7].item() == pytest.approx((1 / NUM_CLASSES - 1) / 3, rel=1e-5)
    right = torch.zeros(1, 2, NUM_CLASSES, 10, 16)
    right[0, 0, 3, 4, 7] = right[0, 0, 9, 4, 8] = right[0, 1, 1, 4, 7] = 30.0
    assert image_semantics_loss(right, k, cam2ego, points, labels).item() < 1e-10
    none = image_semantics_loss(logits, k, cam2ego, [torch.zeros(0, 3)], [torch.zeros(0)])
    assert none.item() == 0
    with pytest.raises(ValueError, match="image_logits"):
        image_semantics_loss(logits[:, :, :5], k, cam2ego, points, labels)


def test_image_semantics_term_is_off_by_default_and_weighted():
    assert "image_semantics" not in [t.name for t in loss_terms(TrainConfig())]
    term = _term(TrainConfig(image_semantics_weight=0.5), "image_semantics")
    assert term.weight == 0.5 and term.needs[0] == "image_logits" and "depth_labels" in term.needs
    with pytest.raises(ValueError, match="image_semantics_weight"):
        TrainConfig(image_semantics_weight=-1.0)


def test_voxel_losses_by_hand_with_mask():
    density = torch.tensor([0.8, 0.3])
    logits = torch.zeros(2, NUM_CLASSES)
    gt = torch.tensor([4, 17], dtype=torch.uint8).view(2, 1, 1)
    every = voxel_targets(gt)                                    # every voxel kept (the official 3D training)
    assert "voxel_rows" not in every and every["voxel_occupied"].tolist() == [1.0, 0.0]
    assert every["occupied_rows"].tolist() == [0] and every["occupied_labels"].tolist() == [4]
    assert voxel_density_loss(density, every["voxel_occupied"]).item() == pytest.approx(
        -(math.log(0.8) + math.log(0.7)) / 2, rel=1e-6)
    assert voxel_semantics_loss(logits[every["occupied_rows"]], every["occupied_labels"]).item() == \
        pytest.approx(LOG17, rel=1e-6)
    mask = torch.tensor([False, True]).view(2, 1, 1)
    masked = voxel_targets(gt, mask)                             # --voxel-mask: only the second voxel is kept
    assert masked["voxel_rows"].tolist() == [1] and masked["voxel_occupied"].tolist() == [0.0]
    assert masked["occupied_rows"].numel() == 0 and masked["occupied_labels"].numel() == 0
    assert voxel_density_loss(density[masked["voxel_rows"]], masked["voxel_occupied"]).item() == \
        pytest.approx(-math.log(0.7), rel=1e-6)
    assert voxel_semantics_loss(logits[masked["occupied_rows"]], masked["occupied_labels"]).item() == 0
    with pytest.raises(ValueError, match="semantics_gt"):
        voxel_targets(torch.full((2, 1, 1), 18))
    with pytest.raises(ValueError, match="mask"):
        voxel_targets(gt, mask.view(1, 2, 1))
    with pytest.raises(ValueError, match="logits"):
        voxel_semantics_loss(logits[:, :3], every["occupied_labels"])
    # the terms read σ and the logits at the supervised voxels, and their targets
    assert _term(TrainConfig(supervision="3d"), "voxel_density").needs == ("voxel_sigma", "voxel_occupied")
    assert _term(TrainConfig(supervision="3d", voxel_mask=True), "voxel_semantics").needs == \
        ("occupied_logits", "occupied_labels")


@pytest.mark.parametrize("overrides, names", [
    ({}, ["render_depth", "render_semantics", "lidar_depth"]),
    ({"supervision": "3d"}, ["voxel_density", "voxel_semantics", "lidar_depth"]),
    ({"supervision": "3d", "depth_loss": False}, ["voxel_density", "voxel_semantics"]),
    ({"supervision": "2d+3d", "free_space": True, "free_before_point": True, "free_prior_weight": 0.1},
     ["render_depth", "render_semantics", "voxel_density", "voxel_semantics", "lidar_depth", "free_space",
      "free_before", "free_prior"]),
    ({"free_beyond_grid": True, "free_before_point": True, "free_space_weight": 0.0},
     ["render_depth", "render_semantics", "lidar_depth"]),
    ({"free_beyond_grid": True, "depth_loss": False}, ["render_depth", "render_semantics", "free_space"]),
    ({"point_semantics_weight": 0.5}, ["render_depth", "render_semantics", "point_semantics", "lidar_depth"]),
])
def test_the_terms_are_chosen_from_the_configuration(overrides, names):
    terms = loss_terms(TrainConfig(**overrides))
    assert [t.name for t in terms] == names
    weights = {t.name: t.weight for t in terms}
    expected = {"render_depth": 0.05 if overrides.get("depth_loss", True) else 0.0, "render_semantics": 1.0,
                "voxel_density": 1.0, "voxel_semantics": 1.0, "lidar_depth": 0.05, "free_space": 1.0,
                "free_before": 1.0, "free_prior": 0.1, "point_semantics": 0.5}
    assert weights == {name: expected[name] for name in names}


def test_free_space_loss_is_zero_for_transparent_beams_and_grows_with_opacity():
    assert float(free_space_loss(torch.zeros(5))) == 0.0
    half = float(free_space_loss(torch.full((4,), 0.5)))
    assert abs(half - np.log(2.0)) < 1e-6
    assert float(free_space_loss(torch.ones(3))) == pytest.approx(-np.log(1e-4), rel=1e-3)  # clamped, finite
    assert float(free_space_loss(torch.zeros(0))) == 0.0
    opacity = torch.full((4,), 0.5, requires_grad=True)
    cfg = TrainConfig(free_space=True, free_before_point=True, free_space_weight=2.0)
    term = _term(cfg, "free_space")
    before = _term(cfg, "free_before")
    assert term.needs == ("free_opacity",) and before.needs == ("before_opacity",) and before.weight == 2.0
    value = term({"free_opacity": opacity})
    assert float(value.detach()) == pytest.approx(2 * np.log(2.0), rel=1e-6)
    value.backward()
    assert torch.all(opacity.grad > 0)


def test_free_prior_charges_every_voxel_by_its_opacity():
    density = torch.zeros(1, 2, 2, 2)
    assert float(free_prior_loss(density)) == 0.0
    density[0, 0, 0, 0] = 0.5
    assert float(free_prior_loss(density)) == pytest.approx(np.log(2.0) / 8, rel=1e-6)
    term = _term(TrainConfig(supervision="3d", free_prior_weight=0.1), "free_prior")
    prior = density.clone().requires_grad_()
    value = term({"density": prior})
    assert term.needs == ("density",) and float(value.detach()) == pytest.approx(0.1 * np.log(2.0) / 8, rel=1e-6)
    value.backward()
    assert float(prior.grad[0, 0, 0, 0]) > float(prior.grad[0, 1, 1, 1]) > 0
    assert "free_prior" not in [t.name for t in loss_terms(TrainConfig(supervision="3d"))]


def test_free_terms_ramp_in_linearly_over_free_ramp_steps():
    """--free-ramp-steps N: the free terms weigh step / N of their weight until step N, then all of it; the other
    terms are not ramped; without a step (analysis calls) every term has its full weight."""
    terms = {t.name: t for t in loss_terms(TrainConfig(free_beyond_grid=True, free_before_point=True,
                                                       free_ramp_steps=400, free_space_weight=0.5))}
    opacity = torch.tensor([1 - math.exp(-1.0)])                # −log(1 − opacity) = 1
    inputs = {"free_opacity": opacity, "before_opacity": opacity}
    for name in ("free_space", "free_before"):
        assert [float(terms[name](inputs, s)) for s in (0, 100, 400, 1000)] == pytest.approx([0, 0.125, 0.5, 0.5])
        assert float(terms[name](inputs)) == pytest.approx(0.5)
    assert terms["render_semantics"].ramp(0) == terms["render_depth"].ramp(0) == 1.0
    with pytest.raises(ValueError, match="free_ramp_steps"):
        TrainConfig(free_ramp_steps=-1)


def _computer(**overrides):
    from occflownet.model.presets import get_preset
    from occflownet.train.step import LossComputer

    return LossComputer(TrainConfig(**overrides), get_preset("tiny"), None)


def test_the_loss_computer_computes_only_the_inputs_its_terms_need():
    # 3D without depth loss: no ray in the batch, no depth distribution in the outputs, and nothing is rendered
    losses = _computer(supervision="3d", depth_loss=False, free_prior_weight=0.1)
    density = torch.tensor([0.8, 0.3]).view(1, 2, 1, 1)
    outputs = {"density": density, "logits": torch.zeros(1, 2, 1, 1, NUM_CLASSES)}
    batch = voxel_targets(torch.tensor([4, 17], dtype=torch.uint8).view(2, 1, 1))
    assert losses.needs == {"density", "voxel_sigma", "voxel_occupied", "occupied_logits", "occupied_labels"}
    assert not losses.heads_at_rows and losses.head_rows(batch, torch.device("cpu")) == {}  # the prior reads all
    assert not set(losses.inputs(outputs, batch, torch.device("cpu"))) & {"rendered", "free_opacity", "depth_prob"}
    terms = {k: float(v) for k, v in losses(outputs, batch, torch.device("cpu")).items()}
    bce = -(math.log(0.8) + math.log(0.7)) / 2
    prior = 0.1 * -(math.log(0.2) + math.log(0.7)) / 2
    assert terms == pytest.approx({"voxel_density": bce, "voxel_semantics": LOG17, "free_prior": prior,
                                   "loss": bce + LOG17 + prior}, rel=1e-6)
    lacking = r"\['voxel_semantics'\] need the batch fields \['occupied_labels'\]"
    with pytest.raises(ValueError, match=lacking):
        losses(outputs, {k: v for k, v in batch.items() if k != "occupied_labels"}, torch.device("cpu"))


def test_3d_labels_alone_run_the_heads_on_the_supervised_voxels_only():
    """Without rendering or prior, the loss computer asks the model for σ at the kept voxels and the logits at the
    kept occupied ones (head_rows), and takes the outputs at those rows as they come: the same terms as picking
    them from the whole grid."""
    losses = _computer(supervision="3d", depth_loss=False, voxel_mask=True)
    cpu = torch.device("cpu")
    g = torch.Generator().manual_seed(0)
    semantics = torch.randint(0, 18, (2, 3, 4, 5), generator=g, dtype=torch.uint8)
    mask = torch.rand(2, 3, 4, 5, generator=g) > 0.4
    per_sample = [voxel_targets(semantics[b], mask[b]) for b in range(2)]
    batch = {"voxel_rows": torch.cat([t["voxel_rows"] + 60 * b for b, t in enumerate(per_sample)]),
             "occupied_rows": torch.cat([t["occupied_rows"] + 60 * b for b, t in enumerate(per_sample)]),
             "voxel_occupied": torch.cat([t["voxel_occupied"] for t in per_sample]),
             "occupied_labels": torch.cat([t["occupied_labels"] for t in per_sample])}
    assert losses.heads_at_rows
    rows = losses.head_rows(batch, cpu)
    assert torch.equal(rows["density_at"], batch["voxel_rows"]) and torch.equal(rows["logits_at"],
                                                                                   batch["occupied_rows"])
    density = torch.rand(2, 3, 4, 5, generator=g)
    logits = torch.randn(2, 3, 4, 5, NUM_CLASSES, generator=g)
    whole = losses({"density": density, "logits": logits}, batch, cpu)
    at_rows = losses({"density": density.reshape(-1)[rows["density_at"]],
                      "logits": logits.reshape(-1, NUM_CLASSES)[rows["logits_at"]]}, batch, cpu)
    occupied = semantics != 17
    expected = {"voxel_density": torch.nn.functional.binary_cross_entropy(density[mask], occupied[mask].float()),
                "voxel_semantics": torch.nn.functional.cross_entropy(logits[mask & occupied],
                                                                      semantics[mask & occupied].long())}
    for terms in (whole, at_rows):
        for name, value in expected.items():
            assert float(terms[name]) == pytest.approx(float(value), rel=1e-6)


def test_scene_class_affinity_by_hand():
    """voxel_scal_loss (MonoScene's geo_scal + sem_scal) on four voxels, two of class 0 and two free, σ = 0.5 and
    uniform logits (p_c = σ / 17): occupancy precision, recall and specificity 1/2 each; class 0's precision 1/2,
    recall 1/34, specificity 33/34. A perfect grid scores ~0; no voxel gives 0 with a graph."""
    classes = torch.tensor([0, 0, 17, 17], dtype=torch.uint8)
    sigma = torch.full((4,), 0.5, requires_grad=True)
    logits = torch.zeros(4, NUM_CLASSES, requires_grad=True)
    loss = voxel_scal_loss(sigma, logits, classes)
    expected = 3 * math.log(2) + math.log(2) + math.log(34) + math.log(34 / 33)
    assert loss.item() == pytest.approx(expected, rel=1e-6)
    loss.backward()
    assert sigma.grad[:2].lt(0).all() and sigma.grad[2:].gt(0).all()    # raise σ where occupied, lower it where free
    assert logits.grad[:2, 0].lt(0).all()                                  # and class 0's logit where it is labelled
    perfect = voxel_scal_loss(torch.tensor([1.0, 1.0, 0.0, 0.0]), torch.eye(NUM_CLASSES)[[0, 0, 1, 1]] * 50, classes)
    assert perfect.item() == pytest.approx(0.0, abs=1e-5)
    empty = voxel_scal_loss(torch.zeros(0, requires_grad=True), torch.zeros(0, NUM_CLASSES), torch.zeros(0))
    assert empty.item() == 0 and empty.requires_grad
    with pytest.raises(ValueError, match="logits"):
        voxel_scal_loss(sigma, logits[:, :3], classes)
    masked = voxel_targets(torch.tensor([4, 17, 2], dtype=torch.uint8).view(3, 1, 1),
                           torch.tensor([True, False, True]).view(3, 1, 1))
    assert masked["voxel_classes"].tolist() == [4, 2]                      # the kept voxels' classes, free = 17
    assert [t.name for t in loss_terms(TrainConfig(supervision="3d", voxel_scal_weight=0.5))] == \
        ["voxel_density", "voxel_semantics", "voxel_scal", "lidar_depth"]
    assert not [t for t in loss_terms(TrainConfig(voxel_scal_weight=0.5)) if t.name == "voxel_scal"]  # 3D labels only


def test_3d_labels_alone_with_the_affinity_terms_run_the_logits_on_every_kept_voxel():
    """With voxel_scal the semantic head runs on every kept voxel (the class terms read them all) and the occupied
    voxels' logits are taken from those rows: the same terms as from the whole grid."""
    losses = _computer(supervision="3d", depth_loss=False, voxel_mask=True, voxel_scal_weight=0.5)
    cpu = torch.device("cpu")
    g = torch.Generator().manual_seed(1)
    semantics = torch.randint(0, 18, (2, 3, 4, 5), generator=g, dtype=torch.uint8)
    mask = torch.rand(2, 3, 4, 5, generator=g) > 0.4
    per_sample = [voxel_targets(semantics[b], mask[b]) for b in range(2)]
    batch = {key: torch.cat([t[key] + (60 * b if key.endswith("rows") else 0) for b, t in enumerate(per_sample)])
             for key in ("voxel_rows", "occupied_rows", "voxel_occupied", "voxel_classes", "occupied_labels")}
    rows = losses.head_rows(batch, cpu)
    assert losses.heads_at_rows and torch.equal(rows["logits_at"], batch["voxel_rows"])
    density = torch.rand(2, 3, 4, 5, generator=g)
    logits = torch.randn(2, 3, 4, 5, NUM_CLASSES, generator=g)
    whole = losses({"density": density, "logits": logits}, batch, cpu)
    at_rows = losses({"density": density.reshape(-1)[rows["density_at"]],
                      "logits": logits.reshape(-1, NUM_CLASSES)[rows["logits_at"]]}, batch, cpu)
    expected = 0.5 * voxel_scal_loss(density[mask], logits[mask], semantics[mask])
    for terms in (whole, at_rows):
        assert float(terms["voxel_scal"]) == pytest.approx(float(expected), rel=1e-6)
        assert float(terms["voxel_semantics"]) == pytest.approx(float(whole["voxel_semantics"]), rel=1e-6)


def _ray_batch() -> dict:
    """One sample, two rays from (0, 0, 1) along +x (10 m) and +y (20 m), one free ray along -x; one volume."""
    from occflownet.data.free_stretch import free_segment_ends

    origins = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    return {"images": torch.zeros(1, 6, 2, 2, 3, dtype=torch.uint8), "cam2ego": torch.eye(4).expand(1, 6, 4, 4),
            "ray_origins": origins, "ray_directions": torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
            "ray_depths": torch.tensor([10.0, 20.0]), "ray_labels": torch.tensor([0, 1]),
            "ray_free_ends": free_segment_ends(torch.tensor([10.0, 20.0])),    # the fraction rule, as the dataset's
            "ray_volume": torch.zeros(2, dtype=torch.long), "volume_source": torch.zeros(1, dtype=torch.long),
            "volume_is_temporal": torch.zeros(1, dtype=torch.bool), "depth_points": [torch.zeros(0, 3)],
            "free_origins": origins[:1], "free_directions": torch.tensor([[-1.0, 0.0, 0.0]]),
            "free_volume": torch.zeros(1, dtype=torch.long)}


def test_free_rays_leave_out_the_masked_voxels_when_the_batch_has_masks():
    """With ``free_stretch="points"`` the dataset gives each free ray a mask of its frame ("free_masks", "free_slot",
    "slot_volume"): the free ray along -x renders through σ = 0.05 /m except where its mask is set. Masking
    -20 m ≤ x < 0 leaves the optical depth 0.05 · 19.6 (-20 to -40 m; trilinear σ fades over half a voxel at the
    mask's edge and at the grid's); the unmasked ray of the same batch still sees 40 m of it."""
    from occflownet.occ3d import GRID

    losses = _computer(free_space=True, free_rays_per_step=2, horizon=0)
    d = losses.depth_bins.numel()
    outputs = {"density": torch.full((1, *GRID.shape), 0.05), "logits": torch.zeros(1, *GRID.shape, NUM_CLASSES),
               "depth_prob": torch.full((1, 6, d, 2, 2), 1.0 / d),
               "feature_intrinsics": torch.eye(3).expand(1, 6, 3, 3)}
    batch = _ray_batch()
    for key in ("free_origins", "free_directions", "free_volume"):
        batch[key] = torch.cat([batch[key], batch[key]])
    masks = torch.zeros(2, *GRID.shape, dtype=torch.bool)
    masks[0, 50:100] = True                                              # -20 m <= x < 0
    batch.update(free_masks=masks, free_slot=torch.tensor([0, 1]), slot_volume=torch.tensor([0, 0]))
    opacity = losses.inputs(outputs, batch, torch.device("cpu"), torch.Generator().manual_seed(0))["free_opacity"]
    optical = -torch.log1p(-opacity)
    assert float(optical[0]) == pytest.approx(0.05 * 19.6, rel=0.02)
    assert float(optical[1]) == pytest.approx(0.05 * (40.0 - 0.05), rel=3e-3)


@pytest.mark.parametrize("sigma", [0.0, 0.05])
def test_the_loss_computer_renders_the_rays_of_its_terms(sigma):
    from occflownet.occ3d import GRID

    losses = _computer(free_space=True, free_before_point=True, free_rays_per_step=2, horizon=0)
    d = losses.depth_bins.numel()
    outputs = {"density": torch.full((1, *GRID.shape), sigma), "logits": torch.zeros(1, *GRID.shape, NUM_CLASSES),
               "depth_prob": torch.full((1, 6, d, 2, 2), 1.0 / d),
               "feature_intrinsics": torch.eye(3).expand(1, 6, 3, 3)}
    terms = {k: float(v) for k, v in losses(outputs, _ray_batch(), torch.device("cpu"),
                                              torch.Generator().manual_seed(0)).items()}
    assert list(terms) == ["render_depth", "render_semantics", "lidar_depth", "free_space", "free_before", "loss"]
    assert terms["lidar_depth"] == 0 and terms["render_semantics"] == pytest.approx(LOG17, rel=1e-5)
    assert terms["loss"] == pytest.approx(sum(v for k, v in terms.items() if k != "loss"), rel=1e-6)
    if sigma == 0:  # transparent: depth 0 (0.05 · mean d²), nothing stops the free rays
        assert terms["render_depth"] == pytest.approx(0.05 * (10.0 ** 2 + 20.0 ** 2) / 2)
        assert terms["free_space"] == 0 and terms["free_before"] == 0
    else:  # σ = 0.05 /m: -log(1 - opacity) is the optical depth 0.05 · length from near = 0.05 m (trilinear σ fades
        # over the last half voxel before the grid's edge at 40 m)
        assert terms["free_space"] == pytest.approx(0.05 * (40.0 - 0.05), rel=3e-3)
        stretches = [0.05 * (0.8 * depth - 0.6 - 0.05) for depth in (10.0, 20.0)]     # to 0.8 · depth - 0.6 m
        assert terms["free_before"] == pytest.approx(np.mean(stretches), rel=3e-3)


def test_point_semantics_reads_the_voxel_that_holds_each_point():
    """--point-semantics-weight: the CE of the logits of the voxel holding each ray's point, in the logits volume of
    the ray's frame; points outside the grid are left out. Rays from (0, 0, 1): +x 10 m → voxel (125, 100, 5),
    +y 20 m → (100, 150, 5), -x 50 m → outside. Logits: 5 for class 0 at the first voxel (label 0), 5 for class 3 at
    the second (label 1), 0 elsewhere."""
    from occflownet.occ3d import GRID
    from occflownet.train.step import FrameVolumes

    losses = _computer(point_semantics_weight=0.5, depth_loss=False, horizon=0)
    assert "point_logits" in losses.needs and "point_semantics" in [t.name for t in losses.terms]
    logits = torch.zeros(1, *GRID.shape, NUM_CLASSES)
    logits[0, 125, 100, 5, 0] = 5.0
    logits[0, 100, 150, 5, 3] = 5.0
    batch = _ray_batch()
    batch.update(ray_origins=torch.tensor([[0.0, 0.0, 1.0]] * 3),
                 ray_directions=torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
                 ray_depths=torch.tensor([10.0, 20.0, 50.0]), ray_labels=torch.tensor([0, 1, 2]),
                 ray_volume=torch.zeros(3, dtype=torch.long))
    cpu = torch.device("cpu")
    # two frame volumes reading one logits volume: the rays of frame 1 read it too
    volumes = FrameVolumes(torch.zeros(2, *GRID.shape), logits, logits_index=torch.tensor([0, 0]))
    volumes.density[1, 125, 100, 5] = 0.25
    picked = losses.point_values(volumes, {**batch, "ray_volume": torch.tensor([1, 0, 1])}, cpu)
    assert picked["point_labels"].tolist() == [0, 1] and picked["point_sigma"].tolist() == [0.25, 0.0]
    logits_at = picked["point_logits"]
    assert logits_at[0, 0] == 5.0 and logits_at[1, 3] == 5.0 and logits_at.sum() == 10.0
    terms = losses({"density": torch.zeros(1, *GRID.shape), "logits": logits}, batch, cpu,
                   torch.Generator().manual_seed(0))
    expected = 0.5 * (-math.log(math.exp(5) / (math.exp(5) + 16)) - math.log(1 / (math.exp(5) + 16))) / 2
    assert float(terms["point_semantics"]) == pytest.approx(expected, rel=1e-5)
    # with 3D labels the point term still loads the rays it reads (the table of the data each input needs)
    assert "rays" in step_data(loss_terms(TrainConfig(point_semantics_weight=0.5, supervision="3d")))
    assert "rays" not in step_data(loss_terms(TrainConfig(supervision="3d")))


def test_point_density_asks_the_voxel_of_each_point_to_be_occupied():
    """--point-density-weight: -log σ of the voxel holding each in-grid point (rays as in the test above; σ 0.5 at
    the first point's voxel, 0.1 elsewhere), so a fully dense voxel costs nothing."""
    from occflownet.occ3d import GRID

    losses = _computer(point_density_weight=2.0, depth_loss=False, horizon=0)
    assert [t.name for t in losses.terms] == ["render_depth", "render_semantics", "point_density"]
    density = torch.full((1, *GRID.shape), 0.1)
    density[0, 125, 100, 5] = 0.5
    batch = {**_ray_batch(), "ray_origins": torch.tensor([[0.0, 0.0, 1.0]] * 3),
             "ray_directions": torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
             "ray_depths": torch.tensor([10.0, 20.0, 50.0]), "ray_labels": torch.tensor([0, 1, 2]),
             "ray_volume": torch.zeros(3, dtype=torch.long)}
    terms = losses({"density": density, "logits": torch.zeros(1, *GRID.shape, NUM_CLASSES)}, batch,
                   torch.device("cpu"), torch.Generator().manual_seed(0))
    assert float(terms["point_density"]) == pytest.approx(2.0 * -(math.log(0.5) + math.log(0.1)) / 2, rel=1e-5)
    assert float(point_density_loss(torch.ones(3))) == 0.0


FOOTPRINT_OPTIONS = {   # the recommended rendering (docs/training.md; its free prior reads every σ)
    "free_beyond_grid": True, "free_before_point": True, "free_stretch": "points", "box_line_of_sight": True,
    "ray_sampling": "sqrt-balanced", "point_semantics_weight": 1.0, "point_density_weight": 1.0,
    "free_prior_weight": 2.0}


QUICKSTART_OPTIONS = dict(recipe("quickstart").settings)   # 3D labels in mask_camera, the frame's rays, the image term


@pytest.mark.parametrize("options", [{}, FOOTPRINT_OPTIONS, {"flow": True}, QUICKSTART_OPTIONS,
                                     {"supervision": "2d+3d", "flow": True},
                                     {"supervision": "2d+3d", "voxel_mask": True},
                                     {"supervision": "2d+3d", "voxel_mask": True, "voxel_scal_weight": 1.0},
                                     {"supervision": "2d+3d", "voxel_scal_weight": 1.0}],
                         ids=["2d-base", "recipe", "flow", "quickstart", "2d3d-flow", "2d3d-mask", "2d3d-scal",
                              "2d3d-scal-every-voxel"])
def test_heads_on_the_rays_footprint_give_the_whole_grids_loss_and_gradients(options, tmp_path):
    """A trained tiny checkpoint (occupied voxels of several classes, so disocclusion, the warp and the point terms
    see something), a real 2-sample batch of the 2D base (t in [-3, 3], dynamic filter, disocclusion), of the
    fitting recipe, of occupancy flow, of the quickstart (3D labels in mask_camera, the current frame's rays and the
    image term, whose head the checkpoint gets fresh) and of 3D labels on every voxel (with flow) or in mask_camera:
    with the heads run on the footprint (and the labelled voxels) only, the step computes the same terms and the same
    parameter gradients as with the heads on the whole grid; the footprint is a part of the grid."""
    from dataclasses import replace

    from exported_models import trained_tiny_checkpoint, workdir
    from occflownet.model import create_model, load_checkpoint
    from occflownet.train import loop
    from occflownet.train.step import LossComputer

    model, _, _ = load_checkpoint(trained_tiny_checkpoint())
    cfg = TrainConfig(preset="tiny", dataroot=str(workdir() / "trained-world"), split="all", out=str(tmp_path),
                      num_workers=0, max_steps=2, batch_size=2, **options)
    if cfg.image_semantics_weight > 0:      # the checkpoint has no image head: its weights and a fresh head
        headed = create_model(replace(model.cfg, image_semantics=True), seed=0)
        assert set(headed.load_state_dict(model.state_dict(), strict=False).missing_keys) == {
            "image_head.weight", "image_head.bias"}
        model = headed
    model.train()
    index, positions, flows = loop._training_data(cfg)
    batch = next(iter(loop._data_loader(cfg, index, positions, flows, 0, loop.ddp.DistInfo())))
    weights = loop._class_weights(cfg, index, torch.device("cpu"))
    results = []
    for footprint in (False, True):
        losses = LossComputer(cfg, model.cfg, weights, footprint=footprint)
        assert losses.heads_on_footprint == footprint
        step_batch = dict(batch)
        rows = losses.head_rows(step_batch, torch.device("cpu"))
        outputs = model(step_batch["images"], step_batch["intrinsics"], step_batch["cam2ego"], **rows)
        terms = losses(outputs, step_batch, torch.device("cpu"), torch.Generator().manual_seed(1), step=5)
        model.zero_grad()
        terms["loss"].backward()
        results.append((terms, [p.grad.clone() for p in model.parameters() if p.grad is not None]))
        if footprint and cfg.flow:       # the warp moves some of the predicted voxels
            assert sum(len(moves["voxels"]) for moves, _ in step_batch["flow"]) > 0
        if footprint:
            share = len(rows["logits_at"]) / (2 * 640_000)
            every_logit = cfg.voxel_scal_weight > 0 and not cfg.voxel_mask     # the affinity terms read them all
            assert share == 1.0 if every_logit else 0.05 < share < 0.8, share
            # the prior, and the 3D density term without a mask, read every σ
            everywhere = "free_prior_weight" in options or ("supervision" in options and not cfg.voxel_mask)
            assert (rows["density_at"] is None) == everywhere
            if "supervision" in options:                       # the labelled voxels are among the rows
                assert bool(torch.isin(step_batch["occupied_rows"], rows["logits_at"]).all())
                if not everywhere:
                    assert bool(torch.isin(step_batch["voxel_rows"], rows["density_at"]).all())
            occupied = (outputs["density"] >= model.cfg.threshold).float().mean()
            assert 0.001 < occupied < 0.5                       # a trained grid: some voxels occupied
    (dense, dense_grads), (rows_terms, row_grads) = results
    assert dense.keys() == rows_terms.keys()
    for name in dense:
        assert float(rows_terms[name].detach()) == pytest.approx(float(dense[name].detach()), rel=1e-5, abs=1e-7), name
    assert len(dense_grads) == len(row_grads)
    for a, b in zip(dense_grads, row_grads):
        torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-6)


def test_where_the_heads_run():
    """On the footprint wherever rays are rendered, with 3D labels too; on the labelled voxels with 3D labels alone;
    on the whole grid when the footprint is turned off (the tests' reference)."""
    from occflownet.model.presets import get_preset
    from occflownet.train.step import LossComputer

    assert _computer(supervision="2d").heads_on_footprint and _computer(supervision="2d", flow=True).heads_on_footprint
    assert _computer(supervision="2d", free_prior_weight=0.5).heads_on_footprint     # σ on the grid, logits not
    assert _computer(supervision="2d+3d", voxel_mask=True).heads_on_footprint
    labels_only = _computer(supervision="3d", voxel_mask=True, horizon=0)
    assert labels_only.heads_at_rows and not labels_only.heads_on_footprint
    whole = LossComputer(TrainConfig(supervision="2d+3d"), get_preset("tiny"), None, footprint=False)
    assert not whole.heads_on_footprint and whole.head_rows({}, torch.device("cpu")) == {}
