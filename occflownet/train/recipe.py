"""Training configuration: one typed dataclass and the per-preset recipes; `occflownet train` maps its options
onto the fields, so ``TrainConfig(preset=p, ...)`` from Python is the same run as ``occflownet train --preset p``."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields

SUPERVISION_MODES = ("2d", "3d", "2d+3d")

# The per-preset recipe: the values a TrainConfig field left at None takes. The official values (AdamW 1e-4,
# 200 warm-up steps, 32,768 rays per sample) for base and paper; tiny learns something in a CPU run of minutes.
PRESET_RECIPES: dict[str, dict] = {
    "tiny": {"rays_per_step": 4096, "lr": 2e-3, "warmup_steps": 50, "ema_decay": 0.99, "checkpoint_every": 50},
    "base": {"rays_per_step": 32768, "lr": 1e-4, "warmup_steps": 200, "ema_decay": 0.999, "checkpoint_every": 500},
    "paper": {"rays_per_step": 32768, "lr": 1e-4, "warmup_steps": 200, "ema_decay": 0.999, "checkpoint_every": 500},
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

    preset: str = "tiny"
    dataroot: str = ""
    out: str = "runs/tiny"
    version: str = "v1.0-trainval"
    split: str = "train"
    supervision: str = "2d"
    horizon: int = 3
    flow: bool = False
    flow_mover: str = "idw"
    dynamic_filter: bool = True
    disocclusion: bool = True
    loss_weighting: bool = True
    depth_loss: bool = True          # rendered depth MSE and the LSS LiDAR depth BCE
    density_scale: float = 1.0       # rendering uses τ_i = density_scale · σ_i · δ_i; 1.0 = official (σ per metre)
    sigma_is: str = "density"        # rendering reads σ as "density" (per metre, official) or "opacity" (per voxel)
    render_depth_weight: float = 0.05  # weight of the rendered-depth MSE (official 0.05)
    render_semantics: str = "mixture"  # CE on the rendered logit mixture (official) or on it ÷ weight sum
    free_prior_weight: float = 0.0   # mean -log(1 - σ) over all voxels (0 = off, official)
    voxel_mask: bool = False         # 3D voxel losses only inside mask_camera (official: False, every voxel)
    head_init: str = ""              # "" = the preset's; "prior" or "official" (model/presets.py HEAD_INITS)
    free_space: bool = False         # also render LiDAR beams without a return; their opacity → 0 (beyond the paper)
    free_rays_per_step: int = 2048   # free-space beams per sample per step (with free_space)
    free_space_weight: float = 1.0   # weight of the free-space term −log(1 − opacity)
    max_steps: int = 1000
    time_limit_s: float = 0.0        # 0 = no limit; otherwise stop (with a checkpoint) after this many seconds
    batch_size: int = 1              # samples per process per step
    rays_per_step: int | None = None  # rays per sample per step; None = the preset's (official 32768)
    lr: float | None = None          # AdamW learning rate; None = the preset's
    weight_decay: float = 1e-2
    grad_clip: float = 5.0
    warmup_steps: int | None = None  # linear warm-up steps; None = the preset's
    ema_decay: float | None = None   # None = the preset's
    checkpoint_every: int | None = None  # steps between checkpoints; None = the preset's
    log_every: int = 10
    seed: int = 0
    num_workers: int = 2
    amp: bool = True                 # mixed precision where the device supports it (CUDA bf16/fp16)
    device: str = "auto"
    threshold: float | None = None   # τ stored with the model; None = 0.35 for 2d, 0.30 when 3D labels are used

    def __post_init__(self):
        if self.preset not in PRESET_RECIPES:
            raise ValueError(f"unknown preset {self.preset!r}; choose one of {sorted(PRESET_RECIPES)}")
        for name, value in PRESET_RECIPES[self.preset].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        if self.supervision not in SUPERVISION_MODES:
            raise ValueError(f"supervision must be one of {SUPERVISION_MODES}, got {self.supervision!r}")
        if self.horizon < 0:
            raise ValueError("horizon must be >= 0")
        if self.flow_mover not in ("idw", "nearest"):
            raise ValueError("flow_mover must be 'idw' or 'nearest'")
        if self.free_space and not self.uses_2d:
            raise ValueError("free_space renders LiDAR beams: it needs supervision '2d' or '2d+3d'")
        if self.render_depth_weight < 0 or self.free_prior_weight < 0:
            raise ValueError("render_depth_weight and free_prior_weight must be >= 0")
        if self.free_rays_per_step < 1 or self.free_space_weight < 0:
            raise ValueError("free_rays_per_step must be >= 1 and free_space_weight >= 0")

    @property
    def uses_2d(self) -> bool:
        return self.supervision in ("2d", "2d+3d")

    @property
    def uses_3d(self) -> bool:
        return self.supervision in ("3d", "2d+3d")

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
