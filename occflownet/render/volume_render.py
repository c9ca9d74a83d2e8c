"""Volume rendering of the predicted voxel volume along rays: coarse-to-fine sampling, weights, depth, semantics.

Inputs (one call renders a batch of rays through a batch of volumes):
- ``density`` σ: float [B, X, Y, Z] (or [X, Y, Z]) in [0, 1], the sigmoid output, in the grid ``cfg.grid``
  (default ``occ3d.GRID``; voxel (i,j,k) centre = lower + (ijk + 0.5) · voxel_size, ego frame);
- ``logits``: float [B, X, Y, Z, C] (or [X, Y, Z, C]) channels-last semantic logits (C = 17);
- ``origins``, ``directions``: float [R, 3] in the same ego frame; directions unit length;
- ``batch_index``: long [R] choosing the volume of each ray (needed when B > 1; the flow code passes a stacked
  [B·T, ...] volume and picks the copy per ray);
- ``logits_index``: long [B] (optional): the logits volume of each density volume, so that several density volumes
  (a frame's disoccluded copy beside the prediction) read one logits volume [B_l, X, Y, Z, C] without copying it;
  default: logits volume b for density volume b;
- ``logits_rows``: long [B_l·X·Y·Z] (optional): the logits are given as a table [K, C] instead, ``logits_rows`` the
  row of each voxel of the B_l logits volumes (flattened as [B_l, X, Y, Z]), -1 for a voxel without one (it reads
  zero logits): the voxels the rays can read are far fewer than the grid's (``occflownet.render.footprint``).

Method (paper section 3.4 and the official code):
1. coarse: ``n_coarse`` jittered uniform bins in [near, far]; σ looked up trilinearly (no gradient: the coarse
   pass only shapes the sampling, as in the official code where the proposal samples are detached);
2. fine: ``n_fine`` distances drawn from the coarse distribution by inverting the CDF ``1 - T`` at the coarse
   edges, ending at 1 (the official ``1 - cat([T_exclusive, 0])``: the transmitted light is drawn in the last bin;
   nerfacc's ``importance_sampling``, deterministic mid-bin draws unless ``fine_stratified``); the final render uses the
   fine samples only, as the official code does (not the union with the coarse samples);
3. σ_i and logits s_i by trilinear lookup at the fine samples (zero outside the grid); with intervals
   [a_i, b_i] around the samples, δ_i = b_i - a_i, τ_i = density_scale · σ_i · δ_i,
   T_i = exp(-Σ_{j<i} τ_j), w_i = T_i (1 - exp(-τ_i)); depth = Σ w_i (a_i + b_i)/2; semantics = Σ w_i s_i
   (raw logits; the softmax lives in the loss). Gradients flow to σ and the logits.

Two implementations compute the same numbers (``RenderConfig.lookup``): ``"numba"``, compiled CPU kernels with
a hand-written backward (``numba_render``), and ``"grid_sample"``, plain autograd through ``F.grid_sample``
(the reference, and the right choice on a GPU). ``"auto"`` (default) picks numba for CPU tensors and grid_sample
for CUDA ones.

``density_scale`` defaults to 1.0, the official behaviour (σ ∈ [0, 1] used directly as a density per metre).
With it a fully occupied voxel has optical depth 0.4 and lets ~67 % of the light through: see docs/training.md.

``sigma_is`` says how σ is read. ``"density"`` (default, official): σ is the extinction per metre, as above.
``"opacity"`` (beyond the paper; docs/tried.md): σ is the share of the light a voxel stops over one voxel length,
so a voxel can be opaque: each voxel's σ becomes the extinction ``-ln(1 - min(σ, OPACITY_CAP)) / voxel_size``
before the lookups (``opacity_to_extinction``); everything after (trilinear lookup, weights, ``density_scale``)
is unchanged. ``RenderOutput.sigma`` then holds the interpolated extinction.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from occflownet.choices import SIGMA_READINGS
from occflownet.occ3d import GRID, Grid
from occflownet.render.lookup import grid_sample_lookup
from occflownet.render.sampling import cdf_from_sigma, importance_sample, intervals_from_samples, \
    uniform_jittered_edges

LOOKUPS = ("auto", "numba", "grid_sample")
OPACITY_CAP = 0.999                       # opacity reading: σ above this stops 99.9 % of the light (17.3 /m at 0.4 m)


def opacity_to_extinction(opacity: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Per-voxel opacity α ∈ [0, 1] (any shape) → extinction per metre ``-ln(1 - min(α, OPACITY_CAP)) / voxel_size``:
    a ray crossing one voxel length of it keeps ``1 - α`` of its light. Differentiable (the cap stops the gradient
    above it)."""
    return -torch.log1p(-opacity.clamp(max=OPACITY_CAP)) / voxel_size


@dataclass(frozen=True)
class RenderConfig:
    """Ray rendering settings; defaults are the official OccFlowNet values (docs/training.md)."""

    near: float = 0.05              # metres along the ray
    far: float = 40.0
    n_coarse: int = 50              # jittered uniform samples for the coarse (sampling-only) pass
    n_fine: int = 100               # importance samples that are rendered
    density_scale: float = 1.0      # τ = density_scale · σ · δ; 1.0 = official (σ unscaled)
    coarse_jitter: bool = True      # jitter the coarse bin edges (official: always, also at test time)
    fine_stratified: bool = False   # one U(0,1) offset per ray for the fine draws (official: False, mid-bin)
    uniform_mix: float = 0.0        # mix this fraction of a uniform pdf into the fine pdf (official: 0)
    lookup: str = "auto"            # "numba" (CPU kernels), "grid_sample" (reference, GPU) or "auto" (by device)
    sigma_is: str = "density"       # "density" (official: σ per metre) or "opacity" (σ per voxel; see above)
    threads: int = 0                # numba threads (0: all cores); results do not depend on it
    grid: Grid = GRID

    def __post_init__(self):
        if not (0.0 <= self.near < self.far):
            raise ValueError(f"RenderConfig: need 0 <= near < far, got near={self.near}, far={self.far}")
        if self.n_coarse < 1 or self.n_fine < 2:
            raise ValueError(f"RenderConfig: need n_coarse >= 1 and n_fine >= 2, got {self.n_coarse}, {self.n_fine}")
        if self.density_scale <= 0:
            raise ValueError(f"RenderConfig.density_scale must be > 0, got {self.density_scale}")
        if not 0.0 <= self.uniform_mix <= 1.0:
            raise ValueError(f"RenderConfig.uniform_mix must be in [0, 1], got {self.uniform_mix}")
        if self.threads < 0:
            raise ValueError(f"RenderConfig.threads must be >= 0, got {self.threads}")
        if self.lookup not in LOOKUPS:
            raise ValueError(f"RenderConfig.lookup must be one of {LOOKUPS}, got {self.lookup!r}")
        if self.sigma_is not in SIGMA_READINGS:
            raise ValueError(f"RenderConfig.sigma_is must be one of {SIGMA_READINGS}, got {self.sigma_is!r}")


@dataclass
class RenderOutput:
    """Per-ray results. R rays, N = n_fine samples per ray, C logit channels."""

    depth: torch.Tensor        # [R] Σ w_i t_i, metres along the ray (not normalised by weight_sum)
    semantics: torch.Tensor    # [R, C] Σ w_i s_i, raw logit mixture
    weight_sum: torch.Tensor   # [R] Σ w_i = 1 - T_final ∈ [0, 1]
    weights: torch.Tensor      # [R, N] w_i
    sigma: torch.Tensor        # [R, N] σ_i at the fine samples (before density_scale; extinction when sigma_is="opacity")
    t_samples: torch.Tensor    # [R, N] sample distances (where σ and logits are looked up)
    t_starts: torch.Tensor     # [R, N] interval starts a_i
    t_ends: torch.Tensor       # [R, N] interval ends b_i


def weights_from_density(sigma: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Volume rendering weights along rays: all [R, N] → (weights, transmittance T_i, alpha_i).

    τ_i = σ_i (b_i - a_i); T_i = exp(-Σ_{j<i} τ_j); alpha_i = 1 - exp(-τ_i); w_i = T_i · alpha_i
    (the same definition as nerfacc's ``render_weight_from_density``). Multiply σ by a density scale first.
    """
    tau = sigma * (t_ends - t_starts)
    excl = torch.cumsum(tau, dim=-1) - tau
    transmittance = torch.exp(-excl)
    alpha = 1.0 - torch.exp(-tau)
    return transmittance * alpha, transmittance, alpha


def _check_logits_index(logits_index, n_density: int, n_logits: int, device) -> torch.Tensor:
    """logits_index long [n_density] (None: 0..n-1, which needs as many logits volumes as density volumes)."""
    if logits_index is None:
        if n_logits != n_density:
            raise ValueError(f"logits hold {n_logits} volumes for {n_density} density volumes: pass logits_index")
        return torch.arange(n_density, device=device)
    if logits_index.shape != (n_density,) or logits_index.dtype.is_floating_point or logits_index.dtype == torch.bool:
        raise ValueError(f"logits_index must be an integer [{n_density}], got {logits_index.dtype} "
                         f"{tuple(logits_index.shape)}")
    if int(logits_index.min()) < 0 or int(logits_index.max()) >= n_logits:
        raise ValueError(f"logits_index values must lie in [0, {n_logits})")
    return logits_index.long().to(device)


def _check_inputs(density, logits, origins, directions, batch_index, grid: Grid, logits_rows=None):
    if density.dim() == 3:
        density = density.unsqueeze(0)
    if logits.dim() == 4 and logits_rows is None:
        logits = logits.unsqueeze(0)
    if density.dim() != 4 or tuple(density.shape[1:]) != tuple(grid.shape):
        raise ValueError(f"density must be [B, {', '.join(map(str, grid.shape))}], got {tuple(density.shape)}")
    if logits_rows is not None:
        n_logits = _check_logits_rows(logits, logits_rows, grid)
    elif logits.dim() != 5 or tuple(logits.shape[1:4]) != tuple(density.shape[1:]):
        raise ValueError(f"logits must be [B, X, Y, Z, C] on density's grid {tuple(density.shape[1:])}, "
                         f"got {tuple(logits.shape)}")
    else:
        n_logits = logits.shape[0]
    if origins.dim() != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both be [R, 3], got {tuple(origins.shape)} and "
                         f"{tuple(directions.shape)}")
    n_vol, n_rays = density.shape[0], origins.shape[0]
    if batch_index is None:
        if n_vol != 1:
            raise ValueError(f"batch_index [R] is required when rendering {n_vol} volumes")
        batch_index = torch.zeros(n_rays, dtype=torch.long, device=origins.device)
    else:
        if batch_index.shape != (n_rays,):
            raise ValueError(f"batch_index must be [R] = [{n_rays}], got {tuple(batch_index.shape)}")
        if batch_index.dtype.is_floating_point or batch_index.dtype == torch.bool:
            raise ValueError(f"batch_index must be an integer tensor, got {batch_index.dtype}")
        batch_index = batch_index.long()
        if n_rays and (int(batch_index.min()) < 0 or int(batch_index.max()) >= n_vol):
            raise ValueError(f"batch_index values must lie in [0, {n_vol}), got [{int(batch_index.min())}, "
                             f"{int(batch_index.max())}]")
    return density, batch_index, n_logits


def _check_logits_rows(logits: torch.Tensor, rows: torch.Tensor, grid: Grid) -> int:
    """Checks a logits table [K, C] and its ``logits_rows`` [B_l·X·Y·Z] (module docstring) → B_l."""
    if logits.dim() != 2:
        raise ValueError(f"logits given with logits_rows must be [K, C], got {tuple(logits.shape)}")
    if rows.dim() != 1 or rows.numel() % grid.num_voxels or rows.dtype.is_floating_point or rows.dtype == torch.bool:
        raise ValueError(f"logits_rows must be an integer [B_l·{grid.num_voxels}], got {rows.dtype} "
                         f"{tuple(rows.shape)}")
    if rows.numel() and (int(rows.min()) < -1 or int(rows.max()) >= logits.shape[0]):
        raise ValueError(f"logits_rows values must lie in [-1, {logits.shape[0]})")
    return rows.numel() // grid.num_voxels


def table_rows(table: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """table [K, C] (logits given with ``logits_rows``) at ``rows`` (long, any shape; -1: no row) → [..., C], zero
    where the row is -1; differentiable in ``table``."""
    padded = torch.cat([table, table.new_zeros(1, table.shape[1])])
    return padded[torch.where(rows >= 0, rows, table.shape[0]).long()]


def _dense_logits(logits: torch.Tensor, rows: torch.Tensor, grid: Grid) -> torch.Tensor:
    """logits [K, C] at ``rows`` [B_l·X·Y·Z] → [B_l, X, Y, Z, C] (zero where the row is -1), differentiable."""
    return table_rows(logits, rows).reshape(-1, *grid.shape, logits.shape[1])


def _use_numba(lookup: str, device: torch.device) -> bool:
    """Whether to render with the numba kernels: always for "numba" (CPU tensors only), for "auto" on CPU when
    numba is installed (it comes with the ``train`` extra; without it "auto" falls back to grid_sample)."""
    if lookup == "grid_sample":
        return False
    if lookup == "numba":
        if device.type != "cpu":
            raise ValueError(f"RenderConfig.lookup='numba' renders CPU tensors only, got {device.type} tensors; "
                             "use 'auto' or 'grid_sample'")
        return True
    if device.type != "cpu":
        return False
    try:
        import numba  # noqa: F401
    except ImportError:
        warnings.warn("numba is not installed: rendering on CPU with the slow grid_sample path "
                      "(pip install 'occflownet[train]' installs numba)", stacklevel=3)
        return False
    return True


def render_rays(density: torch.Tensor, logits: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor,
                cfg: RenderConfig = RenderConfig(), generator: torch.Generator | None = None,
                batch_index: torch.Tensor | None = None, far: torch.Tensor | None = None,
                logits_index: torch.Tensor | None = None, logits_rows: torch.Tensor | None = None) -> RenderOutput:
    """Render depth and semantic logits for R rays through the voxel volume(s); see the module docstring.

    density [B, X, Y, Z] or [X, Y, Z]; logits [B_l, X, Y, Z, C] or [X, Y, Z, C]; origins, directions [R, 3]
    (ego frame, unit directions); batch_index [R] long (required when B > 1); logits_index [B] long (the logits
    volume of each density volume; None: the same index, B_l = B); logits_rows [B_l·X·Y·Z] long: logits is a table
    [K, C] and this its row per voxel (module docstring); far [R] (metres, > ``cfg.near``):
    each ray's own far end instead of ``cfg.far`` (a segment: its weight sum is the opacity up to there).
    ``generator`` drives the coarse jitter (and stratified fine draws) for reproducible sampling.
    """
    grid = cfg.grid
    density, batch_index, n_logits = _check_inputs(density, logits, origins, directions, batch_index, grid,
                                                   logits_rows)
    logits = logits.unsqueeze(0) if logits.dim() == 4 else logits
    logits_index = _check_logits_index(logits_index, density.shape[0], n_logits, density.device)
    if cfg.sigma_is == "opacity":
        density = opacity_to_extinction(density, grid.voxel_size)
    n_rays, channels = origins.shape[0], logits.shape[-1]
    dtype, device = density.dtype, density.device
    origins = origins.detach().to(dtype)
    directions = directions.detach().to(dtype)

    if far is not None:
        far = far.detach().to(device=device, dtype=dtype)
    edges = uniform_jittered_edges(n_rays, cfg.n_coarse, cfg.near, cfg.far if far is None else far,
                                   jitter=cfg.coarse_jitter, generator=generator, device=device, dtype=dtype)
    if _use_numba(cfg.lookup, device):
        from occflownet.render.numba_render import NumbaRender
        if cfg.fine_stratified:
            bias = torch.rand((n_rays,), generator=generator, device=device, dtype=dtype)
        else:
            bias = torch.full((n_rays,), 0.5, device=device, dtype=dtype)
        depth, semantics, weight_sum, weights, sigma, t_samples, t_starts, t_ends = NumbaRender.apply(
            density, logits.reshape(-1, channels), origins, directions, edges, batch_index, logits_index[batch_index],
            bias, torch.full((n_rays,), float(cfg.far), dtype=torch.float64) if far is None else far, cfg,
            logits_rows)
        return RenderOutput(depth=depth, semantics=semantics, weight_sum=weight_sum, weights=weights, sigma=sigma,
                            t_samples=t_samples, t_starts=t_starts, t_ends=t_ends)

    if logits_rows is not None:
        logits = _dense_logits(logits, logits_rows, grid)
    return _render_grid_sample(density, logits, origins, directions, edges, batch_index, logits_index, far, cfg,
                               generator)


def _render_grid_sample(density, logits, origins, directions, edges, batch_index, logits_index, far, cfg,
                        generator) -> RenderOutput:
    """The reference path: plain autograd through F.grid_sample lookups (GPU; on CPU the tests' and benchmarks'
    reference). Arguments as :func:`render_rays` has checked them; logits [B_l, X, Y, Z, C]."""
    grid = cfg.grid
    with torch.no_grad():
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
        points = origins[:, None, :] + mids[..., None] * directions[:, None, :]
        coarse_sigma = grid_sample_lookup(density.unsqueeze(-1), points, batch_index, grid)[..., 0]
        cdf = cdf_from_sigma(edges, coarse_sigma, cfg, far)
        t_samples = importance_sample(edges, cdf, cfg.n_fine, stratified=cfg.fine_stratified,
                                      generator=generator)
        t_starts, t_ends = intervals_from_samples(t_samples, cfg.near, cfg.far if far is None else far[:, None])
        points = origins[:, None, :] + t_samples[..., None] * directions[:, None, :]
    volume = torch.cat([density.unsqueeze(-1), logits[logits_index]], dim=-1)
    values = grid_sample_lookup(volume, points, batch_index, grid)
    sigma = values[..., 0]
    weights, _, _ = weights_from_density(cfg.density_scale * sigma, t_starts, t_ends)
    semantics = torch.bmm(weights.unsqueeze(1), values[..., 1:]).squeeze(1)
    depth = (weights * (0.5 * (t_starts + t_ends))).sum(-1)
    return RenderOutput(depth=depth, semantics=semantics, weight_sum=weights.sum(-1), weights=weights,
                        sigma=sigma, t_samples=t_samples, t_starts=t_starts, t_ends=t_ends)
