"""Volume rendering (occflownet.render.volume_render): known answers, references, gradients."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from occflownet.occ3d import NUM_CLASSES, Grid
from occflownet.render.volume_render import RenderConfig, render_rays, weights_from_density

SMALL = Grid(lower=(-4.0, -4.0, -1.0), upper=(4.0, 4.0, 2.2), voxel_size=0.4, shape=(20, 20, 8))


def _centre(axis: int, index: int, grid: Grid = SMALL) -> float:
    return grid.lower[axis] + (index + 0.5) * grid.voxel_size


def _ray_along_x(n: int = 4):
    """Rays from x = -3 along +x through the centres of voxel column (j=10, k=4)."""
    origins = torch.tensor([[-3.0, _centre(1, 10), _centre(2, 4)]]).repeat(n, 1)
    return origins, torch.tensor([[1.0, 0.0, 0.0]]).repeat(n, 1)


def _slab(first: int, last: int, cls: int):
    density = torch.zeros(SMALL.shape)
    density[first:last + 1] = 1.0
    logits = torch.zeros(*SMALL.shape, NUM_CLASSES)
    logits[first:last + 1, ..., cls] = 5.0
    return density, logits


def test_opaque_single_voxel_slab_renders_its_distance_and_class():
    # slab = voxels i = 15 (x ∈ [2.0, 2.4]); its face is 5.0 m from the origin. With the official unscaled σ a
    # single voxel is not opaque (optical depth 0.4), so this checks the geometry with density_scale = 50.
    density, logits = _slab(15, 15, cls=5)
    origins, dirs = _ray_along_x()
    out = render_rays(density, logits, origins, dirs, RenderConfig(far=10.0, density_scale=50.0, grid=SMALL),
                      torch.Generator().manual_seed(0))
    assert torch.all((out.depth - 5.0).abs() < 0.4), out.depth
    assert torch.all(out.weight_sum > 0.99)
    assert torch.all(out.semantics.argmax(-1) == 5)


@pytest.mark.parametrize("axis,face,origin_coord", [(1, 15, -3.0), (2, 6, -0.8)])
def test_slab_distance_along_y_and_z(axis, face, origin_coord):
    # a slab of voxels with index `face` along `axis`; its near face is at lower + face * 0.4
    density = torch.zeros(SMALL.shape)
    index = [slice(None)] * 3
    index[axis] = face
    density[tuple(index)] = 1.0
    logits = torch.zeros(*SMALL.shape, NUM_CLASSES)
    logits[..., 2] = 1.0
    origin = torch.tensor([_centre(0, 3), _centre(1, 3), _centre(2, 1)])
    origin[axis] = origin_coord
    direction = torch.zeros(3)
    direction[axis] = 1.0
    out = render_rays(density, logits, origin[None], direction[None], RenderConfig(far=10.0, density_scale=50.0,
                                                                                    grid=SMALL))
    distance = SMALL.lower[axis] + face * SMALL.voxel_size - origin_coord
    assert abs(float(out.depth[0]) - distance) < 0.4 and float(out.weight_sum[0]) > 0.99


def test_unscaled_thick_slab_matches_the_continuous_integral():
    # σ = 1 from voxel 15 to the grid's end: the exact render of the trilinear field, by dense quadrature. The ray
    # ends (far = 7 m, x = 4.0) inside the slab, so the light left at far is drawn inside the slab too.
    density, logits = _slab(15, 19, cls=3)
    origins, dirs = _ray_along_x()
    cfg = RenderConfig(far=7.0, grid=SMALL)
    out = render_rays(density, logits, origins, dirs, cfg, torch.Generator().manual_seed(1))
    t = np.linspace(cfg.near, cfg.far, 400001)
    x = -3.0 + t
    centres = -4.0 + (np.arange(20) + 0.5) * 0.4
    sigma = np.interp(x, np.concatenate([[centres[0] - 0.4], centres, [centres[-1] + 0.4]]),
                      np.concatenate([[0.0], density[:, 10, 4].numpy(), [0.0]]), left=0.0, right=0.0)
    dt = t[1] - t[0]
    trans = np.exp(-np.concatenate([[0.0], np.cumsum(0.5 * (sigma[1:] + sigma[:-1]) * dt)]))
    w = sigma * trans * dt
    exact_depth, exact_weight = float((w * t).sum()), float(1.0 - trans[-1])
    assert np.allclose(out.depth.numpy(), exact_depth, atol=0.02), (out.depth, exact_depth)
    assert np.allclose(out.weight_sum.numpy(), exact_weight, atol=0.01)
    assert torch.all(out.semantics.argmax(-1) == 3)
    # the official σ ∈ [0, 1] per metre: even σ = 1 leaves a 1 m mean free path, so the (weight-normalised)
    # rendered surface lies behind the face at 5 m and 14 % of the light passes 2 m of "solid" voxels
    assert exact_depth / exact_weight > 5.0 + 0.5 and exact_weight < 0.9


@pytest.mark.parametrize("lookup", ["numba", "grid_sample"])
def test_transmitted_light_is_sampled_in_the_last_bin_and_stretches_the_surface_interval(lookup):
    # The official fine distribution ends at 1: the light that passes the slab (T ≈ 0.14 after 2 m of σ = 1) is
    # drawn in the last coarse bin, near far = 40 m, and the slab's last sample gets an interval reaching half-way
    # there. So about 10-15 of the 100 samples sit at the end of the ray and the surface absorbs more than the
    # continuous integral says (0.86; up to 1 on some rays) — the behaviour of the official renderer.
    density, logits = _slab(15, 19, cls=3)
    origins, dirs = _ray_along_x(8)
    out = render_rays(density, logits, origins, dirs, RenderConfig(far=40.0, grid=SMALL, lookup=lookup),
                      torch.Generator().manual_seed(1))
    in_last_bin = (out.t_samples > 40.0 - (40.0 - 0.05) / 50 * 1.5).sum(-1)
    # (per ray it varies with the coarse jitter, which moves the coarse samples across the slab's trilinear edges)
    assert torch.all((in_last_bin >= 5) & (in_last_bin <= 25)), in_last_bin
    assert 10 <= in_last_bin.float().mean() <= 17, in_last_bin
    assert torch.all(out.weight_sum > 0.83) and out.weight_sum.max() > 0.95  # some rays: the stretched interval is opaque
    assert torch.all(out.semantics.argmax(-1) == 3)


def test_empty_grid_renders_nothing():
    density = torch.zeros(SMALL.shape, requires_grad=True)
    logits = torch.randn(*SMALL.shape, NUM_CLASSES, requires_grad=True)
    gen = torch.Generator().manual_seed(0)
    origins, dirs = torch.randn(50, 3, generator=gen), torch.nn.functional.normalize(torch.randn(50, 3, generator=gen))
    out = render_rays(density, logits, origins, dirs, RenderConfig(far=10.0, grid=SMALL), gen)
    assert torch.all(out.weights == 0) and torch.all(out.depth == 0) and torch.all(out.semantics == 0)
    (out.depth.sum() + out.semantics.sum()).backward()  # still differentiable (an empty ray has no samples to grow)


def _random_case(n_vol=2, n_rays=300, seed=0, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    density = torch.rand(n_vol, *SMALL.shape, generator=gen, dtype=dtype)
    density = torch.where(torch.rand(density.shape, generator=gen, dtype=dtype) < 0.7, 0.05 * density, density)
    logits = torch.randn(n_vol, *SMALL.shape, NUM_CLASSES, generator=gen, dtype=dtype)
    origins = (torch.rand(n_rays, 3, generator=gen, dtype=dtype) - 0.5) * torch.tensor([10.0, 10.0, 4.0], dtype=dtype)
    dirs = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=gen, dtype=dtype), dim=-1)
    volume = torch.randint(0, n_vol, (n_rays,), generator=gen)
    return density, logits, origins, dirs, volume


def test_weights_are_a_sub_probability():
    density, logits, origins, dirs, volume = _random_case()
    out = render_rays(density, logits, origins, dirs, RenderConfig(far=12.0, grid=SMALL),
                      torch.Generator().manual_seed(0), volume)
    assert torch.all(out.weights >= 0) and torch.all(out.weight_sum <= 1.0 + 1e-6)
    assert out.weight_sum.max() > 0.5
    assert torch.allclose(out.weight_sum, out.weights.sum(-1))


def _reference_weights(sigma, starts, ends):
    """Independent float64 loop over the formula w_i = T_i (1 - exp(-σ_i δ_i)), T_i = exp(-Σ_{j<i} σ_j δ_j)."""
    sigma, starts, ends = (np.asarray(a, dtype=np.float64) for a in (sigma, starts, ends))
    w = np.zeros_like(sigma)
    for r in range(sigma.shape[0]):
        acc = 0.0
        for i in range(sigma.shape[1]):
            tau = sigma[r, i] * (ends[r, i] - starts[r, i])
            w[r, i] = np.exp(-acc) * (1.0 - np.exp(-tau))
            acc += tau
    return w


def test_rendered_weights_match_an_independent_float64_reference():
    density, logits, origins, dirs, volume = _random_case(n_rays=40)
    cfg = RenderConfig(far=12.0, grid=SMALL, density_scale=2.0)
    out = render_rays(density, logits, origins, dirs, cfg, torch.Generator().manual_seed(0), volume)
    ref = _reference_weights(cfg.density_scale * out.sigma, out.t_starts, out.t_ends)
    assert np.abs(out.weights.numpy() - ref).max() < 1e-5
    gen = torch.Generator().manual_seed(5)
    sigma, delta = 3 * torch.rand(30, 64, generator=gen), 0.3 * torch.rand(30, 64, generator=gen)
    starts = torch.cumsum(delta, -1) - delta
    w, _, _ = weights_from_density(sigma, starts, starts + delta)
    assert np.abs(w.numpy() - _reference_weights(sigma, starts, starts + delta)).max() < 1e-5


def test_weights_match_nerfacc():
    nerfacc = pytest.importorskip("nerfacc", reason="nerfacc (optional test dependency) is not installed")
    gen = torch.Generator().manual_seed(5)
    sigma, delta = 3 * torch.rand(30, 64, generator=gen), 0.3 * torch.rand(30, 64, generator=gen)
    starts = torch.cumsum(delta, -1) - delta
    ours, trans, alpha = weights_from_density(sigma, starts, starts + delta)
    theirs, their_trans, their_alpha = nerfacc.render_weight_from_density(starts, starts + delta, sigma)
    assert (ours - theirs).abs().max() < 1e-5
    assert (trans - their_trans).abs().max() < 1e-5 and (alpha - their_alpha).abs().max() < 1e-5


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_numba_path_matches_grid_sample_reference_values_and_gradients(dtype, tol):
    density, logits, origins, dirs, volume = _random_case(dtype=dtype)
    coeff = torch.randn(3, generator=torch.Generator().manual_seed(9), dtype=dtype)
    results = []
    for lookup in ("numba", "grid_sample"):
        d, lg = density.clone().requires_grad_(True), logits.clone().requires_grad_(True)
        cfg = RenderConfig(far=12.0, grid=SMALL, lookup=lookup, density_scale=1.5)
        out = render_rays(d, lg, origins, dirs, cfg, torch.Generator().manual_seed(3), volume)
        loss = coeff[0] * out.depth.sum() + coeff[1] * out.semantics.square().sum() + coeff[2] * out.weight_sum.sum()
        loss.backward()
        results.append((out.depth, out.semantics, out.weight_sum, out.t_samples, d.grad, lg.grad))
    for fast, ref in zip(*results):
        scale = max(1.0, float(ref.detach().abs().max()))
        assert float((fast - ref).detach().abs().max()) <= tol * scale


def test_numba_rendering_whose_semantics_no_loss_reads_leaves_the_logits_without_a_gradient():
    # a free ray's opacity alone (the free-space terms): the logits get no gradient at all, and σ's gradient is the
    # one with the semantics read at weight zero (the semantic term adds exact zeros: the same sums, bit for bit)
    density, logits, origins, dirs, volume = _random_case()
    cfg = RenderConfig(far=12.0, grid=SMALL, lookup="numba")
    grads = []
    for semantics_weight in (None, 0.0):
        d, lg = density.clone().requires_grad_(True), logits.clone().requires_grad_(True)
        out = render_rays(d, lg, origins, dirs, cfg, torch.Generator().manual_seed(3), volume)
        loss = out.weight_sum.square().sum() + 0.5 * out.depth.sum()
        if semantics_weight is not None:
            loss = loss + semantics_weight * out.semantics.sum()
        loss.backward()
        grads.append((d.grad, lg.grad))
    (sigma_alone, logits_alone), (sigma_read, logits_read) = grads
    assert logits_alone is None
    assert torch.count_nonzero(logits_read) == 0
    assert torch.count_nonzero(sigma_alone) > 0 and torch.equal(sigma_alone, sigma_read)


@pytest.mark.parametrize("stratified,uniform_mix", [(False, 0.0), (True, 0.2)])
def test_numba_path_is_bit_identical_for_any_thread_count(stratified, uniform_mix):
    # the kernels split rays (forward) and voxel slabs (gradient scatter) across threads; no sum may depend on it
    grid = Grid(lower=(-4.0, -4.0, -1.0), upper=(12.0, 4.0, 2.2), voxel_size=0.4, shape=(40, 20, 8))
    gen = torch.Generator().manual_seed(5)
    density = torch.rand(3, *grid.shape, generator=gen)
    logits = torch.randn(3, *grid.shape, NUM_CLASSES, generator=gen)
    origins = (torch.rand(300, 3, generator=gen) - 0.5) * torch.tensor([10.0, 6.0, 2.0])
    dirs = torch.nn.functional.normalize(torch.randn(300, 3, generator=gen), dim=1)
    volume = torch.randint(0, 3, (300,), generator=gen)
    results = []
    for threads in (1, 2, 3):
        d, lg = density.clone().requires_grad_(True), logits.clone().requires_grad_(True)
        cfg = RenderConfig(far=15.0, grid=grid, lookup="numba", threads=threads, fine_stratified=stratified,
                           uniform_mix=uniform_mix)
        out = render_rays(d, lg, origins, dirs, cfg, torch.Generator().manual_seed(3), volume)
        (out.depth.sum() + out.semantics.square().sum() + out.weight_sum.sum()).backward()
        results.append((out.depth, out.semantics, out.t_samples, d.grad, lg.grad))
    for other in results[1:]:   # exact: the property tested (each sum runs in one thread, in one order)
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_auto_lookup_renders_cpu_tensors_with_numba(monkeypatch):
    from occflownet.render import numba_render
    calls = []
    original = numba_render.NumbaRender.apply
    monkeypatch.setattr(numba_render.NumbaRender, "apply", lambda *a: calls.append(1) or original(*a))
    density, logits, origins, dirs, volume = _random_case(n_rays=4)
    render_rays(density, logits, origins, dirs, RenderConfig(grid=SMALL), batch_index=volume)
    assert calls == [1]
    render_rays(density, logits, origins, dirs, RenderConfig(grid=SMALL, lookup="grid_sample"), batch_index=volume)
    assert calls == [1]


def test_auto_lookup_without_numba_falls_back_to_grid_sample_with_a_warning(monkeypatch):
    import sys
    density, logits, origins, dirs, volume = _random_case(n_rays=8)
    expected = render_rays(density, logits, origins, dirs, RenderConfig(grid=SMALL, lookup="grid_sample"),
                           torch.Generator().manual_seed(1), volume)
    monkeypatch.setitem(sys.modules, "numba", None)  # makes `import numba` raise ImportError
    with pytest.warns(UserWarning, match="numba is not installed"):
        out = render_rays(density, logits, origins, dirs, RenderConfig(grid=SMALL), torch.Generator().manual_seed(1),
                          volume)
    assert torch.equal(out.depth, expected.depth)            # exact: the fallback runs the same grid_sample path


def test_batch_index_selects_the_volume():
    density, logits = _slab(15, 15, cls=5)
    empty = torch.zeros_like(density)
    origins, dirs = _ray_along_x(2)
    cfg = RenderConfig(far=10.0, density_scale=50.0, grid=SMALL)
    out = render_rays(torch.stack([empty, density]), torch.stack([logits, logits]), origins, dirs, cfg,
                      torch.Generator().manual_seed(0), torch.tensor([0, 1]))
    assert out.weight_sum[0] == 0 and out.weight_sum[1] > 0.99


@pytest.mark.parametrize("lookup", ["numba", "grid_sample"])
def test_shared_logits_render_as_their_copies(lookup):
    """logits_index: three density volumes reading two logits volumes render the same values, and the shared
    logits get the summed gradients of the copies, as rendering through logits[logits_index] copied."""
    density, logits, origins, dirs, volume = _random_case(dtype=torch.float64)      # 2 volumes of each
    density = torch.cat([density, density[:1] * 0.5])                               # a third density volume ...
    volume = torch.remainder(torch.arange(len(volume)), 3)
    index = torch.tensor([0, 1, 0])                                                  # ... reading logits volume 0
    cfg = RenderConfig(far=12.0, grid=SMALL, lookup=lookup, density_scale=1.5)
    results = []
    for shared in (True, False):
        d, lg = density.clone().requires_grad_(True), logits.clone().requires_grad_(True)
        out = render_rays(d, lg if shared else lg[index], origins, dirs, cfg, torch.Generator().manual_seed(3),
                          volume, logits_index=index if shared else None)
        (out.depth.sum() + out.semantics.square().sum() + out.weight_sum.sum()).backward()
        results.append((out.depth, out.semantics, out.weight_sum, d.grad, lg.grad))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="logits_index"):
        render_rays(density, logits, origins, dirs, cfg, batch_index=volume)         # 3 density, 2 logits volumes
    with pytest.raises(ValueError, match="logits_index values"):
        render_rays(density, logits, origins, dirs, cfg, batch_index=volume, logits_index=torch.tensor([0, 1, 2]))


@pytest.mark.parametrize("lookup", ["numba", "grid_sample"])
def test_logits_as_rows_of_the_footprint_render_as_the_whole_volume(lookup):
    """logits_rows: the logits given as a table of the rays' footprint only (occflownet.render.footprint), two
    density volumes sharing logits volume 0 and a third reading volume 1, render the same depths, semantics and
    weights as the whole logits volumes, with the same gradients; the whole volumes' logits get no gradient off
    the footprint."""
    from occflownet.render.footprint import ray_footprint

    density, logits, origins, dirs, volume = _random_case(dtype=torch.float64, n_rays=60)
    density = torch.cat([density, density[:1] * 0.5])
    volume = torch.remainder(torch.arange(len(volume)), 3)
    index = torch.tensor([0, 1, 0])
    cfg = RenderConfig(far=6.0, grid=SMALL, lookup=lookup, density_scale=1.5)
    mask = np.zeros((2, *SMALL.shape), dtype=bool)
    for v in range(3):
        mine = (volume == v).numpy()
        mask[int(index[v])] |= ray_footprint(origins[mine].numpy(), dirs[mine].numpy(), cfg.far, SMALL)
    rows = torch.from_numpy(np.flatnonzero(mask))
    assert 0.05 < mask.mean() < 0.8                                  # the footprint is a part of the volumes
    table = torch.full((mask.size,), -1, dtype=torch.long)
    table[rows] = torch.arange(len(rows))
    results = []
    for as_rows in (False, True):
        d, lg = density.clone().requires_grad_(True), logits.clone().requires_grad_(True)
        given = lg.reshape(-1, NUM_CLASSES)[rows] if as_rows else lg
        out = render_rays(d, given, origins, dirs, cfg, torch.Generator().manual_seed(3), volume,
                          logits_index=index, logits_rows=table if as_rows else None)
        (out.depth.sum() + out.semantics.square().sum() + out.weight_sum.sum()).backward()
        results.append((out.depth, out.semantics, out.weight_sum, d.grad, lg.grad))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    whole_grad = results[0][4].reshape(-1, NUM_CLASSES)
    assert whole_grad.abs().sum() > 0 and not whole_grad[torch.from_numpy(~mask.reshape(-1))].any()
    with pytest.raises(ValueError, match="logits_rows values"):
        render_rays(density, logits.reshape(-1, NUM_CLASSES)[rows], origins, dirs, cfg, batch_index=volume,
                    logits_index=index, logits_rows=torch.where(table >= 0, table + 1, table))
    with pytest.raises(ValueError, match=r"must be \[K, C\]"):
        render_rays(density, logits, origins, dirs, cfg, batch_index=volume, logits_index=index, logits_rows=table)


def test_bad_inputs_are_rejected_with_clear_errors():
    density, logits, origins, dirs, volume = _random_case(n_rays=5)
    cfg = RenderConfig(grid=SMALL)
    with pytest.raises(ValueError, match="batch_index"):
        render_rays(density, logits, origins, dirs, cfg)
    with pytest.raises(ValueError, match="batch_index values"):
        render_rays(density, logits, origins, dirs, cfg, batch_index=torch.full((5,), 2))
    with pytest.raises(ValueError, match="density must be"):
        render_rays(density[:, :10], logits, origins, dirs, cfg, batch_index=volume)
    with pytest.raises(ValueError, match="origins and directions"):
        render_rays(density, logits, origins[:, :2], dirs, cfg, batch_index=volume)
    with pytest.raises(ValueError, match="lookup"):
        RenderConfig(lookup="nearest")


def test_depth_loss_fits_a_free_volume_to_an_analytic_scan():
    """Adam on the raw grid, depth MSE only: a wall at x = 6 m and the ground at z = -0.6 m, camera at z = 0.6."""
    grid = Grid(lower=(-8.0, -8.0, -1.0), upper=(8.0, 8.0, 2.2), voxel_size=0.4, shape=(40, 40, 8))
    gen = torch.Generator().manual_seed(0)
    n_wall, n_ground = 1536, 512
    wall = torch.stack([torch.full((n_wall,), 6.0), torch.rand(n_wall, generator=gen) * 10 - 5,
                        torch.rand(n_wall, generator=gen) * 2.4 - 0.5], -1)
    ground = torch.stack([torch.rand(n_ground, generator=gen) * 4 + 1.5, torch.rand(n_ground, generator=gen) * 6 - 3,
                          torch.full((n_ground,), -0.6)], -1)
    targets = torch.cat([wall, ground])
    origin = torch.tensor([0.0, 0.0, 0.6])
    offsets = targets - origin
    depth_gt = offsets.norm(dim=-1)
    dirs = offsets / depth_gt[:, None]
    origins = origin.expand_as(dirs)
    raw = torch.full((1, *grid.shape), -3.0, requires_grad=True)  # σ ≈ 0.05 everywhere: a free volume
    logits = torch.zeros(1, *grid.shape, NUM_CLASSES)
    cfg = RenderConfig(far=12.0, grid=grid)
    opt = torch.optim.Adam([raw], lr=0.3)

    def mean_error():
        with torch.no_grad():
            out = render_rays(torch.sigmoid(raw), logits, origins, dirs, cfg, torch.Generator().manual_seed(1))
        return float((out.depth - depth_gt).abs().mean())

    start = mean_error()
    for _ in range(200):
        pick = torch.randint(0, len(dirs), (256,), generator=gen)
        out = render_rays(torch.sigmoid(raw), logits, origins[pick], dirs[pick], cfg, gen)
        loss = ((out.depth - depth_gt[pick]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    end = mean_error()
    assert start > 2.0 and end < 0.5, (start, end)


def test_numba_kernels_leave_torch_thread_count_alone():
    """numba's OpenMP layer raises torch's intra-op threads to its own count when it starts; the renderer's thread
    context restores it, so every training step of a process runs torch with the same threads (exact resume)."""
    import os
    import subprocess
    import sys

    code = """
import numba, numpy as np, torch
from occflownet.render.numba_render import numba_threads
before = torch.get_num_threads()
@numba.njit(parallel=True)
def total(a):
    s = 0.0
    for i in numba.prange(a.shape[0]):
        s += a[i]
    return s
with numba_threads(0):
    total(np.ones(1000))
assert torch.get_num_threads() == before == 1, (before, torch.get_num_threads(), numba.threading_layer())
"""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "2"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)


def test_opacity_reading_makes_one_voxel_opaque_and_keeps_the_density_reading_official():
    # one voxel at σ = 0.999: read as a density (official) it stops about 1 - exp(-0.4 · 0.999) ≈ 33 % of the light
    # (more in the rendered sum, whose intervals around the surface samples stretch into the empty space before
    # it); read as an opacity it stops 99.9 %, and the depth is its near face (5.0 m), within a voxel
    density, logits = _slab(15, 15, cls=5)
    density = density * 0.999
    origins, dirs = _ray_along_x()
    official = render_rays(density, logits, origins, dirs, RenderConfig(far=10.0, grid=SMALL),
                           torch.Generator().manual_seed(0))
    opaque = render_rays(density, logits, origins, dirs, RenderConfig(far=10.0, grid=SMALL, sigma_is="opacity"),
                         torch.Generator().manual_seed(0))
    assert torch.all(official.weight_sum < 0.7), official.weight_sum
    assert torch.all(opaque.weight_sum > 0.99) and torch.all((opaque.depth - 5.0).abs() < 0.4), opaque.depth
    # half a voxel's opacity keeps half the light over one voxel length: σ = 0.5 in a 3-voxel slab → 1 - 0.5³
    # (uniform fine samples every 2.5 cm, so that the rendered sum is the integral)
    density, logits = _slab(12, 14, cls=5)
    half = render_rays(density * 0.5, logits, origins, dirs, RenderConfig(far=10.0, grid=SMALL, sigma_is="opacity",
                                                                          uniform_mix=1.0, n_fine=400))
    assert torch.all((half.weight_sum - 0.875).abs() < 0.03), half.weight_sum
    with pytest.raises(ValueError, match="sigma_is"):
        RenderConfig(sigma_is="alpha")


def test_opacity_reading_numba_matches_grid_sample_values_and_gradients():
    g = torch.Generator().manual_seed(3)
    density = (torch.rand(SMALL.shape, generator=g, dtype=torch.float64) ** 4).requires_grad_()
    logits = torch.randn(*SMALL.shape, NUM_CLASSES, generator=g, dtype=torch.float64).requires_grad_()
    origins = torch.tensor([[-3.0, 0.1, 0.3]], dtype=torch.float64).repeat(16, 1)
    dirs = torch.randn(16, 3, generator=g, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=1, keepdim=True)
    grads = {}
    for lookup in ("numba", "grid_sample"):
        out = render_rays(density, logits, origins, dirs, RenderConfig(far=8.0, grid=SMALL, lookup=lookup,
                                                                       sigma_is="opacity"),
                          torch.Generator().manual_seed(1))
        gd, gl = torch.autograd.grad(out.depth.sum() + 0.3 * out.semantics.sum(), (density, logits))
        grads[lookup] = (out.depth.detach(), gd, gl)
    for a, b in zip(grads["numba"], grads["grid_sample"]):
        assert torch.allclose(a, b, atol=1e-9, rtol=1e-7)
    assert float(grads["numba"][1].abs().max()) > 0


@pytest.mark.parametrize("lookup", ["numba", "grid_sample"])
def test_per_ray_far_renders_each_ray_as_its_own_far_would(lookup):
    """``far`` [R] gives every ray its own far end: the same render as RenderConfig(far=f) ray by ray, and on the
    slab from 5 m a segment that stops before it is transparent while one that enters it 1 m absorbs."""
    density, logits, origins, dirs, volume = _random_case(n_rays=6)
    fars = torch.tensor([1.0, 3.5, 6.0, 8.0, 12.0, 2.2])
    out = render_rays(density, logits, origins, dirs, RenderConfig(grid=SMALL, lookup=lookup, uniform_mix=0.2),
                      torch.Generator().manual_seed(3), volume, far=fars)
    for r, f in enumerate(fars.tolist()):
        # the same jitter draws: the generator is consumed per batch, so render the batch with a scalar far
        one = render_rays(density, logits, origins, dirs, RenderConfig(far=f, grid=SMALL, lookup=lookup,
                                                                       uniform_mix=0.2),
                          torch.Generator().manual_seed(3), volume)
        for name in ("depth", "weight_sum", "semantics", "t_ends"):
            torch.testing.assert_close(getattr(out, name)[r], getattr(one, name)[r], rtol=1e-5, atol=1e-5)
        assert float(out.t_ends[r].max()) <= f + 1e-5
    slab, slab_logits = _slab(15, 19, cls=3)                       # σ = 1 from x = 2.0 m, i.e. 5 m along the ray
    o, d = _ray_along_x(2)
    seg = render_rays(slab, slab_logits, o, d, RenderConfig(grid=SMALL, lookup=lookup),
                      torch.Generator().manual_seed(1), far=torch.tensor([4.6, 6.0]))
    assert float(seg.weight_sum[0]) < 0.01
    assert 0.45 < float(seg.weight_sum[1]) < 0.75                  # 1 − e^{−1} = 0.63 over 1 m of σ = 1
    with pytest.raises(ValueError, match="per-ray far"):
        render_rays(slab, slab_logits, o, d, RenderConfig(grid=SMALL), far=torch.tensor([0.01, 5.0]))
