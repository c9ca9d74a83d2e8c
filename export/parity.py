"""torch ↔ onnxruntime parity of an exported occupancy graph.

Both sides are predictors of the one predictor path (:class:`occflownet.runtime.TorchPredictor`,
:class:`occflownet.runtime.OnnxPredictor`) fed the same :class:`occflownet.runtime.ModelInputs`, built by
:func:`occflownet.runtime.frame_inputs` from images and calibration JSON.

Criteria (per sample): density max |σ_torch − σ_ort| ≤ 1e-4, and occupancy equal on ≥ 99.99 % of the voxels whose
σ_torch is not within 1e-3 of τ (voxels at the threshold may legitimately flip).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occflownet.contract import load_calibration
from occflownet.geometry import rotation_z
from occflownet.model import ModelConfig, OccupancyModel
from occflownet.occ3d import CAMERAS
from occflownet.predict import load_image_folder
from occflownet.rig import default_rig
from occflownet.runtime import ModelInputs, OnnxPredictor, TorchPredictor, frame_inputs

DENSITY_TOL = 1e-4
OCCUPANCY_MIN_AGREEMENT = 0.9999
THRESHOLD_BAND = 1e-3


@dataclass
class ParitySample:
    """One named batch: images uint8 [B, 6, H, W, 3], intrinsics float32 [B, 6, 3, 3], cam2ego float32
    [B, 6, 4, 4] (camera → ego)."""

    name: str
    images: np.ndarray
    intrinsics: np.ndarray
    cam2ego: np.ndarray

    @classmethod
    def of(cls, name: str, inputs: ModelInputs) -> ParitySample:
        return cls(name, inputs.images, inputs.intrinsics, inputs.cam2ego)

    @property
    def inputs(self) -> ModelInputs:
        return ModelInputs(self.images, self.intrinsics, self.cam2ego)


@dataclass
class ParityCase:
    name: str
    shape: tuple
    density_max_abs_diff: float
    occupancy_agreement: float      # over voxels with |σ − τ| > THRESHOLD_BAND
    voxels_compared: int

    @property
    def ok(self) -> bool:
        return self.density_max_abs_diff <= DENSITY_TOL and self.occupancy_agreement >= OCCUPANCY_MIN_AGREEMENT

    def describe(self) -> str:
        return (f"{self.name} images{list(self.shape)}: density max diff {self.density_max_abs_diff:.2e} "
                f"(tol {DENSITY_TOL:.0e}), occupancy agreement {100 * self.occupancy_agreement:.4f}% of "
                f"{self.voxels_compared} voxels away from tau -> {'ok' if self.ok else 'FAIL'}")


def second_calibration(width: int, height: int) -> dict:
    """A rig different from the default: every camera turned 30° about ego z, shifted, focal lengths × 0.85."""
    calib = default_rig(width, height)
    turn = rotation_z(np.radians(30.0))
    turn[:3, 3] = (0.4, -0.3, 0.1)
    for cam in calib["cameras"].values():
        k = np.asarray(cam["intrinsic"])
        k[0, 0] *= 0.85
        k[1, 1] *= 0.85
        cam["intrinsic"] = k.tolist()
        cam["cam2ego"] = (turn @ np.asarray(cam["cam2ego"])).tolist()
    return calib


def _random_images(rng, batch: int, height: int, width: int) -> np.ndarray:
    """Smooth-ish random images (noise + gradients), uint8 [B, 6, H, W, 3]."""
    noise = rng.integers(0, 256, (batch, len(CAMERAS), height, width, 3), dtype=np.uint8)
    ramp = np.linspace(0, 255, width, dtype=np.float32)[None, None, None, :, None]
    return ((noise.astype(np.float32) * 0.5 + ramp * 0.5)).astype(np.uint8)


def _frames(images: np.ndarray, calibs: list[dict]) -> ModelInputs:
    """Frame b of ``images`` uint8 [B, 6, H, W, 3] with calibration JSON ``calibs[b]``, as one batch."""
    return ModelInputs.stack([frame_inputs(im, calib) for im, calib in zip(images, calibs, strict=True)])


def frame_sample(folder: str | Path, batch: int = 1) -> ParitySample:
    """A real frame folder (six CAM_*.jpg + calib.json) decoded whole: batch 1 = as calibrated; batch 2 adds the same
    images with the rig turned (a second calibration in the same batch)."""
    folder = Path(folder)
    inputs = frame_inputs(load_image_folder(folder), load_calibration(folder / "calib.json"))
    if batch == 1:
        return ParitySample.of(f"frame:{folder.name}", inputs)
    turn = rotation_z(np.radians(-40.0)).astype(np.float32)
    turned = ModelInputs(inputs.images, inputs.intrinsics, turn @ inputs.cam2ego)
    return ParitySample.of(f"frame:{folder.name}+turned-rig", ModelInputs.stack([inputs, turned]))


def inference_frame_sample(folder: str | Path, cfg: ModelConfig) -> ParitySample:
    """A real frame folder as the inference paths feed it to a model of ``cfg`` (JPEGs at reduced scale with the
    1/n intrinsics rule, ``occflownet.contract.decode_reduction``), batch 1."""
    from occflownet.predict import load_frame

    folder = Path(folder)
    frame = load_frame(folder, tuple(cfg.input_size))
    return ParitySample.of(f"frame:{folder.name}@1/{frame.reduction}",
                           frame.inputs(load_calibration(folder / "calib.json")))


def default_parity_samples(cfg: ModelConfig, frames: list | None = None, seed: int = 0) -> list[ParitySample]:
    """Random images at the default calibration's size (batch 1 and 2), at 1600x900 with two different
    calibrations in one batch, plus each real frame folder of ``frames`` (batch 1 and 2 decoded whole, and batch 1
    as the inference paths decode it)."""
    rng = np.random.default_rng(seed)
    w, h = (int(v) for v in cfg.default_calibration["image_size"])
    default = cfg.default_calibration
    samples = [
        ParitySample.of(f"random-{w}x{h}-default-rig", _frames(_random_images(rng, 1, h, w), [default])),
        ParitySample.of(f"random-{w}x{h}-default-rig-b2", _frames(_random_images(rng, 2, h, w), [default] * 2)),
    ]
    two_rigs = [second_calibration(1600, 900), default_rig(1600, 900)]
    samples.append(ParitySample.of("random-1600x900-two-rigs-b2", _frames(_random_images(rng, 2, 900, 1600), two_rigs)))
    for folder in frames or []:
        samples += [frame_sample(folder, 1), frame_sample(folder, 2), inference_frame_sample(folder, cfg)]
    return samples


def compare(occ_t: np.ndarray, dens_t: np.ndarray, occ_o: np.ndarray, dens_o: np.ndarray, threshold: float,
            name: str = "", shape: tuple = ()) -> ParityCase:
    """Parity figures between a torch prediction (reference) and an onnxruntime one."""
    away = np.abs(dens_t - threshold) > THRESHOLD_BAND
    n = int(away.sum())
    agree = float(np.mean(occ_t[away] == occ_o[away])) if n else 1.0
    diff = float(np.max(np.abs(dens_t.astype(np.float64) - dens_o.astype(np.float64))))
    return ParityCase(name, tuple(shape), diff, agree, n)


def check_parity(model: OccupancyModel, onnx_path: str | Path, samples: list[ParitySample],
                 threshold: float) -> list[ParityCase]:
    """Run every sample through torch (``model.inference``) and onnxruntime, both through the one predictor path;
    one ParityCase per sample."""
    torch_side, onnx_side = TorchPredictor(model), OnnxPredictor.open(onnx_path)
    cases = []
    for s in samples:
        inputs = s.inputs
        cases.append(compare(*torch_side(inputs), *onnx_side(inputs), threshold, s.name, s.images.shape))
    return cases
