"""Server settings: one typed ``pydantic-settings`` class, filled from keyword arguments (the command line), the
``OCCFLOWNET_*`` environment variables and a ``.env`` file in the working folder, in that order of precedence, then
the defaults. Every value is validated when the settings are made; a bad one raises :class:`SettingsError` naming
the variable (``OCCFLOWNET_MAX_QUEUE='many': Input should be a valid integer ...``).

The environment is the one channel that reaches every uvicorn worker process (``--workers N`` starts the app from an
import string in fresh processes), so ``occflownet serve`` writes its settings into the environment
(:meth:`ServeSettings.to_env`) and each worker reads them back (:meth:`ServeSettings.from_env`).

| variable                          | field              | default                                              |
|-----------------------------------|--------------------|------------------------------------------------------|
| ``OCCFLOWNET_MODEL``              | model_path         | (required)                                           |
| ``OCCFLOWNET_API_KEY``            | api_key            | unset: no authentication                             |
| ``OCCFLOWNET_MAX_BODY_BYTES``     | max_body_bytes     | 64 MiB                                               |
| ``OCCFLOWNET_MAX_IMAGE_PIXELS``   | max_image_pixels   | 4096 × 4096 per image                                |
| ``OCCFLOWNET_INTRA_OP_THREADS``   | intra_op_threads   | max(1, cores // workers)                             |
| ``OCCFLOWNET_MAX_INFLIGHT``       | max_inflight       | max(1, (cores // workers) // intra_op_threads)       |
| ``OCCFLOWNET_MAX_QUEUE``          | max_queue          | 4 (requests admitted beyond those running)           |
| ``OCCFLOWNET_MAX_UPLOADS``        | max_uploads        | 32 (request bodies being received at once)           |
| ``OCCFLOWNET_BODY_TIMEOUT_S``     | body_timeout_s     | 30: seconds for a whole body to arrive, else 408     |
| ``OCCFLOWNET_SHUTDOWN_TIMEOUT_S`` | shutdown_timeout_s | 20: seconds SIGTERM waits for requests in flight     |
| ``OCCFLOWNET_WORKERS``            | workers            | 1 (only used for the defaults above)                 |
| ``OCCFLOWNET_ORT_SPIN``           | ort_spin           | 0: ORT worker threads sleep between runs             |
| ``OCCFLOWNET_PROVIDERS``          | providers          | CPUExecutionProvider (comma-separated; each must be  |
|                                   |                    | available in this onnxruntime, checked at load time) |
| ``OCCFLOWNET_WARMUP``             | warmup             | 1: one inference before /readyz turns ready          |
| ``OCCFLOWNET_UI``                 | ui                 | 1: the browser page at /ui (0: the API only)         |
| ``OCCFLOWNET_DOCS``               | docs               | 0: no /docs, /redoc (1: on; they load from a CDN)    |

Booleans take 1/0, true/false, yes/no, on/off; an empty variable counts as unset.
"""
from __future__ import annotations

import os
from typing import Annotated

from pydantic import Field, ValidationError, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

ENV_PREFIX = "OCCFLOWNET_"
MODEL_ENV = ENV_PREFIX + "MODEL"
DEFAULT_MAX_BODY_BYTES = 64 * 1024 * 1024
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
DEFAULT_MAX_QUEUE = 4
DEFAULT_MAX_UPLOADS = 32
DEFAULT_BODY_TIMEOUT_S = 30.0
DEFAULT_SHUTDOWN_TIMEOUT_S = 20.0


class SettingsError(ValueError):
    """A setting has a value it cannot take; the message names the variable or field and the value."""


def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware where the OS tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


class ServeSettings(BaseSettings):
    """Everything the app needs; ``None`` fields get their core-dependent defaults from :meth:`resolved`."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_file=".env", env_ignore_empty=True, extra="ignore",
                                      populate_by_name=True, frozen=True)

    # The descriptions are the help of `occflownet serve`'s options (occflownet/options.py add_model_options), "flag"
    # names the option where it is not the field's name; every field but api_key is an option (max_body_bytes in MiB,
    # as --max-body-mb).
    model_path: str = Field("", validation_alias=MODEL_ENV, description="contract-v1 ONNX file",
                            json_schema_extra={"flag": "model"})
    api_key: str | None = Field(None, repr=False, description="bearer key for every route but the probes and the "
                                "page's static files (blank: none)")
    max_body_bytes: int = Field(DEFAULT_MAX_BODY_BYTES, ge=1, description="request body limit")
    max_image_pixels: int = Field(DEFAULT_MAX_IMAGE_PIXELS, ge=1, description="pixels per image, checked from its "
                                  "header before decoding")
    intra_op_threads: int | None = Field(None, ge=1, description="onnxruntime intra-op threads per inference; "
                                         "unset: cores // workers", json_schema_extra={"flag": "threads"})
    max_inflight: int | None = Field(None, ge=1, description="requests computing at once per worker; unset: "
                                     "max(1, cores // workers // threads)")
    max_queue: int = Field(DEFAULT_MAX_QUEUE, ge=0, description="requests admitted beyond those computing; more get "
                           "503 + Retry-After")
    max_uploads: int = Field(DEFAULT_MAX_UPLOADS, ge=1, description="request bodies being received at once; more "
                             "get 503 + Retry-After (a stalled upload never holds an inference or queue place)")
    body_timeout_s: float = Field(DEFAULT_BODY_TIMEOUT_S, gt=0, description="seconds a request body may take to "
                                  "arrive in full, counted from its headers; then 408 and the connection is closed",
                                  json_schema_extra={"flag": "body-timeout"})
    shutdown_timeout_s: float = Field(DEFAULT_SHUTDOWN_TIMEOUT_S, gt=0, description="seconds SIGTERM waits for "
                                      "the requests in flight before it cancels them",
                                      json_schema_extra={"flag": "shutdown-timeout"})
    workers: int = Field(1, ge=1, description="uvicorn worker processes, each with its own model session")
    ort_spin: bool = Field(False, description="onnxruntime threads spin between runs")
    providers: Annotated[list[str], NoDecode] = Field(["CPUExecutionProvider"], min_length=1,
                                                     description="onnxruntime execution providers, comma-separated")
    warmup: bool = Field(True, description="one inference before /readyz turns ready")
    ui: bool = Field(True, description="the browser page at /ui; off: the API only")
    docs: bool = Field(False, description="the interactive API docs at /docs and /redoc (they load Swagger UI and "
                       "ReDoc from a CDN in the browser); /openapi.json is served either way")

    @field_validator("providers", mode="before")
    @classmethod
    def _comma_separated(cls, value):
        return [p.strip() for p in value.split(",") if p.strip()] if isinstance(value, str) else value

    @field_validator("api_key")
    @classmethod
    def _blank_is_none(cls, value: str | None) -> str | None:
        return value if value is not None and value.strip() else None

    @classmethod
    def from_env(cls, **overrides) -> ServeSettings:
        """The settings of the environment (and ``.env``) with ``overrides`` (by field name, ``None`` = not given)
        winning; a bad value raises SettingsError naming its variable (or, for an override, its field)."""
        given = {k: v for k, v in overrides.items() if v is not None}
        try:
            return cls(**given)
        except ValidationError as exc:
            raise SettingsError("; ".join(_describe(e, given) for e in exc.errors())) from None

    def resolved(self) -> ServeSettings:
        """A copy with the core-dependent defaults filled in (``intra_op_threads``, ``max_inflight``)."""
        cores_per_worker = max(1, available_cores() // self.workers)
        threads = self.intra_op_threads or cores_per_worker
        inflight = self.max_inflight or max(1, cores_per_worker // threads)
        return self.model_copy(update={"intra_op_threads": threads, "max_inflight": inflight})

    def to_env(self) -> dict[str, str]:
        """The inverse of :meth:`from_env` for the fields that differ from ``None``."""
        env = {}
        for name, value in self.model_dump().items():
            if value is None:
                continue
            if isinstance(value, bool):
                value = "1" if value else "0"
            elif isinstance(value, list):
                value = ",".join(value)
            env[env_name(name)] = str(value)
        return env


def env_name(field: str) -> str:
    """The environment variable of a :class:`ServeSettings` field."""
    return MODEL_ENV if field == "model_path" else ENV_PREFIX + field.upper()


def _describe(error: dict, overrides: dict) -> str:
    field = str(error["loc"][0]) if error["loc"] else "settings"
    field = "model_path" if field == MODEL_ENV else field
    source = f"setting {field}" if field in overrides else env_name(field)
    return f"{source}={error.get('input')!r}: {error['msg']}"
