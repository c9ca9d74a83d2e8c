"""The occupancy model (torch): configuration/presets, network, checkpoints.

``from occflownet.model import ModelConfig, PRESETS, get_preset, OccupancyModel, save_checkpoint, load_checkpoint,
model_from_source``
"""
from occflownet.model.checkpoint import (CheckpointError, load_checkpoint, model_from_source, read_checkpoint,
                                         save_checkpoint)
from occflownet.model.presets import PRESETS, ModelConfig, get_preset
from occflownet.model.occupancy_model import InferenceGraph, OccupancyModel, create_model, fuse_occupancy

__all__ = [
    "ModelConfig", "PRESETS", "get_preset", "OccupancyModel", "InferenceGraph", "create_model", "fuse_occupancy",
    "save_checkpoint", "load_checkpoint", "read_checkpoint", "CheckpointError", "model_from_source",
]
