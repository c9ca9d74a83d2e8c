"""The shared voxel walk (occflownet.voxel_walk): known answers, both tie rules, brute force."""
import numpy as np
import pytest

from occflownet.voxel_walk import OUTSIDE, traverse, walk_rays


# The walks are compared with the brute force exactly: visited voxels (booleans) of float64 rays in general position
# (random; the axis-parallel ones exactly parallel), where a tie needs a ray within ~1e-14 of a voxel edge.
def brute_force(origins, dirs, occupied, t_max, lower, vs):
    """Per ray: every voxel whose box the ray segment [0, t_max) enters, in order of entry, up to and including
    the first occupied one (slab test against each voxel separately)."""
    X, Y, Z = occupied.shape
    ijk = np.stack(np.meshgrid(np.arange(X), np.arange(Y), np.arange(Z), indexing="ij"), -1).reshape(-1, 3)
    lo = np.asarray(lower) + ijk * vs
    out = np.zeros(occupied.size, bool)
    occ = occupied.reshape(-1)
    for o, d, tm in zip(origins, dirs, t_max):
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (lo + vs - o) / d
        t_in, t_out = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
        hit = (t_in < t_out) & (t_out > 0) & (np.maximum(t_in, 0) < tm)
        cand = np.nonzero(hit)[0]
        for v in cand[np.argsort(np.maximum(t_in[cand], 0))]:
            out[v] = True
            if occ[v]:
                break
    return out.reshape(occupied.shape)


# A row of 10 voxels of 0.4 m along x starting at x = -2 m; the ray starts 0.3 m before it and runs along +x with a
# direction of length 2, so t is in units of 2 m: cell k is entered at t = (0.3 + 0.4 k) / 2.
ROW_LOWER, ROW_VS = (-2.0, 0.0, 0.0), 0.4
ROW_ORIGIN, ROW_DIR = np.array([[-2.3, 0.2, 0.2]]), np.array([[2.0, 0.0, 0.0]])


def _entry(k):
    return (0.3 + 0.4 * k) / 2.0


@pytest.mark.parametrize("ties", ["first", "last"])
def test_ray_along_x_visits_the_row_in_order_with_its_entry_distances(ties):
    empty = np.zeros((10, 1, 1), bool)
    full = walk_rays(empty, ROW_ORIGIN, ROW_DIR, lower=ROW_LOWER, voxel_size=ROW_VS, ties=ties, visited=True)
    assert full.visited[:, 0, 0].all() and full.code[0] == 0
    assert full.t[0] == pytest.approx(_entry(10), abs=1e-12)  # no hit: where it leaves the grid
    for k in range(10):
        # ending just after cell k's entry, the ray has visited exactly cells 0..k; ending on it, 0..k-1
        for t_end, last in ((_entry(k) + 1e-9, k), (_entry(k) - 1e-9, k - 1)):
            w = walk_rays(empty, ROW_ORIGIN, ROW_DIR, lower=ROW_LOWER, voxel_size=ROW_VS, t_end=[t_end],
                          ties=ties, visited=True)
            assert w.visited[:, 0, 0].tolist() == [i <= last for i in range(10)], (k, t_end)
            if last >= 0:
                assert w.t[0] == pytest.approx(_entry(last + 1), abs=1e-12)  # it stops where cell `last` ends
        # an occupied cell k is the first hit, left at the entry of cell k + 1
        occupied = empty.copy()
        occupied[k:] = True
        hit = walk_rays(occupied.astype(np.uint8) * (k + 1), ROW_ORIGIN, ROW_DIR, lower=ROW_LOWER,
                        voxel_size=ROW_VS, ties=ties, visited=True)
        assert hit.code[0] == k + 1 and hit.t[0] == pytest.approx(_entry(k + 1), abs=1e-12)
        assert hit.visited[:, 0, 0].tolist() == [i <= k for i in range(10)]


def test_diagonal_ray_through_lattice_corners_and_the_two_tie_rules():
    """From the centre of voxel (0, 0, 0) along (1, 1, 1), in voxel units: the ray passes exactly through the
    corners (1, 1, 1) and (2, 2, 2), where all three crossings coincide (t = 0.5, 1.5). 'first' then steps x, y, z
    in that order, 'last' z, y, x; both visit the diagonal voxels, each through two voxels it only touches."""
    shape = (3, 3, 3)
    origin, direction = np.array([[0.5, 0.5, 0.5]]), np.array([[1.0, 1.0, 1.0]])
    diagonal = {(0, 0, 0), (1, 1, 1), (2, 2, 2)}
    expected = {"first": diagonal | {(1, 0, 0), (1, 1, 0), (2, 1, 1), (2, 2, 1)},
                "last": diagonal | {(0, 0, 1), (0, 1, 1), (1, 1, 2), (1, 2, 2)}}
    true_path = brute_force(origin, direction, np.zeros(shape, bool), [np.inf], (0, 0, 0), 1.0)
    assert {tuple(v) for v in np.argwhere(true_path)} == diagonal  # the voxels it crosses with positive length
    for ties, voxels in expected.items():
        w = walk_rays(np.zeros(shape, bool), origin, direction, ties=ties, visited=True)
        assert {tuple(v) for v in np.argwhere(w.visited)} == voxels, ties
        assert w.code[0] == 0 and w.t[0] == 2.5  # leaves the grid through the corner (3, 3, 3)
    # the voxel touched first after the corner is the first hit, left at once (t = 0.5)
    volume = np.zeros(shape, np.uint8)
    volume[1, 0, 0], volume[0, 0, 1] = 5, 7
    assert walk_rays(volume, origin, direction, ties="first").code[0] == 5
    assert walk_rays(volume, origin, direction, ties="last").code[0] == 7
    assert walk_rays(volume, origin, direction, ties="last").t[0] == 0.5


def test_walk_first_hits_equal_brute_force_and_rays_outside():
    rng = np.random.default_rng(4)
    shape, lower, vs = (12, 9, 6), np.array([-2.0, -1.5, -1.0]), 0.5
    volume = np.where(rng.random(shape) < 0.05, rng.integers(1, 17, shape), 0).astype(np.uint8)
    upper = lower + np.array(shape) * vs
    origins = rng.uniform(lower - 2, upper + 2, (300, 3))
    dirs = rng.normal(size=(300, 3))
    dirs[:15, 1] = 0.0  # exactly parallel to a grid plane
    for ties in ("first", "last"):
        w = walk_rays(volume, origins, dirs, lower=lower, voxel_size=vs, ties=ties, visited=True)
        for i in range(len(origins)):
            seen = brute_force(origins[i:i + 1], dirs[i:i + 1], volume > 0, [np.inf], lower, vs)
            hits = np.argwhere(seen & (volume > 0))
            assert w.code[i] == (volume[tuple(hits[0])] if len(hits) else 0), i
            if len(hits):  # t = where the ray leaves the hit voxel
                lo = lower + hits[0] * vs
                with np.errstate(divide="ignore"):
                    t_exit = np.maximum((lo - origins[i]) / dirs[i], (lo + vs - origins[i]) / dirs[i]).min()
                assert w.t[i] == pytest.approx(t_exit, rel=1e-9, abs=1e-9), i
        assert np.array_equal(w.visited, brute_force(origins, dirs, volume > 0, np.full(300, np.inf), lower, vs))
    # a ray that never enters the grid, and one that leaves it at once
    w = walk_rays(volume, [[-3.0, 0.0, 0.0], [-1.9, 0.1, 0.1]], [[-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], lower=lower,
                  voxel_size=vs, empty=0)
    assert w.code[0] == 0 and w.t[0] == np.inf
    assert w.t[1] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="ties"):
        walk_rays(volume, origins, dirs, ties="middle")
    assert OUTSIDE > 17  # class volumes (0..17) never collide with the border code


def test_traverse_equals_brute_force():
    rng = np.random.default_rng(3)
    shape, lower, vs = (12, 9, 6), np.array([-2.0, -1.5, -1.0]), 0.5
    occupied = rng.random(shape) < 0.07
    n = 400
    upper = lower + np.array(shape) * vs
    origins = rng.uniform(lower - 2, upper + 2, (n, 3))  # inside and outside the grid
    dirs = rng.normal(size=(n, 3)) * rng.uniform(0.2, 3.0, (n, 1))  # any length
    dirs[:20, 2] = 0.0  # rays parallel to a grid plane
    t_max = np.where(rng.random(n) < 0.4, rng.uniform(0.1, 4.0, n), np.inf)
    got = traverse(origins, dirs, occupied, t_max, lower, vs)
    want = brute_force(origins, dirs, occupied, t_max, lower, vs)
    assert want.sum() > 100
    assert np.array_equal(got, want), f"{(got & ~want).sum()} extra, {(want & ~got).sum()} missing voxels"


def test_traverse_stops_at_first_occupied_voxel():
    occupied = np.zeros((10, 1, 1), bool)
    occupied[6] = True
    got = traverse(np.array([[0.05, 0.5, 0.5]]), np.array([[1.0, 0.0, 0.0]]), occupied, None, (0, 0, 0), 1.0)
    assert got[:, 0, 0].tolist() == [True] * 7 + [False] * 3


def test_the_numba_walk_leaves_torchs_thread_count_alone():
    # in a fresh process: numba's OpenMP layer, when it starts, raises torch's intra-op count to its own (here
    # from OMP_NUM_THREADS=1 to NUMBA_NUM_THREADS=2); a run trained after labelling in one process must keep its 1
    pytest.importorskip("numba")
    import subprocess
    import sys

    code = ("import numpy as np, torch; from occflownet.voxel_walk import walk_rays; before = torch.get_num_threads();"
            "walk_rays(np.zeros((8, 8, 8), np.uint8), np.random.rand(64, 3) * 8, np.random.randn(64, 3),"
            " engine='numba'); print(before, torch.get_num_threads())")
    env = {**__import__("os").environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1"]
