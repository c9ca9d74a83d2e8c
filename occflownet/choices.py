"""The named choices of the configurations, each set defined once and torch-free: the command line
(``occflownet/options.py``), the configurations (``model/presets.py``, ``train/recipe.py``, ``quickstart.py``) and
their checks read these tuples (``tests/test_choices.py`` lists them and finds no second spelling).
"""
from __future__ import annotations

PRESET_NAMES: tuple[str, ...] = ("tiny", "small", "base", "paper")  # model presets (model/presets.py) and recipes
HEAD_INITS: tuple[str, ...] = ("prior", "official")         # σ/semantic head initialisations (model/decoder.py)
SUPERVISION_MODES: tuple[str, ...] = ("2d", "3d", "2d+3d")  # LiDAR rendering, Occ3D voxel labels, both
FLOW_MOVERS: tuple[str, ...] = ("idw", "nearest")           # occupancy-flow movers (render/occupancy_flow.py)
SIGMA_READINGS: tuple[str, ...] = ("density", "opacity")    # how rendering reads σ (render/volume_render.py)
RENDER_SEMANTICS: tuple[str, ...] = ("mixture", "normalized")  # CE on the rendered mixture or on it ÷ weight sum
LR_SCHEDULES: tuple[str, ...] = ("constant", "cosine")      # the learning rate after the warm-up (train/schedule.py)
INT8_RANGES: tuple[str, ...] = ("reduced", "full")          # int8 weights: 7-bit (any x86 CPU) or 8-bit (VNNI/AMX)
PRECISIONS: tuple[str, ...] = ("auto", "bf16", "fp32")     # training arithmetic of the network (train/loop.py)
FREE_STRETCH_RULES: tuple[str, ...] = ("fraction", "points")  # end of a ray's free stretch (data/free_stretch.py)
VOXEL_WEIGHTINGS: tuple[str, ...] = ("none", "sqrt-balanced")  # 3D density BCE per voxel (data/class_weights.py)
RAY_SAMPLINGS: tuple[str, ...] = ("uniform", "sqrt-balanced")  # how a step draws its rays (data/rays.py sample_rays)


def supervision_parts(mode: str) -> frozenset[str]:
    """The kinds of supervision a mode of :data:`SUPERVISION_MODES` combines: "2d+3d" → {"2d", "3d"}."""
    if mode not in SUPERVISION_MODES:
        raise ValueError(f"supervision must be one of {SUPERVISION_MODES}, got {mode!r}")
    return frozenset(mode.split("+"))
