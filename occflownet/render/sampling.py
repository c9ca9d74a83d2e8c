"""Distances along rays: jittered uniform bins (coarse pass) and inverse-CDF importance sampling (fine pass).

All functions work on batches of rays and distances in metres along unit-direction rays; nothing here looks at
the voxel volume. They follow the official OccFlowNet code (its ``UniformSampler`` and nerfacc 0.5's
``importance_sampling`` with ``stratified=False``) so that the training signal matches the paper's:

- coarse: ``n`` bins whose ``n + 1`` edges are ``linspace(near, far, n + 1)`` with every *interior* edge moved by
  U(-0.5, 0.5) bin widths (the ends stay at ``near`` and ``far``); samples at the bin midpoints;
- fine: ``n`` distances ``t_i = CDF⁻¹(u_i)`` with ``u_i = cdf_0 + (i + b) / n · (cdf_last - cdf_0)``, ``b = 0.5``
  (or one U(0, 1) draw per ray when stratified), the CDF being piecewise linear between the coarse edges;
  the fine *intervals* have edges half-way between consecutive samples, the first/last edge half a gap
  outside the first/last sample, clamped to [near, far].
"""
from __future__ import annotations

import torch


def uniform_jittered_edges(n_rays: int, n_bins: int, near: float, far, *, jitter: bool = True,
                           generator: torch.Generator | None = None, device=None,
                           dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Bin edges [n_rays, n_bins + 1] in metres, increasing, first = near, last = far (a float, or a tensor [R]:
    each ray's own far end).

    With ``jitter`` each interior edge is shifted by an independent U(-0.5, 0.5) · (far - near) / n_bins, so
    neighbouring bins never swap order and the union of the bins is exactly [near, far].
    """
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    if torch.is_tensor(far):
        if far.shape != (n_rays,) or not bool((far > near).all()):
            raise ValueError(f"per-ray far must be [{n_rays}] and greater than near ({near}) everywhere")
        far = far.to(device=device, dtype=dtype)[:, None]
    elif not far > near:
        raise ValueError(f"far ({far}) must be greater than near ({near})")
    unit = torch.linspace(0.0, 1.0, n_bins + 1, device=device, dtype=dtype).expand(n_rays, n_bins + 1)
    if jitter and n_bins > 1:
        noise = torch.rand((n_rays, n_bins - 1), generator=generator, device=device, dtype=dtype) - 0.5
        zeros = noise.new_zeros(n_rays, 1)
        unit = unit + torch.cat([zeros, noise / n_bins, zeros], dim=-1)
    return near + unit * (far - near)


def cdf_from_sigma(edges: torch.Tensor, sigma: torch.Tensor, cfg, far: torch.Tensor | None = None) -> torch.Tensor:
    """Coarse σ [R, M] at bins with edges [R, M + 1] → the fine-sampling CDF [R, M + 1], optionally mixed with a
    uniform CDF (``cfg``: a ``RenderConfig``; density_scale, uniform_mix, near, far; ``far`` [R]: per-ray far ends
    instead of ``cfg.far``).

    The official distribution (its renderer: ``cdfs = 1 - cat([T_exclusive, 0])``): ``1 - T_m`` at the first M
    edges (``T_m`` = transmittance at the start of bin m) and exactly 1 at the last edge, so the light that passes
    through every bin (``T_M``) is drawn in the last bin together with that bin's own absorption. A ray through
    empty space therefore samples its last bin, and a surface is never under-sampled for being thin.
    """
    tau = cfg.density_scale * sigma * (edges[:, 1:] - edges[:, :-1])
    cdf = 1.0 - torch.exp(-torch.cumsum(tau[:, :-1], dim=-1))
    cdf = torch.cat([cdf.new_zeros(cdf.shape[0], 1), cdf, cdf.new_ones(cdf.shape[0], 1)], dim=-1)
    if cfg.uniform_mix > 0:  # both CDFs end at 1, so the mixture is a CDF too
        far = cfg.far if far is None else far[:, None]
        uniform = (edges - cfg.near) / (far - cfg.near)
        cdf = (1.0 - cfg.uniform_mix) * cdf + cfg.uniform_mix * uniform
    return cdf


def importance_sample(edges: torch.Tensor, cdf: torch.Tensor, n_samples: int, *, stratified: bool = False,
                      generator: torch.Generator | None = None) -> torch.Tensor:
    """Distances [R, n_samples] drawn by inverting a piecewise-linear CDF, sorted along each ray.

    edges: [R, M + 1] increasing bin edges (metres). cdf: [R, M + 1] non-decreasing values at the edges
    (``1 - transmittance`` in the renderer; it need not end at 1: the draws cover [cdf_0, cdf_last]).
    A ray whose CDF is flat (``cdf_0 == cdf_last``) gets all samples at the midpoint of its last bin, as nerfacc
    does; the renderer then gives it zero-width intervals and zero weight. (``cdf_from_sigma`` always ends at 1, so
    the renderer never produces a flat CDF.)
    """
    if edges.shape != cdf.shape or edges.dim() != 2:
        raise ValueError(f"edges {tuple(edges.shape)} and cdf {tuple(cdf.shape)} must both be [R, M + 1]")
    n_rays, n_edges = edges.shape
    if stratified:
        bias = torch.rand((n_rays, 1), generator=generator, device=edges.device, dtype=edges.dtype)
    else:
        bias = edges.new_full((n_rays, 1), 0.5)
    steps = torch.arange(n_samples, device=edges.device, dtype=edges.dtype).unsqueeze(0)
    lo, hi = cdf[:, :1], cdf[:, -1:]
    u = lo + (steps + bias) * ((hi - lo) / n_samples)
    # searchsorted "right" over all but the last edge, as nerfacc's upper_bound(base, last): cdf[p-1] <= u < cdf[p]
    p = torch.searchsorted(cdf[:, :-1].contiguous(), u.contiguous(), right=True)
    p0 = (p - 1).clamp(0, n_edges - 1)
    p1 = p.clamp(0, n_edges - 1)
    u0, u1 = cdf.gather(1, p0), cdf.gather(1, p1)
    t0, t1 = edges.gather(1, p0), edges.gather(1, p1)
    du = u1 - u0
    flat = du < 1e-10
    frac = torch.where(flat, torch.full_like(u, 0.5), (u - u0) / torch.where(flat, torch.ones_like(du), du))
    return t0 + frac * (t1 - t0)


def intervals_from_samples(samples: torch.Tensor, near: float, far) -> tuple[torch.Tensor, torch.Tensor]:
    """Fine intervals around sorted samples [R, N] → (starts [R, N], ends [R, N]) in metres.

    Interior edges lie half-way between consecutive samples; the outer edges half a gap beyond the first and
    last sample, clamped to [near, far] (nerfacc's ``compute_intervels_kernel``; far a float or a tensor [R, 1]).
    Intervals tile a contiguous stretch of the ray, so ``ends[:, i] == starts[:, i + 1]``.
    """
    if samples.shape[-1] < 2:
        raise ValueError("intervals_from_samples needs at least 2 samples per ray")
    mids = 0.5 * (samples[:, 1:] + samples[:, :-1])
    first = (samples[:, :1] - 0.5 * (samples[:, 1:2] - samples[:, :1])).clamp(min=near)
    last = samples[:, -1:] + 0.5 * (samples[:, -1:] - samples[:, -2:-1])
    last = torch.minimum(last, far) if torch.is_tensor(far) else last.clamp(max=far)
    edges = torch.cat([first, mids, last], dim=-1)
    return edges[:, :-1], edges[:, 1:]
