"""The voxel rules of the label pipeline with known answers: the majority vote and its tie rule, free space from
beams, mask_lidar, and mask_camera against an independent brute-force walk."""
import numpy as np

from occflownet.occ3d import BUS, CAR, DRIVEABLE_SURFACE, FREE, MANMADE, Grid
from occflownet.labels.config import UNLABELLED
from occflownet.labels.voxels import VoxelVote, beam_free_space, camera_mask, lidar_mask, vote
from occflownet.rig import default_rig
from occflownet.contract import calibration_arrays
from test_voxel_walk import brute_force

GRID = Grid(lower=(-4.0, -4.0, -1.0), upper=(4.0, 4.0, 2.2), voxel_size=0.4, shape=(20, 20, 8))


def centre(i, j, k):
    return np.asarray(GRID.lower) + (np.array([i, j, k]) + 0.5) * GRID.voxel_size


def test_vote_majority_tie_rule_and_unlabelled():
    rng = np.random.default_rng(0)
    jitter = lambda n: rng.uniform(-0.15, 0.15, (n, 3))  # noqa: E731 (inside one voxel)
    pts = [centre(3, 3, 3) + jitter(5), centre(3, 3, 3) + jitter(2),   # 5 car, 2 manmade: car
           centre(5, 5, 2) + jitter(2), centre(5, 5, 2) + jitter(2),   # 2 road, 2 car: tie → car (lower index)
           centre(7, 7, 2) + jitter(3),                                # unlabelled only
           centre(9, 9, 2) + jitter(1), centre(9, 9, 2) + jitter(4),   # 1 bus, 4 unlabelled: bus
           np.array([[9.0, 0.0, 0.0]])]                                # outside the grid: ignored
    labels = [CAR] * 5 + [MANMADE] * 2 + [DRIVEABLE_SURFACE] * 2 + [CAR] * 2 + [UNLABELLED] * 3 + [BUS] \
        + [UNLABELLED] * 4 + [MANMADE]
    v = vote(np.concatenate(pts), np.array(labels, np.uint8), GRID)
    assert v.semantics[3, 3, 3] == CAR and v.semantics[5, 5, 2] == CAR and v.semantics[9, 9, 2] == BUS
    assert v.semantics[7, 7, 2] == FREE and v.unlabelled[7, 7, 2] and v.occupied[7, 7, 2]
    assert (v.semantics != FREE).sum() == 3 and v.occupied.sum() == 4 and v.unlabelled.sum() == 1
    strict = vote(np.concatenate(pts), np.array(labels, np.uint8), GRID, min_points=3)
    assert strict.semantics[3, 3, 3] == CAR and strict.semantics[5, 5, 2] == CAR      # 7 and 4 labelled points
    assert strict.semantics[9, 9, 2] == FREE and strict.occupied[9, 9, 2]             # 1 labelled of 5


def test_beams_mark_the_voxels_they_cross_and_mask_lidar():
    origin = centre(1, 10, 4)
    end = centre(12, 10, 4)                                     # along +x through voxels 1..12 of row (·, 10, 4)
    crossed = beam_free_space(origin[None], end[None], GRID)
    assert set(map(tuple, np.argwhere(crossed))) == {(i, 10, 4) for i in range(1, 13)}
    sem = np.full(GRID.shape, FREE, np.uint8)
    sem[12, 10, 4] = MANMADE
    occupied = sem != FREE
    occupied[6, 10, 4] = True                                   # an unlabelled voxel on the way: not observed
    mask = lidar_mask(VoxelVote(sem, occupied, occupied & (sem == FREE)), crossed)
    assert set(map(tuple, np.argwhere(mask))) == {(i, 10, 4) for i in range(1, 13) if i != 6}
    assert not beam_free_space(np.zeros((0, 3)), np.zeros((0, 3)), GRID).any()


def test_camera_mask_is_what_rays_to_observed_voxels_see():
    """A wall in front of the rig: mask_camera holds exactly the observed voxels that the brute-force walk of rays
    from each camera to each observed voxel centre visits up to the first occupied voxel; the wall's back and the
    voxels behind it are hidden; unobserved voxels never enter."""
    rig = default_rig(48, 27)
    K, T = calibration_arrays(rig)
    K, T = K.astype(np.float64), T.astype(np.float64)
    sizes = np.array([[48, 27]] * 6)
    grid = Grid(lower=(-2.0, -6.0, -1.0), upper=(6.0, 6.0, 2.2), voxel_size=0.4, shape=(20, 30, 8))
    occupied = np.zeros(grid.shape, bool)
    occupied[15:17, 9:21, 2:7] = True                           # a 0.8 m thick wall at x = 4.0 .. 4.8 m
    observed = np.ones(grid.shape, bool)
    observed[:, :, 0] = False                                   # the lowest layer was never observed
    mask = camera_mask(observed, occupied, K, T, sizes, grid)
    expected = np.zeros(grid.shape, bool)
    ijk = np.argwhere(observed)
    centres = np.asarray(grid.lower) + (ijk + 0.5) * grid.voxel_size
    for c in range(6):
        pc = (centres - T[c][:3, 3]) @ T[c][:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = K[c][0, 0] * pc[:, 0] / pc[:, 2] + K[c][0, 2], K[c][1, 1] * pc[:, 1] / pc[:, 2] + K[c][1, 2]
        ok = (pc[:, 2] >= 0.05) & (u >= 0) & (u < 48) & (v >= 0) & (v < 27)
        d = centres[ok] - T[c][:3, 3]
        expected |= brute_force(np.broadcast_to(T[c][:3, 3], d.shape), d, occupied, np.ones(len(d)), grid.lower,
                                grid.voxel_size)
    # exact: booleans from float64 walks of rays in general position (no ray within ~1e-9 of a voxel edge or of the
    # image border), where CPUs' rounding differs by ~1e-14
    assert np.array_equal(mask, expected & observed)
    assert mask[15, 15, 4] and not mask[16, 15, 4] and not mask[18, 15, 4]   # front face seen, back and behind not
    assert mask[13, 15, 5] and not mask[:, :, 0].any()                        # free space in front seen
