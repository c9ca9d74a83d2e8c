"""Checkpoints: one torch file {state_dict, config, occflownet_version, extra}, written atomically.

The file is loadable with ``torch.load(weights_only=True)``: ``extra`` may hold tensors, dicts/lists/tuples of
tensors, numbers, strings, booleans and None (e.g. optimizer state dicts, step counters, the train config).
"""
from __future__ import annotations

from pathlib import Path

import torch

from occflownet import __version__
from occflownet.files import atomic_path
from occflownet.model.presets import ModelConfig, get_preset
from occflownet.model.occupancy_model import OccupancyModel, create_model


class CheckpointError(ValueError):
    """A checkpoint file cannot be used (corrupt, truncated, wrong content or wrong preset); names the file."""


def save_checkpoint(path, model: OccupancyModel, cfg: ModelConfig, extra: dict | None = None) -> Path:
    """Write ``model``'s weights and ``cfg`` to ``path`` atomically and durably (``files.atomic_path``, fsync)."""
    path = Path(path)
    payload = {
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "config": cfg.to_dict(),
        "occflownet_version": __version__,
        "extra": dict(extra or {}),
    }
    with atomic_path(path, fsync=True) as tmp:
        torch.save(payload, tmp)
    return path


def read_checkpoint(path) -> dict:
    """Load and validate the raw checkpoint dict (``weights_only=True``); raises CheckpointError naming ``path``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # truncated zip, not a torch file, disallowed pickle content, ...
        raise CheckpointError(f"{path}: not a readable occflownet checkpoint (corrupt or truncated?): "
                              f"{type(exc).__name__}: {exc}") from exc
    if not isinstance(payload, dict) or not {"state_dict", "config"} <= set(payload):
        raise CheckpointError(f"{path}: not an occflownet checkpoint (needs 'state_dict' and 'config')")
    return payload


def load_checkpoint(path, expect_preset: str | None = None, map_location="cpu"):
    """→ (model in eval mode, cfg, extra). ``expect_preset``: fail unless the checkpoint is of that preset."""
    path = Path(path)
    payload = read_checkpoint(path)
    try:
        cfg = ModelConfig.from_dict(payload["config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: invalid model config: {exc}") from exc
    if expect_preset is not None and cfg.preset != expect_preset:
        raise CheckpointError(f"{path}: checkpoint is of preset {cfg.preset!r}, expected {expect_preset!r}")
    model = OccupancyModel(cfg)
    try:
        model.load_state_dict(payload["state_dict"], strict=True)
    except RuntimeError as exc:
        raise CheckpointError(f"{path}: weights do not match preset {cfg.preset!r}: {exc}") from exc
    model.to(map_location).eval()
    return model, cfg, payload.get("extra") or {}


def model_from_source(checkpoint: str | Path | None = None, preset: str | None = None, seed: int | None = None
                      ) -> OccupancyModel:
    """An ``OccupancyModel`` in eval mode from a checkpoint (its weights: training stores the EMA weights there), or
    a randomly initialised preset (seeded: same seed → same weights). Run it with
    ``occflownet.runtime.TorchPredictor``. CheckpointError (a ValueError) naming the file."""
    if checkpoint is not None:
        model, _, _ = load_checkpoint(checkpoint)
        return model.eval()
    if preset is None:
        raise ValueError("need a checkpoint or a preset")
    return create_model(get_preset(preset), seed=0 if seed is None else seed).eval()
