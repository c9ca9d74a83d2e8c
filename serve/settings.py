"""Server settings: one typed dataclass, filled from ``OCCFLOWNET_*`` environment variables or the CLI.

The environment is the one channel that reaches every uvicorn worker process (``--workers N`` starts the app from an
import string in fresh processes), so ``occflownet serve`` writes its options into the environment and each worker
reads them back with :meth:`ServeSettings.from_env`.

| variable                          | field              | default                                              |
|-----------------------------------|--------------------|------------------------------------------------------|
| ``OCCFLOWNET_MODEL``              | model_path         | (required)                                           |
| ``OCCFLOWNET_API_KEY``            | api_key            | unset: no authentication                             |
| ``OCCFLOWNET_MAX_BODY_BYTES``     | max_body_bytes     | 64 MiB                                               |
| ``OCCFLOWNET_MAX_IMAGE_PIXELS``   | max_image_pixels   | 4096 × 4096 per image                                |
| ``OCCFLOWNET_INTRA_OP_THREADS``   | intra_op_threads   | max(1, cores // workers)                             |
| ``OCCFLOWNET_MAX_INFLIGHT``       | max_inflight       | max(1, (cores // workers) // intra_op_threads)       |
| ``OCCFLOWNET_MAX_QUEUE``          | max_queue          | 4 (requests admitted beyond those running)           |
| ``OCCFLOWNET_WORKERS``            | workers            | 1 (only used for the defaults above)                 |
| ``OCCFLOWNET_ORT_SPIN``           | ort_spin           | 0: ORT worker threads sleep between runs             |
| ``OCCFLOWNET_PROVIDERS``          | providers          | CPUExecutionProvider (comma-separated list)          |
| ``OCCFLOWNET_WARMUP``             | warmup             | 1: one inference before /readyz turns ready          |
| ``OCCFLOWNET_UI``                 | ui                 | 1: the browser page at /ui (0: the API only)         |
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field, fields

ENV_PREFIX = "OCCFLOWNET_"
DEFAULT_MAX_BODY_BYTES = 64 * 1024 * 1024
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
DEFAULT_MAX_QUEUE = 4
MAX_CALIBRATION_BYTES = 1024 * 1024


def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware where the OS tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


@dataclass
class ServeSettings:
    """Everything the app needs; ``None`` fields get their defaults from :meth:`resolved`."""

    model_path: str = ""
    api_key: str | None = None
    max_body_bytes: int = DEFAULT_MAX_BODY_BYTES
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    intra_op_threads: int | None = None
    max_inflight: int | None = None
    max_queue: int = DEFAULT_MAX_QUEUE
    workers: int = 1
    ort_spin: bool = False
    providers: list[str] = field(default_factory=lambda: ["CPUExecutionProvider"])
    warmup: bool = True
    ui: bool = True

    def resolved(self) -> "ServeSettings":
        """A copy with the core-dependent defaults filled in and every limit checked (ValueError names the field)."""
        cores_per_worker = max(1, available_cores() // max(1, self.workers))
        threads = self.intra_op_threads or cores_per_worker
        inflight = self.max_inflight or max(1, cores_per_worker // threads)
        out = ServeSettings(**{**asdict(self), "intra_op_threads": threads, "max_inflight": inflight})
        for name in ("max_body_bytes", "max_image_pixels", "intra_op_threads", "max_inflight", "workers"):
            if getattr(out, name) < 1:
                raise ValueError(f"setting {name} must be >= 1, got {getattr(out, name)}")
        if out.max_queue < 0:
            raise ValueError(f"setting max_queue must be >= 0, got {out.max_queue}")
        if out.api_key is not None and not out.api_key.strip():
            out.api_key = None
        return out

    @classmethod
    def from_env(cls, environ: dict | None = None) -> "ServeSettings":
        """Read ``OCCFLOWNET_<FIELD>`` variables; a malformed value raises ValueError naming the variable."""
        env = os.environ if environ is None else environ
        values: dict = {}
        for f in fields(cls):
            var = ENV_PREFIX + ("MODEL" if f.name == "model_path" else f.name.upper())
            raw = env.get(var)
            if raw is None or raw == "":
                continue
            try:
                values[f.name] = _parse(f.name, raw)
            except ValueError as exc:
                raise ValueError(f"environment variable {var}={raw!r}: {exc}") from None
        return cls(**values)

    def to_env(self) -> dict[str, str]:
        """The inverse of :meth:`from_env` for the fields that differ from ``None``."""
        env = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            var = ENV_PREFIX + ("MODEL" if f.name == "model_path" else f.name.upper())
            if isinstance(value, bool):
                env[var] = "1" if value else "0"
            elif isinstance(value, list):
                env[var] = ",".join(value)
            else:
                env[var] = str(value)
        return env


def _parse(name: str, raw: str):
    if name in ("model_path", "api_key"):
        return raw
    if name in ("ort_spin", "warmup", "ui"):
        low = raw.strip().lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ValueError("expected 1/0, true/false, yes/no or on/off")
    if name == "providers":
        return [p.strip() for p in raw.split(",") if p.strip()]
    return int(raw)
