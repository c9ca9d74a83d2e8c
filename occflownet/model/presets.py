"""Model configuration: one flat, typed dataclass and the three presets `tiny`, `base`, `paper`.

The configuration is stored in every checkpoint (``dataclasses.asdict``) and, in part, in every ONNX file's
metadata, so it round-trips: ``ModelConfig(**asdict(cfg)) == cfg`` and ``ModelConfig.from_dict(json.loads(...))``
(lists are turned back into tuples). This module imports no torch.

Shapes and frames used by the fields:
- ``input_size`` (H, W) is the *internal* image size the backbone sees after the in-graph resize + crop; the
  network's inputs may have any size (see ``occflownet.model.preprocess``).
- Depth bins are camera-frame **z-depth** in metres (OpenCV camera: z forward), uniform between ``depth_min`` and
  ``depth_max``; ``depth_bin_centers()`` gives their centres.
- The 3D decoder runs on the voxel grid coarsened by ``decoder_stride`` (1 = the full 200x200x16 grid).
"""
from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, field, fields, replace

from occflownet.choices import HEAD_INITS
from occflownet.occ3d import GRID
from occflownet.rig import default_rig


# The synthetic world's default camera image size (width, height); the default calibration is for this size.
DEFAULT_IMAGE_SIZE = (480, 270)
FEATURE_STRIDE = 16  # the neck's output stride: feature map = input_size / 16
IMAGENET_MEAN = (123.675, 116.28, 103.53)  # RGB, 0..255 scale (torchvision's normalisation)
IMAGENET_STD = (58.395, 57.12, 57.375)


def _default_calibration() -> dict:
    return default_rig(*DEFAULT_IMAGE_SIZE)


@dataclass
class ModelConfig:
    """Everything needed to rebuild an :class:`~occflownet.model.OccupancyModel` (weights aside)."""

    preset: str = "tiny"
    # --- input / preprocessing (in the graph) ---
    input_size: tuple[int, int] = (160, 288)      # (H, W) internal, both multiples of 32
    subsample_large_inputs: bool = True            # keep every n-th pixel of >= 4x larger inputs first
    image_mean: tuple[float, float, float] = IMAGENET_MEAN
    image_std: tuple[float, float, float] = IMAGENET_STD
    # --- image backbone (torchvision ResNet layout) ---
    backbone_block: str = "basic"                  # "basic" (ResNet-18/34) or "bottleneck" (ResNet-50/101)
    backbone_layers: tuple[int, int, int, int] = (1, 1, 1, 1)
    backbone_width: int = 16                       # stem width; torchvision ResNets use 64
    neck_channels: int = 64                        # stride-16 feature channels
    # --- LSS lifting ---
    depth_min: float = 1.0
    depth_max: float = 45.0
    num_depth_bins: int = 32
    context_channels: int = 32                     # lifted feature channels pooled into the decoder grid
    fine_skip: bool = True                         # also lift head_channels features at full resolution (s > 1)
    # --- 3D decoder ---
    decoder_stride: int = 4                        # 1, 2, 4 or 8: the trunk's grid is GRID.shape / stride
    decoder_channels: int = 32
    decoder_blocks: int = 1                        # 3D residual blocks (conv3x3x3-BN-ReLU-conv3x3x3-BN + skip)
    head_channels: int = 8                         # per-voxel feature width after upsampling (stride > 1)
    sigma_hidden: tuple[int, ...] = (16,)          # hidden layers of the density MLP Φσ
    semantic_hidden: tuple[int, ...] = (16,)       # hidden layers of the semantic MLP Φs
    head_init: str = "prior"                       # "prior": torch default, Φσ bias -2.2 (σ ≈ 0.1);
                                                   # "official": Xavier-uniform weights, zero biases (σ ≈ 0.5)
    # --- training only ---
    image_semantics: bool = False                  # a 1x1 head on the stride-16 features giving each cell's class,
                                                   # trained by an auxiliary loss; not part of inference or export
    # --- fusion ---
    threshold: float = 0.35                        # τ: occupied where σ >= τ (0.35 2D-trained, 0.30 3D-trained)
    default_calibration: dict = field(default_factory=_default_calibration)

    def __post_init__(self):
        if self.head_init not in HEAD_INITS:
            raise ValueError(f"head_init must be one of {HEAD_INITS}, got {self.head_init!r}")
        for name in ("input_size", "image_mean", "image_std", "backbone_layers", "sigma_hidden",
                     "semantic_hidden"):
            setattr(self, name, tuple(getattr(self, name)))
        self.input_size = tuple(int(v) for v in self.input_size)
        h, w = self.input_size
        if len(self.input_size) != 2 or h % 32 or w % 32 or h <= 0 or w <= 0:
            raise ValueError(f"input_size must be (H, W), positive multiples of 32, got {self.input_size}")
        if self.backbone_block not in ("basic", "bottleneck"):
            raise ValueError(f"backbone_block must be 'basic' or 'bottleneck', got {self.backbone_block!r}")
        if len(self.backbone_layers) != 4 or min(self.backbone_layers) < 1:
            raise ValueError(f"backbone_layers must be 4 positive block counts, got {self.backbone_layers}")
        if not 0 < self.depth_min < self.depth_max:
            raise ValueError(f"need 0 < depth_min < depth_max, got {self.depth_min}, {self.depth_max}")
        if self.num_depth_bins < 2:
            raise ValueError("num_depth_bins must be >= 2")
        s = self.decoder_stride
        if s not in (1, 2, 4, 8) or any(n % s for n in GRID.shape):
            raise ValueError(f"decoder_stride must be 1, 2, 4 or 8 (dividing {GRID.shape}), got {s}")
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"threshold must lie in (0, 1), got {self.threshold}")
        if self.context_channels < 1 or self.head_channels < 1 or self.decoder_channels < 1:
            raise ValueError("context_channels, decoder_channels and head_channels must be >= 1")

    # ---- derived quantities ----
    @property
    def feature_size(self) -> tuple[int, int]:
        """(h, w) of the stride-16 feature map."""
        return self.input_size[0] // FEATURE_STRIDE, self.input_size[1] // FEATURE_STRIDE

    @property
    def uses_fine_skip(self) -> bool:
        """Whether lifted features are also pooled at full resolution as a skip into the heads."""
        return self.decoder_stride > 1 and self.fine_skip

    @property
    def trunk_grid(self) -> tuple[int, int, int]:
        """Shape (X, Y, Z) of the decoder trunk's grid."""
        return tuple(n // self.decoder_stride for n in GRID.shape)

    def depth_bin_edges(self) -> list[float]:
        """D + 1 bin edges in metres (z-depth), uniform from depth_min to depth_max."""
        step = (self.depth_max - self.depth_min) / self.num_depth_bins
        return [self.depth_min + i * step for i in range(self.num_depth_bins + 1)]

    def depth_bin_centers(self) -> list[float]:
        """D bin centres in metres: camera-frame z-depth of each LSS depth bin."""
        e = self.depth_bin_edges()
        return [(a + b) / 2.0 for a, b in zip(e[:-1], e[1:])]

    # ---- serialisation ----
    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """Inverse of :meth:`to_dict` (also accepts JSON-decoded dicts); unknown keys are an error."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown ModelConfig fields: {unknown}")
        return cls(**d)


# One preset per name of occflownet.choices.PRESET_NAMES (tests/test_choices.py).
PRESETS: dict[str, ModelConfig] = {
    # CPU preset: trains on two cores in minutes; reduced-resolution trunk (50x50x4) + full-res skip and heads.
    "tiny": ModelConfig(preset="tiny"),
    # tiny with its lifting made denser and a backbone twice as wide: at tiny's 160x288 input and 32 depth bins (1.4 m
    # apart) the full-resolution skip lifts its features into 6 % of the voxels of mask_camera, a sparse dot
    # pattern; at 256x448 and 88 bins (0.5 m apart) into 33 % (docs/results.md#training-speed). The stem width 32
    # scores higher on unseen scenes with the quickstart recipe (docs/results.md#the-quickstart). Same trunk,
    # decoder and heads.
    "small": ModelConfig(preset="small", input_size=(256, 448), num_depth_bins=88, backbone_width=32),
    # The usual deployment size: ResNet-50 at 256x704, trunk at 100x100x8.
    "base": ModelConfig(
        preset="base", input_size=(256, 704), backbone_block="bottleneck", backbone_layers=(3, 4, 6, 3),
        backbone_width=64, neck_channels=256, num_depth_bins=88, context_channels=32, fine_skip=True,
        decoder_stride=2, decoder_channels=32, decoder_blocks=2, head_channels=32,
        sigma_hidden=(64, 64), semantic_hidden=(64, 64)),
    # The paper's scale: 512x1408 images, full-resolution 3D decoder, heads with 3 hidden layers of 256.
    # (The paper uses a Swin-B backbone; the ResNet-50 here keeps the package torchvision-weight compatible.)
    "paper": ModelConfig(
        preset="paper", input_size=(512, 1408), backbone_block="bottleneck", backbone_layers=(3, 4, 6, 3),
        backbone_width=64, neck_channels=256, num_depth_bins=88, context_channels=32, fine_skip=False,
        decoder_stride=1, decoder_channels=32, decoder_blocks=2, head_channels=32,
        sigma_hidden=(256, 256, 256), semantic_hidden=(256, 256, 256)),
}


def get_preset(name: str, **overrides) -> ModelConfig:
    """A fresh copy of preset ``name`` (``tiny``, ``base``, ``paper``), with optional field overrides."""
    if name not in PRESETS:
        raise ValueError(f"unknown model preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(copy.deepcopy(PRESETS[name]), **overrides)
