"""The training state: what the loop carries from one step to the next, written and read back as one checkpoint.

``TrainingState.save(path)`` and ``TrainingState.load(path)`` are mirror images over one dict, the checkpoint
file. It is an occflownet model checkpoint (``occflownet.model.load_checkpoint`` reads it: ``eval``, ``export``
and ``predict`` use the **EMA** weights) whose ``extra["train"]`` holds the rest of the state:

====================  ================================================================================
``state_dict``        EMA weights (``EMA.shadow``)
``config``            the ModelConfig (preset, τ, head init, default calibration)
``extra.train``       ``config``: the TrainConfig (resolved; its ``ema_decay`` is the EMA's decay),
                      ``model``: raw weights (the optimiser's), ``ema_updates``: the EMA's update counter,
                      ``optimizer``: AdamW state, ``scheduler``: LambdaLR state, ``step``: optimiser steps
                      done, ``torch_rng``: torch's CPU RNG state when the file was written
====================  ================================================================================

Written atomically (temp file + ``os.replace``); loadable with ``torch.load(weights_only=True)``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import torch

from occflownet.model.checkpoint import read_checkpoint, save_checkpoint
from occflownet.model.occupancy_model import OccupancyModel, create_model
from occflownet.model.presets import ModelConfig
from occflownet.train.ema import EMA
from occflownet.train.recipe import TrainConfig
from occflownet.train.schedule import warmup_schedule

# The keys of ``extra["train"]`` (the same since the first checkpoints: every file written so far resumes).
TRAIN_KEYS = ("config", "model", "ema_updates", "optimizer", "scheduler", "step", "torch_rng")

# TrainConfig fields a resumed run may change: how long and where it runs, not what it learns.
# The recipe's name is a label: what a run learns is in the other fields.
CONTINUATION_FIELDS = frozenset({"dataroot", "out", "max_steps", "time_limit_s", "checkpoint_every", "log_every",
                                 "num_workers", "device", "precision", "recipe"})


class TrainingError(RuntimeError):
    """Training cannot start or must stop; the message says why and what to do."""


@dataclass
class TrainingState:
    """Model, EMA, optimiser, schedule and step of a run, with the configurations they were built from."""

    cfg: TrainConfig
    model_cfg: ModelConfig
    model: OccupancyModel                        # raw weights, on the training device
    ema: EMA                                     # averaged weights (what the checkpoint's state_dict holds)
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    step: int = 0                                # optimiser steps done

    @classmethod
    def create(cls, cfg: TrainConfig, model_cfg: ModelConfig, device) -> "TrainingState":
        """A fresh run: weights from ``cfg.seed`` (this seeds torch's RNG), AdamW with weight decay on weights
        but not on norms/biases (parameters with ndim <= 1), linear warm-up then ``cfg.lr_schedule`` over
        ``cfg.max_steps``, EMA with ``cfg.ema_decay``."""
        model = create_model(model_cfg, seed=cfg.seed).to(device)
        params = list(model.parameters())
        optimizer = torch.optim.AdamW([{"params": [p for p in params if p.ndim > 1], "weight_decay": cfg.weight_decay},
                                       {"params": [p for p in params if p.ndim <= 1], "weight_decay": 0.0}],
                                      lr=cfg.lr)
        return cls(cfg, model_cfg, model, EMA(model, cfg.ema_decay), optimizer,
                   warmup_schedule(optimizer, cfg.warmup_steps, cfg.lr_schedule, cfg.max_steps))

    def save(self, path) -> Path:
        """Write the state to ``path`` atomically (the layout in the module docstring)."""
        train = {"config": self.cfg.to_dict(), "model": self.model.state_dict(), "ema_updates": self.ema.updates,
                 "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                 "step": self.step, "torch_rng": torch.get_rng_state()}
        return save_checkpoint(path, self.ema.shadow, self.model_cfg, {"train": train})

    @classmethod
    def load(cls, path, device="cpu", cfg: TrainConfig | None = None) -> "TrainingState":
        """Read back what :meth:`save` wrote (and set torch's RNG to its state at that time).

        ``cfg``: continue under this configuration instead of the stored one; it may differ from it only in
        :data:`CONTINUATION_FIELDS` (e.g. more steps, another time limit), otherwise TrainingError names the file.
        """
        path = Path(path)
        payload = read_checkpoint(path)
        train = (payload.get("extra") or {}).get("train") or {}
        missing = [k for k in TRAIN_KEYS if k not in train]
        if missing:
            raise TrainingError(f"{path}: not a training checkpoint (extra.train lacks {missing}), so it cannot be "
                                "resumed; train into another --out")
        stored = TrainConfig.from_dict(train["config"])
        cfg = stored if cfg is None else _continuation(stored, cfg, path)
        state = cls.create(cfg, ModelConfig.from_dict(payload["config"]), device)
        state.model.load_state_dict(train["model"])
        state.ema.load_state_dict({"decay": cfg.ema_decay, "updates": train["ema_updates"],
                                   "shadow": payload["state_dict"]})
        state.optimizer.load_state_dict(train["optimizer"])
        state.scheduler.load_state_dict(train["scheduler"])
        state.step = int(train["step"])
        torch.set_rng_state(train["torch_rng"])
        return state


def _continuation(stored: TrainConfig, cfg: TrainConfig, path: Path) -> TrainConfig:
    """``cfg`` if a run trained under ``stored`` may continue under it; TrainingError otherwise."""
    changed = [f.name for f in fields(TrainConfig)
               if f.name not in CONTINUATION_FIELDS and getattr(stored, f.name) != getattr(cfg, f.name)]
    if changed:
        was = ", ".join(f"{k}={getattr(stored, k)!r}" for k in changed)
        now = ", ".join(f"{k}={getattr(cfg, k)!r}" for k in changed)
        raise TrainingError(f"{path} was trained with {was}; this run asks for {now}. Resume with the options of "
                            f"that run (only {', '.join(sorted(CONTINUATION_FIELDS))} may change) or train into "
                            "another --out")
    return cfg
