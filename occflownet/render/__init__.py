"""Differentiable volume rendering of the voxel volume (training only).

Import-light: names are loaded from their submodules on first use, so ``import occflownet.render`` pulls in
nothing heavy. Modules: ``volume_render`` (RenderConfig, RenderOutput, render_rays, weights_from_density),
``sampling`` (coarse/fine distances along rays), ``numba_render`` + ``numba_kernels`` (the fast CPU path),
``lookup`` (grid_sample lookups: reference and GPU path), ``disocclusion``, ``occupancy_flow``.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "RenderConfig": "volume_render",
    "RenderOutput": "volume_render",
    "render_rays": "volume_render",
    "weights_from_density": "volume_render",
    "disocclude": "disocclusion",
    "dynamic_mask": "disocclusion",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'occflownet.render' has no attribute {name!r}")
    return getattr(importlib.import_module(f"occflownet.render.{module}"), name)
