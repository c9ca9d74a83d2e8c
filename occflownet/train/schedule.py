"""Learning-rate schedule: linear warm-up to the base rate, then constant (the official recipe's shape) or a cosine
decay to 0 at the last step (``TrainConfig.lr_schedule``)."""
from __future__ import annotations

import math

import torch

from occflownet.choices import LR_SCHEDULES


def lr_factor(step: int, warmup_steps: int, kind: str = "constant", total_steps: int = 0) -> float:
    """The multiple of the base rate at optimiser step ``step`` (0-based): ``min(1, (step + 1) / warmup_steps)``
    during the warm-up; then 1 (``"constant"``) or ``0.5 (1 + cos(π p))`` with p = (step + 1 − warmup) /
    (total − warmup) ∈ [0, 1] (``"cosine"``: the last of ``total_steps`` steps runs at 0)."""
    if kind not in LR_SCHEDULES:
        raise ValueError(f"lr schedule must be one of {LR_SCHEDULES}, got {kind!r}")
    warmup_steps = max(1, int(warmup_steps))
    if step + 1 < warmup_steps or kind == "constant":
        return min(1.0, (step + 1) / warmup_steps)
    progress = min(1.0, (step + 1 - warmup_steps) / max(1, total_steps - warmup_steps))
    return 0.5 * (1.0 + math.cos(math.pi * progress))


def warmup_schedule(optimizer: torch.optim.Optimizer, warmup_steps: int, kind: str = "constant",
                    total_steps: int = 0) -> torch.optim.lr_scheduler.LambdaLR:
    """The schedule of :func:`lr_factor` on ``optimizer``'s base rates."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: lr_factor(step, warmup_steps, kind, total_steps))
