"""Quarter turns of the ego frame (occflownet.train.augment.BevRotation): a voxel goes where its centre goes, four
turns are no turn, and a turned item is the same scene in the turned frame — rays still end in voxels of their
class, the cameras lift each pixel to the turned place, box moves move turned voxels to turned places."""
import numpy as np
import pytest
import torch

from occflownet.occ3d import GRID, Grid
from occflownet.train.augment import BevFlip, BevRotation, apply_xy_map
from occflownet.train.dataset import TrainingSamples
from occflownet.train.recipe import TrainConfig

TURNS = [BevRotation(1), BevRotation(2), BevRotation(3)]


def _item(root, step: int = 5):
    from occflownet.data.flow import flow_path, load_flow_records
    from occflownet.data.index import load_index

    index = load_index(root)
    config = TrainConfig(dataroot=str(root), supervision="2d+3d", flow=True, rays_per_step=3000)
    return TrainingSamples(root, index, index.split_positions("all"), config,
                           load_flow_records(flow_path(root, index.version)))[(2, step)]


def _turned(points: np.ndarray, turns: int) -> np.ndarray:
    """(x, y, z) → (-y, x, z), ``turns`` times: the map the rotation means, written out."""
    out = np.array(points, dtype=np.float64, copy=True)
    for _ in range(turns % 4):
        out = np.stack([-out[..., 1], out[..., 0], out[..., 2]], axis=-1)
    return out


def test_one_voxel_goes_where_its_centre_goes():
    grid = np.full(GRID.shape, 17, np.uint8)
    grid[150, 120, 3] = 4                                   # centre (20.2, 8.2) m; a quarter turn: (-8.2, 20.2) m
    item = {"cam2ego": torch.eye(4).expand(6, 4, 4).clone(), "occ_semantics": torch.from_numpy(grid)}
    turned = BevRotation(1).apply(item)["occ_semantics"].numpy()
    assert np.argwhere(turned != 17).tolist() == [[79, 150, 3]]
    assert np.argwhere(BevRotation(2).apply(item)["occ_semantics"].numpy() != 17).tolist() == [[49, 79, 3]]
    assert BevRotation(0).apply(item) is item and BevRotation(4).apply(item) is item


def test_four_turns_are_no_turn_and_a_turn_undoes_its_opposite(prepared_synth_root):
    root, _ = prepared_synth_root
    item = _item(root)
    for k in (1, 2, 3):
        back = BevRotation(4 - k).apply(BevRotation(k).apply(item))
        # exact: a quarter turn swaps and negates coordinates (x·0 + y·1 and the like round nothing) and permutes
        # voxels
        for key in ("cam2ego", "ray_origins", "ray_directions", "depth_points", "occ_semantics", "occ_mask"):
            assert torch.equal(back[key], item[key]), (k, key)
        np.testing.assert_array_equal(back["flow"]["voxels"], item["flow"]["voxels"])
        np.testing.assert_allclose(back["flow"]["transforms"], item["flow"]["transforms"], atol=1e-6)


def test_turned_rays_end_in_voxels_of_their_class(prepared_synth_root):
    root, _ = prepared_synth_root
    item = _item(root)

    def agreement(it) -> float:
        t0 = it["ray_volume"] == 0
        points = (it["ray_origins"] + it["ray_depths"][:, None] * it["ray_directions"])[t0].numpy()
        ijk = GRID.index_of(points)
        inside = np.all((ijk >= 0) & (ijk < np.asarray(GRID.shape)), axis=1)
        return float(np.mean(it["occ_semantics"].numpy()[tuple(ijk[inside].T)] == it["ray_labels"][t0].numpy()[inside]))

    before = agreement(item)
    assert before > 0.9
    for turn in TURNS:
        turned = turn.apply(item)
        assert agreement(turned) == pytest.approx(before, abs=0.01)
        assert not torch.equal(turned["occ_semantics"], item["occ_semantics"])      # the labels did move
        np.testing.assert_allclose(turned["ray_origins"].numpy(), _turned(item["ray_origins"].numpy(),
                                                                          turn.quarter_turns), atol=1e-6)


def test_the_lifting_follows_the_turn(prepared_synth_root):
    from occflownet.model.lift import frustum_points

    root, _ = prepared_synth_root
    item = _item(root, 0)
    k = item["intrinsics"][None] / 16.0
    k[..., 2, 2] = 1.0
    depths = torch.tensor([2.0, 7.5, 20.0])
    plain = frustum_points(k, item["cam2ego"][None], depths, 6, 10)
    for turn in TURNS:
        turned = frustum_points(k, turn.apply(item)["cam2ego"][None], depths, 6, 10)
        expected = torch.from_numpy(_turned(plain.numpy(), turn.quarter_turns)).to(plain.dtype)
        torch.testing.assert_close(turned, expected, rtol=1e-5, atol=1e-4)


def test_the_box_moves_move_turned_voxels_to_turned_places(prepared_synth_root):
    root, _ = prepared_synth_root
    item = _item(root)
    moves = item["flow"]
    assert len(moves["transforms"]) > 0
    centres = np.stack([GRID.centers(a)[moves["voxels"][:, a]] for a in range(3)], axis=1)
    for turn in TURNS:
        turned = turn.apply(item)["flow"]
        t_centres = np.stack([GRID.centers(a)[turned["voxels"][:, a]] for a in range(3)], axis=1)
        np.testing.assert_allclose(t_centres, _turned(centres, turn.quarter_turns), atol=1e-5)
        for b in range(len(moves["transforms"])):
            rows = moves["box"] == b
            moved = centres[rows] @ moves["transforms"][b][:3, :3].T + moves["transforms"][b][:3, 3]
            t_moved = t_centres[rows] @ turned["transforms"][b][:3, :3].T + turned["transforms"][b][:3, 3]
            np.testing.assert_allclose(t_moved, _turned(moved, turn.quarter_turns), atol=1e-4)


def test_a_flip_is_the_same_map_through_either_class():
    item = {"cam2ego": torch.eye(4).expand(6, 4, 4).clone(),
            "occ_semantics": torch.from_numpy(np.random.default_rng(0).integers(0, 18, GRID.shape).astype(np.uint8))}
    half_turn = BevRotation(2).apply(item)
    both = BevFlip(True, True).apply(item)                   # mirroring both axes is the half turn
    assert torch.equal(half_turn["occ_semantics"], both["occ_semantics"])
    assert torch.equal(half_turn["cam2ego"], both["cam2ego"])
    with pytest.raises(ValueError, match="square"):
        apply_xy_map(item, BevRotation(1).matrix, Grid(lower=(-40.0, -20.0, -1.0), upper=(40.0, 20.0, 5.4),
                                                      shape=(200, 100, 16)))


def test_the_dataset_draws_turns_deterministically_and_leaves_other_draws_alone(prepared_synth_root):
    from occflownet.data.index import load_index

    root, _ = prepared_synth_root
    index = load_index(root)
    make = lambda rotate: TrainingSamples(root, index, index.split_positions("all"),  # noqa: E731
                                          TrainConfig(dataroot=str(root), rays_per_step=500, bev_rotate=rotate))
    plain, turning = make(False), make(True)
    turns = set()
    for step in range(12):
        a, b = plain[(3, step)], turning[(3, step)]
        # exact: the same draws of the same step (depths, labels) computed twice
        assert torch.equal(b["ray_depths"], a["ray_depths"]) and torch.equal(b["ray_labels"], a["ray_labels"])
        cos, sin = float(b["cam2ego"][0, 0, 0] * a["cam2ego"][0, 0, 0] + b["cam2ego"][0, 1, 0] * a["cam2ego"][0, 1, 0]), \
            float(a["cam2ego"][0, 0, 0] * b["cam2ego"][0, 1, 0] - a["cam2ego"][0, 1, 0] * b["cam2ego"][0, 0, 0])
        turns.add(round(np.degrees(np.arctan2(sin, cos))) % 360)
        assert torch.equal(turning[(3, step)]["cam2ego"], b["cam2ego"])               # the same key, the same turn
    assert turns == {0, 90, 180, 270}
