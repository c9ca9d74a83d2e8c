"""Differentiable volume rendering of the voxel volume (training only); import from the modules.

Modules: ``volume_render`` (RenderConfig, RenderOutput, render_rays, weights_from_density), ``sampling``
(coarse/fine distances along rays), ``numba_render`` + ``numba_kernels`` (the fast CPU path), ``lookup``
(grid_sample lookups: reference and GPU path), ``disocclusion``, ``occupancy_flow``.
"""
