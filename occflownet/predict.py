"""Prediction with the torch model (``occflownet predict --checkpoint`` / ``--preset P --random-init``).

The onnxruntime path (``--model``) lives in :mod:`occflownet.inference_io` and never imports torch; both share
the image/calibration loading and the outputs, so the two give the same grid up to float rounding.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from occflownet.model import OccupancyModel, create_model, get_preset, load_checkpoint


def model_from_source(checkpoint: str | Path | None = None, preset: str | None = None,
                      seed: int | None = None) -> OccupancyModel:
    """A model in eval mode from a checkpoint, or a randomly initialised preset (seeded: same seed → same weights)."""
    if checkpoint is not None:
        model, _, _ = load_checkpoint(checkpoint)
        return model.eval()
    if preset is None:
        raise ValueError("need a checkpoint or a preset")
    return create_model(get_preset(preset), seed=0 if seed is None else seed).eval()


def predict_torch(model: OccupancyModel, images: np.ndarray, intrinsics: np.ndarray, cam2ego: np.ndarray):
    """One sample: images uint8 [6, H, W, 3], intrinsics [6, 3, 3], cam2ego [6, 4, 4] →
    (occupancy uint8 [200, 200, 16], density float32 [200, 200, 16])."""
    with torch.no_grad():
        occ, dens = model.inference(torch.from_numpy(np.ascontiguousarray(images))[None],
                                    torch.from_numpy(np.asarray(intrinsics, dtype=np.float32))[None],
                                    torch.from_numpy(np.asarray(cam2ego, dtype=np.float32))[None])
    return occ[0].numpy(), dens[0].numpy()
