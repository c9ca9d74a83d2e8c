"""Learning-rate schedule: linear warm-up to the base rate, then constant (the official recipe's shape)."""
from __future__ import annotations

import torch


def warmup_schedule(optimizer: torch.optim.Optimizer, warmup_steps: int) -> torch.optim.lr_scheduler.LambdaLR:
    """``lr(step) = base_lr * min(1, (step + 1) / warmup_steps)``."""
    warmup_steps = max(1, int(warmup_steps))
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: min(1.0, (step + 1) / warmup_steps))
