"""Run logging: a JSON-lines file of every logged step, and TensorBoard event files when tensorboard exists."""
from __future__ import annotations

import json
import math
import time
from pathlib import Path


class RunLogger:
    """Appends one JSON object per logged step to ``<out>/log.jsonl`` (rank 0 only)."""

    def __init__(self, out: Path, enabled: bool = True):
        self.enabled = enabled
        self.path = Path(out) / "log.jsonl"
        self._tb = None
        if enabled:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            try:
                from torch.utils.tensorboard import SummaryWriter  # needs the optional tensorboard package

                self._tb = SummaryWriter(str(Path(out) / "tensorboard"))
            except Exception:  # tensorboard not installed: JSON lines only
                self._tb = None

    def log(self, step: int, values: dict) -> None:
        if not self.enabled:
            return
        record = {"step": step, "time": time.time()}
        record.update({k: (float(v) if isinstance(v, (int, float)) and math.isfinite(float(v)) else str(v))
                       for k, v in values.items()})
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        if self._tb is not None:
            for k, v in values.items():
                if isinstance(v, (int, float)):
                    self._tb.add_scalar(k, v, step)

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
