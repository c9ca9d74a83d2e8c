"""Training configuration: one typed dataclass and the per-preset recipes. `occflownet train` derives its options
from the fields (``occflownet/options.py``: name, default, help, choices), so ``TrainConfig(preset=p, ...)`` from
Python is the same run as ``occflownet train --preset p ...``."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from occflownet.choices import (FLOW_MOVERS, FREE_STRETCH_RULES, HEAD_INITS, LR_SCHEDULES, PRECISIONS, PRESET_NAMES,
                                RAY_SAMPLINGS, RENDER_SEMANTICS, SIGMA_READINGS, SUPERVISION_MODES, VOXEL_WEIGHTINGS,
                                supervision_parts)
from occflownet.options import option

# The per-preset recipe: the values a TrainConfig field left at None takes. The official values (AdamW 1e-4,
# 200 warm-up steps, 32,768 rays per sample) for base and paper; tiny learns something in a CPU run of minutes.
# One recipe per name of PRESET_NAMES (tests/test_choices.py).
CPU_RECIPE = {"rays_per_step": 4096, "lr": 2e-3, "warmup_steps": 50, "ema_decay": 0.99, "checkpoint_every": 50}
PRESET_RECIPES: dict[str, dict] = {
    "tiny": CPU_RECIPE,
    "small": CPU_RECIPE,
    "base": {"rays_per_step": 32768, "lr": 1e-4, "warmup_steps": 200, "ema_decay": 0.999, "checkpoint_every": 500},
    "paper": {"rays_per_step": 32768, "lr": 1e-4, "warmup_steps": 200, "ema_decay": 0.999, "checkpoint_every": 500},
}
HEAD_INIT_CHOICES = ("", *HEAD_INITS)  # "" = the preset's

# Rendering supervision as this project recommends it (beyond the paper; each part measured in docs/ablation.md
# and docs/training.md § "What a step does"): the stretch of each ray in front of its LiDAR point (up to where it
# first nears a point) and the rays beyond the grid rendered as free, ramped in over 400 steps; rays through
# annotated boxes dropped; rays drawn ∝ 1/√(their class's count); the point terms (the voxel of each return is
# occupied and carries its class) with a free prior of 2; no rendered-depth MSE; with --flow, moved voxels written
# to the nearest voxel (the official code's mover, not the paper's splat: docs/ablation.md, eleventh round; it
# changes nothing without --flow). {TrainConfig field: value}: the quickstart applies it when it renders rays; on
# the command line it is the options docs/training.md spells (a test holds the two equal).
RENDERING_RECIPE: dict[str, object] = {
    "free_beyond_grid": True, "free_before_point": True, "free_stretch": "points", "box_line_of_sight": True,
    "free_ramp_steps": 400, "ray_sampling": "sqrt-balanced", "point_semantics_weight": 1.0,
    "point_density_weight": 1.0, "free_prior_weight": 2.0, "render_depth_weight": 0.0, "flow_mover": "nearest",
}


@dataclass
class TrainConfig:
    """Everything a run needs to be reproduced; written into every checkpoint.

    Defaults follow the official recipe (AdamW wd 1e-2, clip 5, O = 3, dynamic filter, disocclusion and loss
    weighting on = the paper's *Base* setting). The fields of :data:`PRESET_RECIPES` (rays per step, lr, warm-up,
    EMA decay, checkpoint interval) default to None = the preset's value, filled in by ``__post_init__``: after
    construction every field holds a concrete value, and that is what checkpoints and ``train_config.json`` record.
    (``dataclasses.replace(cfg, preset=...)`` keeps the resolved values of the old preset; build a new config.)
    """

    preset: str = option("tiny", "model preset and its training recipe", choices=PRESET_NAMES)
    dataroot: str = option("", "nuScenes-format root (run `occflownet prepare` on it first)")
    out: str = option("runs/tiny", "run folder: checkpoints/, log.jsonl, train_config.json")
    version: str = option("v1.0-trainval", "table version folder (on the command line, default: the only one in "
                                           "the root)")
    split: str = option("train", "split of the index to train on")
    supervision: str = option("2d", "2d: rendering of LiDAR rays; 3d: Occ3D voxel labels; 2d+3d: both",
                              choices=SUPERVISION_MODES)
    horizon: int = option(3, "temporal frames t in [-O, O] (O = 0: no temporal rays)")
    flow: bool = option(False, "occupancy flow: render temporal rays through the moved dynamic voxels")
    flow_mover: str = option("idw", "how moved voxels are written back onto the grid", choices=FLOW_MOVERS)
    dynamic_filter: bool = option(True, "drop the rays of temporal frames t ≠ 0 that end on dynamic objects "
                                        "(not with --flow, which keeps and moves them)")
    disocclusion: bool = option(True, "temporal frames render a copy with the predicted dynamic classes at σ = 0 "
                                      "(without --flow)")
    loss_weighting: bool = option(True, "weight each ray's losses by ω(label) from prepare's class counts (off: "
                                        "uniform)")
    depth_loss: bool = option(True, "rendered-depth MSE and LiDAR depth BCE (off: semantics only)")
    density_scale: float = option(1.0, "rendering optical depth per metre = scale * sigma (1.0 = the official, "
                                       "unscaled sigma)")
    sigma_is: str = option("density", "rendering reads sigma as a density per metre (official) or an opacity per "
                                      "voxel (one voxel can stop the light; docs/render.md)", choices=SIGMA_READINGS)
    render_depth_weight: float = option(0.05, "weight of the rendered-depth MSE (0.05 = official)")
    lidar_depth_weight: float = option(0.05, "weight of the LiDAR depth BCE on the LSS depth distribution (0.05 = "
                                             "official)")
    render_semantics: str = option("mixture", "CE on the rendered logit mixture (official) or on it divided by the "
                                              "ray's weight sum", choices=RENDER_SEMANTICS)
    point_semantics_weight: float = option(0.0, "weight of the CE of the semantic logits of the voxel that holds each "
                                                "ray's LiDAR point (in its frame's volume) against the point's label: "
                                                "sharp class boundaries where the rendered mixture spreads a grazing "
                                                "ray over several voxels (0: off, official; beyond the paper)")
    point_density_weight: float = option(0.0, "weight of -log(sigma) of the voxel that holds each ray's LiDAR point "
                                              "(in its frame's volume): a return says its voxel is occupied, where "
                                              "the rendered depth only asks for the light to stop near it on "
                                              "average (0: off, official; beyond the paper)")
    free_prior_weight: float = option(0.0, "weight of the mean -log(1 - sigma) over all voxels (0: off, official)")
    density_logit_clip: float = option(0.0, "rendering reads sigma = sigmoid(clamp(logit, -M, M)) with the "
                                             "gradient passed straight through the clamp, so that a voxel whose "
                                             "logit ran far out still learns (0: off, official; beyond the paper)")
    density_grad_floor: float = option(0.0, "rendering reads sigma = sigmoid(logit) exactly, but passes back at "
                                            "least the gradient of the sigmoid at -M (+M above): a voxel whose logit "
                                            "ran deep into saturation early can still be pulled back (0: off, "
                                            "official; beyond the paper)")
    voxel_mask: bool = option(False, "3D voxel losses only inside mask_camera (off: every voxel, as the official "
                                     "code)")
    voxel_weighting: str = option("none", "3D density BCE per voxel: none (official) or sqrt-balanced: a voxel of "
                                          "class c weighs sqrt(N_free / N_c), 1 to 30, N counted over the training "
                                          "split's labels (inside mask_camera with --voxel-mask); beyond the paper",
                                  choices=VOXEL_WEIGHTINGS)
    head_init: str = option("", "σ/semantic head init: prior (σ ≈ 0.1 at the start) or official (Xavier, zero "
                                "bias); empty: the preset's", choices=HEAD_INIT_CHOICES)
    free_space: bool = option(False, "also render LiDAR beams that returned nothing; their opacity goes to 0 "
                                     "(beyond the paper)")
    free_beyond_grid: bool = option(False, "also render the camera rays to LiDAR points beyond the grid as free "
                                           "rays: the grid is empty along them (beyond the paper)")
    box_line_of_sight: bool = option(False, "drop the rays (and free rays) that pass through an annotated object "
                                            "box before their point: hidden from the camera, or crossing where an "
                                            "object stands at the keyframe (beyond the paper)")
    free_before_point: bool = option(False, "also render the stretch of each ray in front of its LiDAR point (up to "
                                            "where --free-stretch ends it) as free; its opacity goes to 0 (beyond "
                                            "the paper)")
    free_stretch: str = option("fraction", "where --free-before-point's stretch ends: fraction = 0.8 depth - 0.6 m; "
                                           "points = where the ray first comes within a voxel of a LiDAR point of "
                                           "its frame; with it the free rays leave out the voxels within a voxel "
                                           "of a point (occflownet/data/free_stretch.py)",
                               choices=FREE_STRETCH_RULES)
    free_rays_per_step: int = option(2048, "free rays per sample per step (with --free-space/--free-beyond-grid; "
                                           "--free-before-point renders as many of the rays' free stretches)")
    free_space_weight: float = option(1.0, "weight of the free-space term -log(1 - opacity)")
    free_ramp_steps: int = option(0, "raise the weight of the free terms (--free-space, --free-beyond-grid, "
                                     "--free-before-point) linearly from 0 to --free-space-weight over this many "
                                     "steps, so that surfaces form before the free space is carved (0: full weight "
                                     "from the start; beyond the paper)")
    ray_sampling: str = option("uniform", "how a step draws its rays: uniform (official) or sqrt-balanced (a ray of "
                                          "a class with n rays in the keyframe is drawn with probability ∝ 1/√n; "
                                          "beyond the paper)", choices=RAY_SAMPLINGS)
    bev_flip: bool = option(False, "mirror each training sample's ego frame in x and in y, each with probability "
                                   "0.5 (the official recipe's BEV augmentation; occflownet/train/augment.py)")
    image_aug: bool = option(False, "warp each training image by a random resize, sideways shift, horizontal flip and "
                                    "rotation, its intrinsics with it (the official recipe's image augmentation; "
                                    "occflownet/train/augment.py)")
    max_steps: int = option(1000, "optimisation steps")
    time_limit_s: float = option(0.0, "stop with a checkpoint after this many seconds (0: no limit)",
                                 flag="time-limit")
    batch_size: int = option(1, "samples per process per step")
    rays_per_step: int | None = option(None, "rays per sample per step (default: the preset's; official 32768)")
    lr: float | None = option(None, "AdamW learning rate (default: the preset's)")
    lr_schedule: str = option("constant", "after the warm-up: constant (official) or a cosine decay to 0 at "
                                          "--max-steps (a resumed run decays over its new --max-steps)",
                              choices=LR_SCHEDULES)
    weight_decay: float = option(1e-2, "AdamW weight decay")
    grad_clip: float = option(5.0, "gradient norm clip")
    warmup_steps: int | None = option(None, "linear warm-up steps (default: the preset's)")
    ema_decay: float | None = option(None, "EMA decay of the weights (default: the preset's)")
    checkpoint_every: int | None = option(None, "steps between checkpoints (default: the preset's)")
    log_every: int = option(10, "steps between log records")
    seed: int = option(0, "seed of the weights, the sampling and the rays")
    num_workers: int = option(2, "data loader processes")
    precision: str = option("auto", "the network's arithmetic in training: auto = bf16 autocast on CUDA, float32 "
                                    "on CPUs; bf16 = bf16 autocast also on CPUs that compute it natively "
                                    "(AVX512-BF16, AMX: 1.4x faster a step, but less stable in long runs, "
                                    "docs/training.md); fp32 = float32 everywhere. Rendering and losses stay "
                                    "float32", choices=PRECISIONS)
    device: str = option("auto", "torch device (auto: CUDA when available)")
    threshold: float | None = option(None, "τ stored with the model (default 0.35 for 2d, 0.30 with 3D labels)")

    def __post_init__(self):
        if self.preset not in PRESET_RECIPES:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {sorted(PRESET_RECIPES)}")
        for name, value in PRESET_RECIPES[self.preset].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        supervision_parts(self.supervision)  # ValueError naming the modes
        if self.horizon < 0:
            raise ValueError("horizon must be >= 0")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be one of {LR_SCHEDULES}, got {self.lr_schedule!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.flow_mover not in FLOW_MOVERS:
            raise ValueError(f"flow_mover must be one of {FLOW_MOVERS}, got {self.flow_mover!r}")
        if self.head_init not in HEAD_INIT_CHOICES:
            raise ValueError(f"head_init must be one of {HEAD_INIT_CHOICES}, got {self.head_init!r}")
        if (self.free_space or self.free_beyond_grid or self.free_before_point) and not self.uses_2d:
            raise ValueError("free_space, free_beyond_grid and free_before_point render rays: they need supervision "
                             "'2d' or '2d+3d'")
        if self.sigma_is not in SIGMA_READINGS or self.render_semantics not in RENDER_SEMANTICS:
            raise ValueError(f"sigma_is must be one of {SIGMA_READINGS} and render_semantics one of "
                             f"{RENDER_SEMANTICS}, got {self.sigma_is!r}, {self.render_semantics!r}")
        if min(self.render_depth_weight, self.lidar_depth_weight, self.free_prior_weight, self.density_logit_clip,
               self.density_grad_floor, self.point_semantics_weight, self.point_density_weight) < 0:
            raise ValueError("render_depth_weight, lidar_depth_weight, free_prior_weight, density_logit_clip, "
                             "density_grad_floor, point_semantics_weight and point_density_weight must be >= 0")
        if max(self.point_semantics_weight, self.point_density_weight) > 0 and not self.uses_2d:
            raise ValueError("point_semantics_weight and point_density_weight read the rays' points: they need "
                             "supervision '2d' or '2d+3d'")
        if self.free_stretch not in FREE_STRETCH_RULES:
            raise ValueError(f"free_stretch must be one of {FREE_STRETCH_RULES}, got {self.free_stretch!r}")
        if self.free_rays_per_step < 1 or self.free_space_weight < 0 or self.free_ramp_steps < 0:
            raise ValueError("free_rays_per_step must be >= 1, free_space_weight and free_ramp_steps >= 0")
        if self.voxel_weighting not in VOXEL_WEIGHTINGS:
            raise ValueError(f"voxel_weighting must be one of {VOXEL_WEIGHTINGS}, got {self.voxel_weighting!r}")
        if self.ray_sampling not in RAY_SAMPLINGS:
            raise ValueError(f"ray_sampling must be one of {RAY_SAMPLINGS}, got {self.ray_sampling!r}")

    @property
    def uses_2d(self) -> bool:
        return "2d" in supervision_parts(self.supervision)

    @property
    def uses_3d(self) -> bool:
        return "3d" in supervision_parts(self.supervision)

    @property
    def uses_free_rays(self) -> bool:
        """Whether free rays are rendered (free-space beams and/or beyond-grid rays)."""
        return self.free_space or self.free_beyond_grid

    def resolved_threshold(self) -> float:
        if self.threshold is not None:
            return float(self.threshold)
        return 0.30 if self.uses_3d else 0.35

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})
