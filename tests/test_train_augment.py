"""BEV flip augmentation (occflownet.train.augment): a flip is its own inverse, and a flipped item is the same
scene in the mirrored frame — rays still end in voxels of their class, the lifting puts each pixel at the mirrored
place, the LiDAR depth targets and the box moves agree."""
import numpy as np
import pytest
import torch

from occflownet.occ3d import GRID, Grid
from occflownet.train.augment import BevFlip
from occflownet.train.dataset import TrainingSamples
from occflownet.train.recipe import TrainConfig

FLIPS = [BevFlip(True, False), BevFlip(False, True), BevFlip(True, True)]


def _items(root, flip: bool, image_aug: bool = False) -> TrainingSamples:
    """The training items of every keyframe of ``root`` with rays, depth points, 3D labels and box moves."""
    from occflownet.data.flow import flow_path, load_flow_records
    from occflownet.data.index import load_index

    index = load_index(root)
    config = TrainConfig(dataroot=str(root), supervision="2d+3d", flow=True, rays_per_step=3000, bev_flip=flip,
                         image_aug=image_aug)
    return TrainingSamples(root, index, index.split_positions("all"), config,
                           load_flow_records(flow_path(root, index.version)))


def _label_agreement(item) -> float:
    """Share of the t = 0 rays whose point (origin + depth · direction) lies in a voxel of their own label."""
    t0 = item["ray_volume"] == 0
    points = (item["ray_origins"] + item["ray_depths"][:, None] * item["ray_directions"])[t0].numpy()
    index = GRID.index_of(points)
    inside = np.all((index >= 0) & (index < np.asarray(GRID.shape)), axis=1)
    semantics = item["occ_semantics"].numpy()
    labels = semantics[tuple(index[inside].T)]
    return float(np.mean(labels == item["ray_labels"][t0].numpy()[inside]))


def test_a_flip_is_its_own_inverse(prepared_synth_root):
    root, _ = prepared_synth_root
    item = _items(root, False)[(2, 5)]
    for flip in FLIPS:
        back = flip.apply(flip.apply(item))
        # exact: a flip negates coordinates and permutes voxels (sign changes and copies round nothing)
        for key in ("cam2ego", "ray_origins", "ray_directions", "depth_points", "occ_semantics", "occ_mask"):
            assert torch.equal(back[key], item[key]), key
        np.testing.assert_array_equal(back["flow"]["voxels"], item["flow"]["voxels"])
        np.testing.assert_allclose(back["flow"]["transforms"], item["flow"]["transforms"], atol=1e-6)
    assert BevFlip().apply(item) is item


def test_the_free_rays_masks_follow_the_flip(prepared_synth_root):
    """With ``--free-stretch points`` the item holds the voxels near each frame's LiDAR points ("free_masks" [T, X, Y,
    Z]); flipped, they are still near the (flipped) points of the t = 0 rays, and a flip is its own inverse."""
    from occflownet.data.index import load_index

    root, _ = prepared_synth_root
    index = load_index(root)
    config = TrainConfig(dataroot=str(root), rays_per_step=3000, free_beyond_grid=True, free_stretch="points",
                         horizon=0)
    item = TrainingSamples(root, index, index.split_positions("all"), config)[(2, 5)]
    assert item["free_masks"].shape == (1, *GRID.shape) and set(item["free_slot"].tolist()) == {0}

    def near_share(it):
        rays = it["ray_volume"] == 0
        points = (it["ray_origins"] + it["ray_depths"][:, None] * it["ray_directions"])[rays].numpy()
        ijk = GRID.index_of(points)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(GRID.shape)), axis=1)
        return float(it["free_masks"][0].numpy()[tuple(ijk[inside].T)].mean())

    assert near_share(item) > 0.99
    for flip in FLIPS:
        flipped = flip.apply(item)
        assert near_share(flipped) > 0.99 and not torch.equal(flipped["free_masks"], item["free_masks"])
        assert torch.equal(flip.apply(flipped)["free_masks"], item["free_masks"])


def test_flipped_rays_end_in_voxels_of_their_class_as_often_as_unflipped(prepared_synth_root):
    root, _ = prepared_synth_root
    item = _items(root, False)[(2, 5)]
    before = _label_agreement(item)
    assert before > 0.9
    for flip in FLIPS:
        flipped = flip.apply(item)
        assert flipped["occ_semantics"].shape == item["occ_semantics"].shape
        assert _label_agreement(flipped) == pytest.approx(before, abs=0.01)
        # the mirrored labels are not the labels: the check above could not pass by accident
        assert not torch.equal(flipped["occ_semantics"], item["occ_semantics"])


def test_the_lifting_and_the_depth_targets_follow_the_flip(prepared_synth_root):
    from occflownet.model.lift import frustum_points
    from occflownet.train.losses import lidar_depth_targets

    root, _ = prepared_synth_root
    item = _items(root, False)[(1, 0)]
    k = item["intrinsics"][None] / 16.0
    k[..., 2, 2] = 1.0
    depths = torch.tensor([2.0, 7.5, 20.0])
    for flip in FLIPS:
        flipped = flip.apply(item)
        plain = frustum_points(k, item["cam2ego"][None], depths, 6, 10)
        mirrored = frustum_points(k, flipped["cam2ego"][None], depths, 6, 10)
        torch.testing.assert_close(mirrored, plain * torch.from_numpy(flip.signs), rtol=1e-5, atol=1e-4)
        targets = [lidar_depth_targets(k, it["cam2ego"][None], [it["depth_points"]], (6, 10), depths)
                   for it in (item, flipped)]
        # exact: the mirrored geometry is the plain one with negated operands, and IEEE rounding is symmetric in
        # the sign, so every product and sum is the plain one negated and the depth targets are the same
        assert torch.equal(*targets) and int((targets[0] >= 0).sum()) > 0


def test_the_depth_points_carry_their_own_labels(prepared_synth_root):
    """Each depth point's label is that of its own point: as the rays' labels, it mostly names the class of the 3D
    label at the point's voxel, also off the commonest class (the road); the same labels shuffled would not."""
    root, _ = prepared_synth_root
    item = _items(root, False)[(1, 0)]
    points, labels = item["depth_points"].numpy(), item["depth_labels"].numpy()
    assert item["depth_labels"].dtype == torch.uint8 and labels.shape == points.shape[:1] and len(labels) > 100
    semantics = item["occ_semantics"].numpy()[tuple(GRID.index_of(points).T)]
    rare = labels != np.bincount(labels).argmax()
    assert rare.sum() > 20
    agree = float(np.mean((semantics == labels)[rare]))
    shuffled = float(np.mean(semantics[rare] == np.random.default_rng(0).permutation(labels[rare])))
    assert agree > 0.5 and agree > shuffled + 0.2, (agree, shuffled)


def test_the_box_moves_move_mirrored_voxels_to_mirrored_places(prepared_synth_root):
    root, _ = prepared_synth_root
    item = _items(root, False)[(2, 5)]
    moves = item["flow"]
    assert len(moves["transforms"]) > 0
    centres = np.stack([GRID.centers(a)[moves["voxels"][:, a]] for a in range(3)], axis=1)
    for flip in FLIPS:
        mirrored = flip.apply(item)["flow"]
        m_centres = np.stack([GRID.centers(a)[mirrored["voxels"][:, a]] for a in range(3)], axis=1)
        np.testing.assert_allclose(m_centres, centres * flip.signs, atol=1e-6)
        for k in range(len(moves["transforms"])):
            rows = moves["box"] == k
            moved = centres[rows] @ moves["transforms"][k][:3, :3].T + moves["transforms"][k][:3, 3]
            m_moved = m_centres[rows] @ mirrored["transforms"][k][:3, :3].T + mirrored["transforms"][k][:3, 3]
            np.testing.assert_allclose(m_moved, moved * flip.signs, atol=1e-4)


def test_the_dataset_draws_flips_deterministically_and_leaves_other_draws_alone(prepared_synth_root):
    root, _ = prepared_synth_root
    plain, flipping = _items(root, False), _items(root, True)
    seen = set()
    for step in range(12):
        a, b = plain[(3, step)], flipping[(3, step)]
        # exact: the same draws of the same step (depths, labels, keys) and the same computation run twice
        assert torch.equal(b["ray_depths"], a["ray_depths"]) and torch.equal(b["ray_labels"], a["ray_labels"])
        signs = torch.sign(b["ray_directions"] * a["ray_directions"]).mode(dim=0).values
        seen.add(tuple(signs[:2].tolist()))
        assert torch.equal(flipping[(3, step)]["cam2ego"], b["cam2ego"])          # the same key, the same flip
        if tuple(signs[:2].tolist()) == (1.0, 1.0):
            assert torch.equal(b["occ_semantics"], a["occ_semantics"])
    assert len(seen) >= 3                                                          # flips do happen, both axes
    with pytest.raises(ValueError, match="symmetric"):
        BevFlip(True).apply(plain[(3, 0)], Grid(lower=(-40.0, -30.0, -1.0), upper=(40.0, 50.0, 5.4)))


# --- image augmentation ---------------------------------------------------------------------------------------------

def _ramp(v: int = 2, h: int = 54, w: int = 96) -> torch.Tensor:
    """uint8 [v, h, w, 3] images linear in the pixel coordinates (bilinear sampling reproduces them exactly)."""
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    planes = [40 + 1.5 * xs + 0.5 * ys, 200 - 1.2 * xs + 0.4 * ys, 30 + 0.8 * xs + 2.0 * ys]
    return torch.from_numpy(np.stack([np.stack(planes, -1)] * v).round().astype(np.uint8))


def test_the_identity_map_and_a_flip_warp_exactly():
    from occflownet.train.augment import ImageAug

    images = _ramp()
    k = torch.tensor([[80.0, 0.0, 47.0], [0.0, 80.0, 27.0], [0.0, 0.0, 1.0]]).expand(2, 3, 3)
    same = ImageAug(np.stack([ImageAug.map_for(54, 96)] * 2)).apply({"images": images, "intrinsics": k})
    # exact: the identity and the flip map pixel centres onto pixel centres (integer coordinates, weights 0 and 1)
    assert torch.equal(same["images"], images) and torch.equal(same["intrinsics"], k)
    flipped = ImageAug(np.stack([ImageAug.map_for(54, 96, flip=True)] * 2)).apply({"images": images, "intrinsics": k})
    assert torch.equal(flipped["images"], torch.flip(images, [2]))
    # x' = W - 1 - x: fx → -fx, cx → W - 1 - cx
    torch.testing.assert_close(flipped["intrinsics"][0], torch.tensor([[-80.0, 0.0, 48.0], [0.0, 80.0, 27.0],
                                                                       [0.0, 0.0, 1.0]]))


def test_an_augmented_image_shows_at_q_what_the_stored_one_shows_at_the_inverse_map_of_q():
    """Known answer: on images linear in x and y the bilinear warp is exact, so each augmented pixel whose source lies
    inside the stored image equals the linear function at A⁻¹ q (up to uint8 rounding); pixels whose source is
    outside are black."""
    from occflownet.train.augment import ImageAug

    h, w = 54, 96
    images = _ramp(3, h, w)
    aug = ImageAug.draw(np.random.default_rng(4), h, w, 3)
    out = aug.apply({"images": images, "intrinsics": torch.eye(3).expand(3, 3, 3)})["images"]
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    for v in range(3):
        src = np.einsum("ij,hwj->hwi", np.linalg.inv(aug.maps[v]), np.stack([xs, ys, np.ones_like(xs)], -1))
        sx, sy = src[..., 0], src[..., 1]
        inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
        outside = (sx < -1) | (sx > w) | (sy < -1) | (sy > h)
        assert inside.mean() > 0.6 and not np.allclose(aug.maps[v], np.eye(3))
        expected = 40 + 1.5 * sx + 0.5 * sy                       # channel 0, before rounding
        got = out[v, ..., 0].numpy().astype(np.float64)
        assert np.abs(got - expected)[inside].max() <= 1.0
        assert np.all(out[v].numpy()[outside] == 0)


def test_the_intrinsics_follow_the_warp_and_keep_the_depth():
    """A camera-frame point projects with the augmented intrinsics to A · (its stored pixel), at the same z."""
    from occflownet.train.augment import ImageAug

    rng = np.random.default_rng(7)
    k = torch.tensor([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]]).expand(6, 3, 3)
    aug = ImageAug.draw(rng, 900, 1600, 6)
    k_aug = aug.apply({"images": torch.zeros(6, 900, 1600, 3, dtype=torch.uint8), "intrinsics": k})["intrinsics"]
    points = rng.uniform([-10, -5, 2], [10, 5, 50], size=(20, 3))
    for v in range(6):
        stored = points @ k[v].numpy().astype(np.float64).T
        moved = points @ k_aug[v].numpy().astype(np.float64).T
        np.testing.assert_allclose(moved[:, 2], points[:, 2], rtol=1e-6)
        np.testing.assert_allclose(moved[:, :2] / moved[:, 2:], (stored / stored[:, 2:]) @ aug.maps[v][:2].T,
                                   atol=0.05)


# The official recipe's image augmentation (boschresearch/OccFlowNet, configs/occflownet/occflownet_stbase_2d.py,
# data_config): images resized from 'src_size' (900, 1600) to 'input_size' (512, 1408), a base resize of 1408 / 1600 =
# 0.88, plus a jitter drawn from 'resize': (-0.06, 0.11); rotation drawn from 'rot': (-5.4, 5.4) degrees; 'flip': True
# (a coin toss per camera). Relative to the base resize, the scale lies in [(0.88 - 0.06) / 0.88, (0.88 + 0.11) / 0.88].
OFFICIAL_SCALE = ((0.88 - 0.06) / 0.88, (0.88 + 0.11) / 0.88)
OFFICIAL_ROTATION_DEG = 5.4


def test_image_aug_draws_stay_in_the_official_ranges():
    """600 draws fill the official ranges (stated above, from the official config) and stay inside them."""
    from occflownet.train.augment import ImageAug

    maps = ImageAug.draw(np.random.default_rng(0), 270, 480, 600).maps
    linear = maps[:, :2, :2]
    scale = np.sqrt(np.abs(np.linalg.det(linear)))
    low, high = OFFICIAL_SCALE
    assert low - 1e-9 <= scale.min() < low + 0.02 * (high - low), (scale.min(), low)
    assert high - 0.02 * (high - low) < scale.max() <= high + 1e-9, (scale.max(), high)
    flips = np.linalg.det(linear) < 0
    assert 0.4 < flips.mean() < 0.6
    angle = np.degrees(np.arctan2(linear[:, 1, 0], np.where(flips, -1, 1) * linear[:, 0, 0]))
    assert -OFFICIAL_ROTATION_DEG - 1e-6 <= angle.min() < -0.95 * OFFICIAL_ROTATION_DEG, angle.min()
    assert 0.95 * OFFICIAL_ROTATION_DEG < angle.max() <= OFFICIAL_ROTATION_DEG + 1e-6, angle.max()
    # exact: the same draw from the same seed, run twice
    np.testing.assert_array_equal(ImageAug.draw(np.random.default_rng(0), 270, 480, 600).maps, maps)


def test_the_dataset_warps_images_with_their_intrinsics_and_leaves_other_draws_alone(prepared_synth_root):
    root, _ = prepared_synth_root
    plain, augmented = _items(root, False), _items(root, False, image_aug=True)
    a, b = plain[(3, 2)], augmented[(3, 2)]
    # exact: the image augmentation changes images and intrinsics only; the rest is the same computation, and
    # `again` is a rerun of the same step
    for key in ("ray_depths", "ray_labels", "ray_directions", "cam2ego", "depth_points", "occ_semantics"):
        assert torch.equal(a[key], b[key]), key
    assert b["images"].shape == a["images"].shape and b["images"].dtype == torch.uint8
    for v in range(6):
        assert not torch.equal(a["images"][v], b["images"][v]) and not torch.equal(a["intrinsics"][v],
                                                                                   b["intrinsics"][v])
    again = augmented[(3, 2)]
    assert torch.equal(again["images"], b["images"]) and torch.equal(again["intrinsics"], b["intrinsics"])
    assert not torch.equal(augmented[(3, 3)]["intrinsics"], b["intrinsics"])


def _photometric(brightness=0.0, contrast=1.0, saturation=1.0):
    from occflownet.train.augment import Photometric

    return Photometric(np.array([brightness], float), np.array([contrast], float), np.array([saturation], float))


def _pixels(*rgb) -> dict:
    """An item of one camera whose image is the pixels ``rgb`` in a row: uint8 [1, 1, N, 3]."""
    return {"images": torch.tensor([[list(rgb)]], dtype=torch.uint8), "intrinsics": torch.eye(3)[None]}


def test_photometric_parts_give_their_known_answers():
    item = _pixels((100, 50, 200), (10, 250, 0))
    # exact: integer-valued floats, scaled by integers or 1, and rounded
    assert torch.equal(_photometric().apply(item)["images"], item["images"])
    assert _photometric(brightness=10).apply(item)["images"].tolist() == [[[[110, 60, 210], [20, 255, 10]]]]
    assert _photometric(brightness=-32).apply(item)["images"].tolist() == [[[[68, 18, 168], [0, 218, 0]]]]
    assert _photometric(contrast=2).apply(item)["images"].tolist() == [[[[200, 100, 255], [20, 255, 0]]]]
    grey = _photometric(saturation=0).apply(item)["images"][0, 0]
    expected = [round(0.299 * r + 0.587 * g + 0.114 * b) for r, g, b in ((100, 50, 200), (10, 250, 0))]
    assert grey[:, 0].tolist() == expected and torch.equal(grey[:, 0:1].expand(-1, 3), grey)
    # saturation 2 moves each channel twice its distance from the grey (82.05 for the first pixel), clipped
    assert _photometric(saturation=2).apply(item)["images"][0, 0, 0].tolist() == [118, 18, 255]
    assert torch.equal(_photometric(brightness=5).apply(item)["intrinsics"], item["intrinsics"])


# mmdet's PhotoMetricDistortion defaults (BEVFormer's PhotoMetricDistortionMultiViewImage takes the same):
# brightness_delta=32, contrast_range=(0.5, 1.5), saturation_range=(0.5, 1.5), each step with probability 0.5.
MMDET_PHOTOMETRIC = (32, (0.5, 1.5), (0.5, 1.5), 0.5)


def test_photometric_draws_fill_their_ranges_half_of_the_time():
    from occflownet.train.augment import (BRIGHTNESS_DELTA, CONTRAST_RANGE, PHOTOMETRIC_RATIO, SATURATION_RANGE,
                                          Photometric)

    assert (BRIGHTNESS_DELTA, CONTRAST_RANGE, SATURATION_RANGE, PHOTOMETRIC_RATIO) == MMDET_PHOTOMETRIC
    rng = np.random.default_rng(0)
    jitter = Photometric.draw(rng, 2000)
    for values, idle, (low, high) in ((jitter.brightness, 0.0, (-BRIGHTNESS_DELTA, BRIGHTNESS_DELTA)),
                                      (jitter.contrast, 1.0, CONTRAST_RANGE),
                                      (jitter.saturation, 1.0, SATURATION_RANGE)):
        on = values != idle
        assert 0.45 < on.mean() < 0.55
        margin = 0.01 * (high - low)
        assert low <= values[on].min() < low + margin and high - margin < values[on].max() <= high
    # six draws per camera whatever is applied, so the generator's later draws do not depend on the outcome
    rng_a, rng_b = np.random.default_rng(1), np.random.default_rng(1)
    Photometric.draw(rng_a, 6)
    rng_b.random((6, 6))
    assert rng_a.random() == rng_b.random()
    with pytest.raises(ValueError, match="2 draws for 1 images"):
        Photometric.draw(rng, 2).apply(_pixels((1, 2, 3)))


def test_the_dataset_jitters_images_only(prepared_synth_root):
    from occflownet.data.index import load_index

    root, _ = prepared_synth_root
    index = load_index(root)

    def items(photometric):
        config = TrainConfig(dataroot=str(root), supervision="2d+3d", rays_per_step=3000,
                             photometric_aug=photometric)
        return TrainingSamples(root, index, index.split_positions("all"), config)

    a, b = items(False)[(3, 2)], items(True)[(3, 2)]
    # exact: the jitter changes the images only; the rest is the same computation
    for key in ("ray_depths", "ray_labels", "ray_directions", "cam2ego", "intrinsics", "depth_points", "occ_semantics"):
        assert torch.equal(a[key], b[key]), key
    assert b["images"].dtype == torch.uint8 and b["images"].shape == a["images"].shape
    assert not torch.equal(a["images"], b["images"])
