"""Training configuration: one typed dataclass, built from a named recipe (``occflownet/train/recipes.py``).

`occflownet train` derives its options from the fields (``occflownet/options.py``: name, default, help, choices,
smallest value, ``--help`` group), so ``TrainConfig.from_recipe(name, preset=p, ...)`` from Python is the same run as
``occflownet train --recipe name --preset p ...``. The dataclass's defaults are the paper's *Base* setting as the
official code trains it (the ``paper`` recipe); every other recipe sets its values over them.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from occflownet.choices import (FLOW_MOVERS, FREE_STRETCH_RULES, HEAD_INITS, LR_SCHEDULES, PRECISIONS, PRESET_NAMES,
                                RAY_SAMPLINGS, SUPERVISION_MODES, supervision_parts)
from occflownet.options import check_fields, option
from occflownet.train.recipes import PRESET_SCHEDULES, RECIPE_NAMES, recipe

HEAD_INIT_CHOICES = ("", *HEAD_INITS)  # "" = the preset's

# The sections of `occflownet train --help`, in order. A recipe is what the fields of RECIPE_GROUPS add up to: a run
# that changes one of them is no longer the measured recipe (``recipe_changes``); the other groups say where and
# how long a run goes and what it writes.
RUN, MODEL, SUPERVISION, OPTIMISATION, OUTPUT, EXPERIMENTAL = ("data and run", "model", "supervision",
                                                               "optimisation", "output", "experimental")
GROUPS = (
    (RUN, "what to train on, for how long, where"),
    (MODEL, None),
    (SUPERVISION, "set by the recipe; changing one makes a combination that is not a measured recipe"),
    (OPTIMISATION, "set by the recipe and the preset; changing one makes a combination that is not a measured recipe"),
    (OUTPUT, None),
    (EXPERIMENTAL, "the parts the recipes are made of and research options; changing one makes a combination that is "
                   "not a measured recipe (docs/training.md)"),
)
RECIPE_GROUPS = (SUPERVISION, OPTIMISATION, EXPERIMENTAL)


@dataclass
class TrainConfig:
    """Everything a run needs to be reproduced; written into every checkpoint and ``RUN/train_config.json``.

    Build it from a recipe: ``TrainConfig.from_recipe("recommended", dataroot=..., out=...)``; the defaults alone are
    the paper's Base (the ``paper`` recipe). The fields of :data:`~occflownet.train.recipes.PRESET_SCHEDULES` (rays
    per step, lr, warm-up, EMA decay, checkpoint interval) default to None = the preset's value, filled in by
    ``__post_init__``: after construction every field holds a concrete value, and that is what checkpoints and
    ``train_config.json`` record. (``dataclasses.replace(cfg, preset=...)`` keeps the resolved values of the old
    preset; build a new config.)
    """

    recipe: str = option("paper", "the named recipe the run was built from (`occflownet recipes`)",
                         choices=RECIPE_NAMES, group=RUN)
    dataroot: str = option("", "nuScenes-format root (run `occflownet prepare` on it first)", group=RUN)
    version: str = option("v1.0-trainval", "table version folder (on the command line, default: the only one in "
                                           "the root)", group=RUN)
    split: str = option("train", "split of the index to train on", group=RUN)
    seed: int = option(0, "seed of the weights, the sampling and the rays", group=RUN)
    max_steps: int = option(1000, "optimisation steps", minimum=1, group=RUN)
    time_limit_s: float = option(0.0, "stop with a checkpoint after this many seconds (0: no limit)",
                                 flag="time-limit", minimum=0, group=RUN)
    device: str = option("auto", "torch device (auto: CUDA when available)", group=RUN)
    num_workers: int = option(2, "data loader processes", minimum=0, group=RUN)

    preset: str = option("tiny", "model preset and its optimisation values", choices=PRESET_NAMES, group=MODEL)
    threshold: float | None = option(None, "τ stored with the model (default 0.35 for 2d, 0.30 with 3D labels)",
                                     minimum=0, group=MODEL)

    supervision: str = option("2d", "2d: rendering of LiDAR rays; 3d: Occ3D voxel labels; 2d+3d: both",
                              choices=SUPERVISION_MODES, group=SUPERVISION)
    horizon: int = option(3, "temporal frames t in [-O, O] (O = 0: no temporal rays)", minimum=0, group=SUPERVISION)
    flow: bool = option(False, "occupancy flow: render temporal rays through the moved dynamic voxels",
                        group=SUPERVISION)
    flow_mover: str = option("idw", "how moved voxels are written back onto the grid: idw (the paper's splat) or "
                                    "nearest (the official code's)", choices=FLOW_MOVERS, group=SUPERVISION)
    voxel_mask: bool = option(False, "3D voxel losses only inside mask_camera (off: every voxel, as the official "
                                     "code)", group=SUPERVISION)

    batch_size: int = option(1, "samples per process per step", minimum=1, group=OPTIMISATION)
    rays_per_step: int | None = option(None, "rays per sample per step (default: the preset's; official 32768)",
                                       minimum=1, group=OPTIMISATION)
    lr: float | None = option(None, "AdamW learning rate (default: the preset's)", minimum=0, group=OPTIMISATION)

    out: str = option("runs/tiny", "run folder: checkpoints/, log.jsonl, train_config.json", group=OUTPUT)
    checkpoint_every: int | None = option(None, "steps between checkpoints (default: the preset's)", minimum=1,
                                          group=OUTPUT)
    log_every: int = option(10, "steps between log records", minimum=1, group=OUTPUT)

    dynamic_filter: bool = option(True, "drop the rays of temporal frames t ≠ 0 that end on dynamic objects "
                                        "(not with --flow, which keeps and moves them)", group=EXPERIMENTAL)
    disocclusion: bool = option(True, "temporal frames render a copy with the predicted dynamic classes at σ = 0 "
                                      "(without --flow)", group=EXPERIMENTAL)
    loss_weighting: bool = option(True, "weight each ray's losses by ω(label) from prepare's class counts (off: "
                                        "uniform)", group=EXPERIMENTAL)
    depth_loss: bool = option(True, "rendered-depth MSE and LiDAR depth BCE (off: semantics only)",
                              group=EXPERIMENTAL)
    render_depth_weight: float = option(0.05, "weight of the rendered-depth MSE (0.05 = official)", minimum=0,
                                        group=EXPERIMENTAL)
    lidar_depth_weight: float = option(0.05, "weight of the LiDAR depth BCE on the LSS depth distribution (0.05 = "
                                             "official)", minimum=0, group=EXPERIMENTAL)
    image_semantics_weight: float = option(0.0, "weight of the CE of an image head on the stride-16 features (a 1x1 "
                                                "conv, training only) against the label of the nearest LiDAR point "
                                                "in each feature cell (0: off; beyond the paper)", minimum=0,
                                           group=EXPERIMENTAL)
    point_semantics_weight: float = option(0.0, "weight of the CE of the semantic logits of the voxel that holds each "
                                                "ray's LiDAR point (in its frame's volume) against the point's label "
                                                "(0: off, official; beyond the paper)", minimum=0, group=EXPERIMENTAL)
    point_density_weight: float = option(0.0, "weight of -log(sigma) of the voxel that holds each ray's LiDAR point "
                                              "(in its frame's volume): a return says its voxel is occupied (0: off, "
                                              "official; beyond the paper)", minimum=0, group=EXPERIMENTAL)
    voxel_scal_weight: float = option(0.0, "weight of the scene-class affinity terms on the 3D labels (MonoScene): "
                                           "-log precision, recall and specificity of occupancy (σ) and of each "
                                           "labelled class (σ·softmax) over the supervised voxels (0: off; beyond "
                                           "the paper)", minimum=0, group=EXPERIMENTAL)
    free_prior_weight: float = option(0.0, "weight of the mean -log(1 - sigma) over all voxels (0: off, official)",
                                      minimum=0, group=EXPERIMENTAL)
    free_space: bool = option(False, "also render LiDAR beams that returned nothing; their opacity goes to 0 "
                                     "(beyond the paper)", group=EXPERIMENTAL)
    free_beyond_grid: bool = option(False, "also render the camera rays to LiDAR points beyond the grid as free "
                                           "rays: the grid is empty along them (beyond the paper)",
                                    group=EXPERIMENTAL)
    box_line_of_sight: bool = option(False, "drop the rays (and free rays) that pass through an annotated object "
                                            "box before their point (beyond the paper)", group=EXPERIMENTAL)
    free_before_point: bool = option(False, "also render the stretch of each ray in front of its LiDAR point (up to "
                                            "where --free-stretch ends it) as free; its opacity goes to 0 (beyond "
                                            "the paper)", group=EXPERIMENTAL)
    free_stretch: str = option("fraction", "where --free-before-point's stretch ends: fraction = 0.8 depth - 0.6 m; "
                                           "points = where the ray first comes within a voxel of a LiDAR point of "
                                           "its frame; with it the free rays leave out the voxels within a voxel "
                                           "of a point (occflownet/data/free_stretch.py)",
                               choices=FREE_STRETCH_RULES, group=EXPERIMENTAL)
    free_rays_per_step: int = option(2048, "free rays per sample per step (with --free-space/--free-beyond-grid; "
                                           "--free-before-point renders as many of the rays' free stretches)",
                                     minimum=1, group=EXPERIMENTAL)
    free_space_weight: float = option(1.0, "weight of the free-space terms -log(1 - opacity)", minimum=0,
                                      group=EXPERIMENTAL)
    free_ramp_steps: int = option(0, "raise the weight of the free terms linearly from 0 to --free-space-weight "
                                     "over this many steps (0: full weight from the start; beyond the paper)",
                                  minimum=0, group=EXPERIMENTAL)
    ray_sampling: str = option("uniform", "how a step draws its rays: uniform (official) or sqrt-balanced (a ray of "
                                          "a class with n rays among the step's frames t in [-O, O] is drawn with probability ∝ 1/√n; "
                                          "beyond the paper)", choices=RAY_SAMPLINGS, group=EXPERIMENTAL)
    bev_flip: bool = option(False, "mirror each training sample's ego frame in x and in y, each with probability "
                                   "0.5 (the official recipe's BEV augmentation; occflownet/train/augment.py)",
                            group=EXPERIMENTAL)
    bev_rotate: bool = option(False, "turn each training sample's ego frame about z by 0, 90, 180 or 270 degrees "
                                     "(uniform), its cameras, rays, labels and box moves with it (beyond the paper; "
                                     "occflownet/train/augment.py)", group=EXPERIMENTAL)
    image_aug: bool = option(False, "warp each training image by a random resize, sideways shift, horizontal flip and "
                                    "rotation, its intrinsics with it (the official recipe's image augmentation; "
                                    "occflownet/train/augment.py)", group=EXPERIMENTAL)
    photometric_aug: bool = option(False, "jitter each training image's brightness, contrast and saturation, per "
                                          "camera (beyond the paper; occflownet/train/augment.py)", group=EXPERIMENTAL)
    head_init: str = option("", "σ/semantic head init: prior (σ ≈ 0.1 at the start) or official (Xavier, zero "
                                "bias); empty: the preset's", choices=HEAD_INIT_CHOICES, group=EXPERIMENTAL)
    lr_schedule: str = option("constant", "after the warm-up: constant (official) or a cosine decay to 0 at "
                                          "--max-steps (a resumed run decays over its new --max-steps)",
                              choices=LR_SCHEDULES, group=EXPERIMENTAL)
    weight_decay: float = option(1e-2, "AdamW weight decay", minimum=0, group=EXPERIMENTAL)
    grad_clip: float = option(5.0, "gradient norm clip", minimum=0, group=EXPERIMENTAL)
    warmup_steps: int | None = option(None, "linear warm-up steps (default: the preset's)", minimum=0,
                                      group=EXPERIMENTAL)
    ema_decay: float | None = option(None, "EMA decay of the weights (default: the preset's)", minimum=0,
                                     group=EXPERIMENTAL)
    precision: str = option("auto", "the network's arithmetic in training: auto = bf16 autocast on CUDA, float32 "
                                    "on CPUs; bf16 = bf16 autocast also on CPUs that compute it natively "
                                    "(1.4x faster a step, but less stable in long runs, docs/results.md#training-speed); fp32 = "
                                    "float32 everywhere. Rendering and losses stay float32", choices=PRECISIONS,
                            group=EXPERIMENTAL)

    def __post_init__(self):
        check_fields(self)                      # choices and smallest values, from the fields' metadata
        for name, value in PRESET_SCHEDULES[self.preset].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.ema_decay >= 1:
            raise ValueError(f"ema_decay must be below 1, got {self.ema_decay}")

    @classmethod
    def from_recipe(cls, name: str = "recommended", **overrides) -> "TrainConfig":
        """The configuration of recipe ``name`` (``occflownet/train/recipes.py``) with ``overrides`` (field: value)
        over its values. ValueError for an unknown recipe or field."""
        unknown = sorted(set(overrides) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"TrainConfig has no field {', '.join(unknown)}")
        return cls(**{**recipe(name).settings, **overrides, "recipe": name})

    @property
    def uses_3d(self) -> bool:
        """Whether the run is supervised by Occ3D voxel labels (it then stores the 3D-trained τ)."""
        return "3d" in supervision_parts(self.supervision)

    def resolved_threshold(self) -> float:
        if self.threshold is not None:
            return float(self.threshold)
        return 0.30 if self.uses_3d else 0.35

    def recipe_changes(self) -> dict[str, tuple[object, object]]:
        """{field: (the recipe's value, this run's value)} of the fields of :data:`RECIPE_GROUPS` where the run
        differs from its recipe (with the same preset): empty for a run that is the measured recipe."""
        mine = {f.name for f in fields(self) if f.metadata.get("group") in RECIPE_GROUPS}
        same = TrainConfig.from_recipe(self.recipe, **{k: v for k, v in self.to_dict().items()
                                                      if k not in mine and k != "recipe"})
        return {k: (getattr(same, k), getattr(self, k)) for k in sorted(mine) if getattr(same, k) != getattr(self, k)}

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The configuration a ``to_dict`` (or ``train_config.json``) recorded; keys of fields this version no
        longer has are ValueError when they hold anything but their off value, so a recorded run is never rerun
        as another one."""
        known = {f.name for f in fields(cls)}
        dropped = {k: v for k, v in d.items() if k not in known and v not in REMOVED_OFF.get(k, ())}
        if dropped:
            raise ValueError(f"the recorded configuration sets options this version does not have: {dropped}")
        return cls(**{k: v for k, v in d.items() if k in known})

    @classmethod
    def from_json(cls, path) -> "TrainConfig":
        """The configuration recorded in a run's ``train_config.json``; FileNotFoundError naming the file."""
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise FileNotFoundError(f"no such configuration file: {path}") from None
        try:
            return cls.from_dict(json.loads(text))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{path}: {exc}") from None


# Options of earlier versions, with the values that mean "off" (what a recorded run that did not use them holds):
# research knobs that no recipe used and that measured no gain (docs/tried.md).
REMOVED_OFF = {"density_scale": (1.0,), "sigma_is": ("density",), "render_semantics": ("mixture",),
               "density_logit_clip": (0.0,), "density_grad_floor": (0.0,), "voxel_weighting": ("none",)}
