"""The named training recipes: the one place a recipe is spelled. Data only (torch-free); a run is built from a name
by ``TrainConfig.from_recipe(name, **overrides)`` (``occflownet/train/recipe.py``) and on the command line by
``occflownet train --recipe NAME`` (default :data:`DEFAULT_RECIPE`); ``occflownet recipes`` lists them.

A recipe's ``settings`` are the :class:`~occflownet.train.recipe.TrainConfig` values it sets over the dataclass's
defaults, which are the paper's *Base* setting as the official code trains it (so ``paper`` sets nothing). The
recipes of the paper's ablation ladder carry their row (``ladder_row``; ``benchmarks/`` picks rows by it). What each
recipe scored, and on which protocol, is ``measured``, with the page of docs/ that holds the table (``source``);
``step_seconds`` is the cost of one ``tiny`` step (float32, 2 threads, the recipe's own rays a step) on the reference
machine, whose float32 matmul rate is :data:`REFERENCE_GFLOPS`, measured by ``benchmarks/perf/recipe_steps.py``
(docs/results.md#training-speed).

Also here: the optimisation values each model preset defaults to (:data:`PRESET_SCHEDULES`), which a recipe leaves
to the preset.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from occflownet.choices import PRESET_NAMES

# The optimisation values a TrainConfig field left at None takes, per model preset: the official values (AdamW
# 1e-4, 200 warm-up steps, 32,768 rays per sample) for base and paper; tiny and small learn something in a CPU run
# of minutes. One entry per name of PRESET_NAMES.
_CPU_SCHEDULE = {"rays_per_step": 4096, "lr": 2e-3, "warmup_steps": 50, "ema_decay": 0.99, "checkpoint_every": 50}
_OFFICIAL_SCHEDULE = {"rays_per_step": 32768, "lr": 1e-4, "warmup_steps": 200, "ema_decay": 0.999,
                      "checkpoint_every": 500}
PRESET_SCHEDULES: Mapping[str, Mapping[str, object]] = MappingProxyType(
    {"tiny": _CPU_SCHEDULE, "small": _CPU_SCHEDULE, "base": _OFFICIAL_SCHEDULE, "paper": _OFFICIAL_SCHEDULE})
assert tuple(PRESET_SCHEDULES) == PRESET_NAMES

REFERENCE_GFLOPS = 363.0   # float32 matmul 1024³, 2 threads, of the machine behind ``step_seconds``


@dataclass(frozen=True)
class Recipe:
    """One named recipe: ``settings`` {TrainConfig field: value} over the dataclass's defaults (the paper's Base),
    a one-line ``description``, what it ``supervises``, its figure (``measured``; None: not measured as spelled
    here) and the docs page behind it (``source``), its row in the paper's ablation ladder (or None), and the
    seconds of a ``tiny`` step on the reference machine (None: not measured)."""

    name: str
    description: str
    supervises: str
    settings: Mapping[str, object]
    measured: str | None
    source: str
    ladder_row: int | None = None
    step_seconds: float | None = None


# The parts the recipes are made of. The paper's ablation ladder (its Tables 1, 2 and 4): each row adds a component.
_NO_DYNAMICS = {"dynamic_filter": False, "disocclusion": False, "loss_weighting": False}
_ROW1 = {"supervision": "3d", "horizon": 0}
_ROW3 = {"horizon": 0, **_NO_DYNAMICS}
_ROW2 = {**_ROW3, "depth_loss": False}
_ROW4 = dict(_NO_DYNAMICS)
_ROW6 = {"flow": True}
# How this project renders rays (beyond the paper; what each part adds: docs/results.md#fitting-one-world): the
# stretch of each ray in front of its LiDAR point and the rays beyond the grid rendered as free (ramped in over 400
# steps), rays through annotated boxes dropped, rays drawn ∝ 1/√(their class's count), the point terms with a free
# prior of 2, no rendered-depth MSE, and flow's moved voxels written to the nearest voxel (the official code's
# mover).
_RENDERING = {
    "free_beyond_grid": True, "free_before_point": True, "free_stretch": "points", "box_line_of_sight": True,
    "free_ramp_steps": 400, "ray_sampling": "sqrt-balanced", "point_semantics_weight": 1.0,
    "point_density_weight": 1.0, "free_prior_weight": 2.0, "render_depth_weight": 0.0, "flow_mover": "nearest",
}
_LADDER = "docs/results.md#the-papers-ablation-ladder-on-one-world"
_FITTING = "docs/results.md#fitting-one-world"
_GENERALIZATION = "docs/results.md#the-generalization-benchmark"
_QUICKSTART = "docs/results.md#the-quickstart"
# Half the preset's rays per step for the quickstart: a cheaper step, so more steps in its minutes (equal time: higher
# on unseen scenes, docs/results.md#the-quickstart).
_QUICK_RAYS = {"rays_per_step": 2048, "free_rays_per_step": 1024}
_RAYS = "LiDAR rays rendered (2D)"
# The LiDAR points' classes on the image features (a training-only head; beyond the paper): higher on unseen scenes
# for both recipes that carry it (docs/results.md#the-generalization-benchmark, #the-quickstart).
_IMAGE_SEMANTICS = {"image_semantics_weight": 0.5}

_RECIPES = (
    Recipe("recommended", "the paper's method with flow, rendered as this project measured it fits best: free "
           "stretches, point terms, free prior, no rendered-depth MSE, nearest-voxel flow; and the LiDAR points' "
           "classes on the image features", _RAYS + ", O = 3, flow",
           {**_ROW6, **_RENDERING, **_IMAGE_SEMANTICS}, "18.6 ± 0.2 % val mIoU on unseen scenes (the generalization "
           "benchmark: K = 8, 1,200 steps, seeds 0-2; 13.0 ± 1.2 % without the image term); fitting a fresh world "
           "at 800 steps 1.30x / 1.34x the 3D labels' mIoU (seeds 0 / 1)", _GENERALIZATION, step_seconds=None),
    Recipe("quickstart", "the quickstart's minutes: 3D labels inside mask_camera with their class-affinity terms, "
           "the rendered rays of the current frame (O = 0) with the recommended rendering, and the LiDAR points' "
           "classes on the image features", "Occ3D labels in mask_camera + " + _RAYS + ", O = 0",
           {**_ROW3, **_RENDERING, "supervision": "2d+3d", "voxel_mask": True, **_QUICK_RAYS,
            "voxel_scal_weight": 0.5, **_IMAGE_SEMANTICS},
           "18.6 / 14.7 / 17.0 % val mIoU on the quickstart's val scene, 23.8 / 21.2 / 20.6 % on a 4-scene "
           "unseen world (`occflownet quickstart`, small, seeds 0 / 1 / 2: 15.1 / 19.4 % means without the image "
           "term the same day)", _QUICKSTART,
           step_seconds=0.202),
    Recipe("quickstart-3d", "3D labels inside mask_camera only: the cheapest step", "Occ3D labels in mask_camera",
           {**_ROW1, "voxel_mask": True}, "12.5 / 15.3 % val mIoU (the former 6 x 8 quickstart world, "
           "seeds 0 / 1), cars 6 / 5 %",
           _QUICKSTART, step_seconds=0.129),
    Recipe("paper-3d", "row 1 of the paper's ablation: Occ3D voxel labels on every voxel (official use_mask=False)",
           "Occ3D labels, every voxel", _ROW1, "45.8 / 42.9 % mIoU (1 × 8 world, 2,000 steps, seeds 0 / 1); 31.5 % "
           "at 800 steps on a fresh world", _FITTING,
           ladder_row=1),
    Recipe("paper-semantics", "row 2: rendered semantics only, the current frame, no depth in any term",
           _RAYS + ", semantics only", _ROW2,
           "0.3 % mIoU with the recommended rendering: the grid stays empty (1 × 8 world, 2,000 steps)", _LADDER,
           ladder_row=2),
    Recipe("paper-depth", "row 3: rendered semantics and depth, the current frame", _RAYS + ", O = 0", _ROW3,
           None, _LADDER, ladder_row=3),
    Recipe("paper-temporal", "row 4: + the rays of the frames t in [-3, 3]", _RAYS + ", O = 3", _ROW4,
           None, _LADDER, ladder_row=4),
    Recipe("paper", "row 5, the paper's Base as the official code trains it: + dynamic ray filter, disocclusion, "
           "loss weighting", _RAYS + ", O = 3", {}, "7.1 % mIoU (1 × 8 world, 800 steps)",
           _LADDER, ladder_row=5),
    Recipe("paper-flow", "row 6: + occupancy flow with the paper's inverse-distance splat", _RAYS + ", O = 3, flow",
           _ROW6, None, _LADDER, ladder_row=6),
    Recipe("paper-2d3d", "row 7: flow and 3D labels on every voxel", "Occ3D labels + " + _RAYS + ", O = 3, flow",
           {**_ROW6, "supervision": "2d+3d"}, None, _LADDER, ladder_row=7),
    Recipe("paper-free-space", "row 8 (beyond the paper): Base + LiDAR beams without a return rendered as free",
           _RAYS + " + free beams", {"free_space": True}, None, _LADDER, ladder_row=8),
    Recipe("paper-flow-free-space", "row 9 (beyond the paper): flow + LiDAR beams without a return rendered as free",
           _RAYS + " + free beams, flow", {**_ROW6, "free_space": True}, None, _LADDER,
           ladder_row=9),
)

RECIPES: Mapping[str, Recipe] = MappingProxyType({r.name: r for r in _RECIPES})
RECIPE_NAMES: tuple[str, ...] = tuple(RECIPES)
DEFAULT_RECIPE = "recommended"
# The rendering options the recommended recipe adds to the paper's rows: benchmarks/ runs the ladder with them
# ("the ladder with the recipe's rendering") by adding RENDERING to each row's settings.
RENDERING: Mapping[str, object] = MappingProxyType(_RENDERING)
# The image term the recipes set (benchmarks/ adds or removes it as a lever).
IMAGE_SEMANTICS: Mapping[str, object] = MappingProxyType(_IMAGE_SEMANTICS)


def recipe(name: str) -> Recipe:
    """The recipe called ``name``; ValueError listing the names otherwise."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; choose one of {', '.join(RECIPE_NAMES)} (`occflownet recipes`)")
    return RECIPES[name]


def ladder() -> dict[int, Recipe]:
    """{row: recipe} of the paper's ablation ladder (rows 1-7; 8 and 9 add free-space beams, beyond the paper)."""
    return {r.ladder_row: r for r in _RECIPES if r.ladder_row is not None}
