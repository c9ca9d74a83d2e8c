"""Coarse/fine distances along rays (occflownet.render.sampling): known answers."""
from __future__ import annotations

import torch

from occflownet.render.sampling import cdf_from_sigma, importance_sample, intervals_from_samples, \
    uniform_jittered_edges


def test_uniform_edges_cover_near_far_and_stay_ordered():
    gen = torch.Generator().manual_seed(0)
    edges = uniform_jittered_edges(64, 50, 0.05, 40.0, generator=gen)
    assert edges.shape == (64, 51)
    assert torch.all(edges[:, 0] == 0.05) and torch.allclose(edges[:, -1], torch.full((64,), 40.0))
    assert torch.all(edges[:, 1:] > edges[:, :-1])
    step = (40.0 - 0.05) / 50
    regular = torch.linspace(0.05, 40.0, 51)
    offset = (edges - regular).abs()
    assert offset.max() <= 0.5 * step + 1e-5 and offset.max() > 0.1 * step  # jittered by at most half a bin
    plain = uniform_jittered_edges(3, 4, 1.0, 5.0, jitter=False)
    assert torch.allclose(plain, torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0]] * 3))


def test_linear_cdf_gives_mid_bin_uniform_samples():
    edges = torch.linspace(0.0, 10.0, 11).expand(2, 11)
    cdf = torch.linspace(0.0, 1.0, 11).expand(2, 11)
    t = importance_sample(edges, cdf, 5)
    assert torch.allclose(t, torch.tensor([[1.0, 3.0, 5.0, 7.0, 9.0]] * 2), atol=1e-5)


def test_samples_follow_the_mass_and_unnormalised_cdf_is_rescaled():
    edges = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]])
    # all the mass (0.3 of the ray: 1 - T_final = 0.3) in the bin [2, 3]
    cdf = torch.tensor([[0.0, 0.0, 0.0, 0.3, 0.3]])
    t = importance_sample(edges, cdf, 4)
    assert torch.allclose(t, torch.tensor([[2.125, 2.375, 2.625, 2.875]]), atol=1e-5)


def test_flat_cdf_puts_every_sample_at_the_last_bin_midpoint():
    edges = torch.tensor([[0.0, 1.0, 2.0, 4.0]])
    t = importance_sample(edges, torch.zeros(1, 4), 3)
    assert torch.allclose(t, torch.full((1, 3), 3.0))
    a, b = intervals_from_samples(t, 0.0, 4.0)
    assert torch.all(b - a == 0)  # zero-width intervals: such a ray renders nothing


def test_stratified_draws_stay_inside_their_strata():
    edges = torch.linspace(0.0, 1.0, 2).expand(100, 2)
    cdf = torch.tensor([[0.0, 1.0]]).expand(100, 2)
    t = importance_sample(edges, cdf, 4, stratified=True, generator=torch.Generator().manual_seed(3))
    strata = torch.floor(t * 4)                  # exact: t = (i + u) / 4, and / 4, * 4 are exact in binary
    assert torch.equal(strata, torch.arange(4.0).expand(100, 4))
    assert t[:, 0].std() > 0.05


def test_intervals_tile_between_samples():
    t = torch.tensor([[1.0, 2.0, 4.0, 5.0]])
    a, b = intervals_from_samples(t, 0.0, 5.2)
    assert torch.allclose(a, torch.tensor([[0.5, 1.5, 3.0, 4.5]]))
    assert torch.allclose(b, torch.tensor([[1.5, 3.0, 4.5, 5.2]]))  # last edge clamped to far
    assert torch.equal(a[:, 1:], b[:, :-1])      # exact: the interior edges are one tensor (the midpoints)


def test_cdf_is_the_official_one_built_from_nerfacc_transmittance():
    # The official renderer: trans = nerfacc.render_weight_from_density(starts, ends, σ)[1] (exclusive T per bin),
    # cdfs = 1 - cat([trans, 0]) — it ends at 1, so the last bin also holds the light that passes every bin.
    import pytest

    nerfacc = pytest.importorskip("nerfacc", reason="nerfacc (optional test dependency) is not installed")
    from occflownet.render.volume_render import RenderConfig

    gen = torch.Generator().manual_seed(0)
    edges = uniform_jittered_edges(64, 50, 0.05, 40.0, generator=gen)
    sigma = torch.where(torch.rand(64, 50, generator=gen) < 0.8, torch.zeros(64, 50), torch.rand(64, 50, generator=gen))
    _, trans, _ = nerfacc.render_weight_from_density(edges[:, :-1], edges[:, 1:], sigma)
    official = 1.0 - torch.cat([trans, torch.zeros_like(trans[:, :1])], dim=-1)
    ours = cdf_from_sigma(edges, sigma, RenderConfig())
    assert torch.allclose(ours, official, atol=1e-6)
    assert torch.all(ours[:, -1] == 1.0)
    # the transmitted mass T_M lies in the last bin: a ray through empty space draws every sample there
    t = importance_sample(edges[:1], cdf_from_sigma(edges[:1], torch.zeros(1, 50), RenderConfig()), 10)
    assert torch.all(t >= edges[0, -2]) and torch.all(t <= 40.0)


def test_nerfacc_documented_example():
    # nerfacc.importance_sampling's docstring: edges [0, 1] with cdf [0, 0.5] → samples [0.25, 0.75];
    # edges [0, 1, 2] with cdf [0, 0.5, 1] → samples [0.5, 1.5]
    t = importance_sample(torch.tensor([[0.0, 1.0]]), torch.tensor([[0.0, 0.5]]), 2)
    assert torch.allclose(t, torch.tensor([[0.25, 0.75]]))
    t = importance_sample(torch.tensor([[0.0, 1.0, 2.0]]), torch.tensor([[0.0, 0.5, 1.0]]), 2)
    assert torch.allclose(t, torch.tensor([[0.5, 1.5]]))
    a, b = intervals_from_samples(t, 0.0, 2.0)
    assert torch.allclose(torch.cat([a[:, :1], b], -1), torch.tensor([[0.0, 1.0, 2.0]]))
