"""The server's Prometheus metrics, kept by ``prometheus_client``.

One process (``--workers 1``, tests): the metrics live in the :class:`Metrics` object's own registry. Several
worker processes (``--workers N``): ``occflownet serve`` points ``PROMETHEUS_MULTIPROC_DIR`` at a fresh folder
before the workers start (:func:`multiprocess_dir`), every worker writes its values there (prometheus_client's
multiprocess mode), and a scrape of ``/metrics`` — whichever worker answers it — is the aggregate of all of them:
counters and histograms summed over the workers, the in-flight/queue/running gauges summed over the live ones, the
readiness the minimum (1 only when every live worker is ready), the start time the earliest.

- ``occflownet_http_requests_total{route,method,status}``       counter
- ``occflownet_http_request_duration_seconds{route}``            histogram (whole request, server side)
- ``occflownet_stage_duration_seconds{stage}``                   histogram, stage ∈ decode, queue, inference, encode
- ``occflownet_http_requests_in_flight``                         gauge
- ``occflownet_inference_queue_depth`` / ``_inferences_running`` gauges (admitted, waiting / running)
- ``occflownet_uploads_in_progress``                             gauge (request bodies being received)
- ``occflownet_rejected_total{reason}``                          counter (saturated, not_ready, uploads)
- ``occflownet_model_ready``                                     gauge 0/1
- ``occflownet_process_start_time_seconds``                      gauge
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import prometheus_client
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest, multiprocess

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
CONTENT_TYPE = prometheus_client.CONTENT_TYPE_LATEST
STAGES = ("decode", "queue", "inference", "encode")
REJECT_REASONS = ("saturated", "not_ready", "uploads")
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"  # prometheus_client's own variable

prometheus_client.disable_created_metrics()  # no *_created series: the start time is its own gauge


def multiprocess_enabled() -> bool:
    """Whether this process writes its metrics to ``PROMETHEUS_MULTIPROC_DIR`` (set before prometheus_client was
    imported: it chooses where values live at import)."""
    return bool(os.environ.get(MULTIPROC_ENV))


@contextmanager
def multiprocess_dir():
    """For ``occflownet serve --workers N``: ``PROMETHEUS_MULTIPROC_DIR`` set for the worker processes while the
    block runs → the folder. A folder the user named in that variable is used and emptied of old metric files
    first (prometheus_client needs a clean folder per run); otherwise a fresh temporary one, removed afterwards."""
    given = os.environ.get(MULTIPROC_ENV)
    folder = Path(given) if given else Path(tempfile.mkdtemp(prefix="occflownet-metrics-"))
    folder.mkdir(parents=True, exist_ok=True)
    for stale in folder.glob("*.db"):
        stale.unlink()
    os.environ[MULTIPROC_ENV] = str(folder)
    try:
        yield folder
    finally:
        if given:
            for db in folder.glob("*.db"):
                db.unlink()
        else:
            os.environ.pop(MULTIPROC_ENV, None)
            shutil.rmtree(folder, ignore_errors=True)


class Metrics:
    """The server's metrics (module docstring); :meth:`render` gives the exposition text of this process, or of
    all worker processes in multiprocess mode."""

    def __init__(self):
        self.multiprocess = multiprocess_enabled()
        self._registry = None if self.multiprocess else CollectorRegistry(auto_describe=True)
        reg = {"registry": self._registry}
        self.requests = Counter("occflownet_http_requests", "HTTP requests answered, by route, method and status.",
                                ("route", "method", "status"), **reg)
        self.request_duration = Histogram("occflownet_http_request_duration_seconds",
                                          "Server-side request duration by route.", ("route",), buckets=BUCKETS,
                                          **reg)
        self.stage_duration = Histogram("occflownet_stage_duration_seconds", "Time per stage of POST /v1/occupancy.",
                                        ("stage",), buckets=BUCKETS, **reg)
        self.rejected = Counter("occflownet_rejected", "Requests refused with 503, by reason.",
                                ("reason",), **reg)
        self.in_flight = Gauge("occflownet_http_requests_in_flight", "HTTP requests being handled now.",
                               multiprocess_mode="livesum", **reg)
        self.queue_depth = Gauge("occflownet_inference_queue_depth",
                                 "Admitted occupancy requests not yet running inference.", multiprocess_mode="livesum",
                                 **reg)
        self.running = Gauge("occflownet_inferences_running", "Inferences running now.", multiprocess_mode="livesum",
                             **reg)
        self.uploads = Gauge("occflownet_uploads_in_progress", "Request bodies being received now.",
                             multiprocess_mode="livesum", **reg)
        self.ready = Gauge("occflownet_model_ready", "1 once the warm-up inference has succeeded (every worker).",
                           multiprocess_mode="livemin", **reg)
        self.started = Gauge("occflownet_process_start_time_seconds", "Start time of the process (Unix time).",
                             multiprocess_mode="livemin", **reg)
        for stage in STAGES:
            self.stage_duration.labels(stage=stage)
        for reason in REJECT_REASONS:
            self.rejected.labels(reason=reason)
        self.ready.set(0)
        self.started.set(time.time())

    def request_started(self) -> None:
        self.in_flight.inc()

    def request_finished(self, route: str, method: str, status: int, seconds: float) -> None:
        self.in_flight.dec()
        self.requests.labels(route=route, method=method, status=str(status)).inc()
        self.request_duration.labels(route=route).observe(seconds)

    def observe_stage(self, stage: str, seconds: float) -> None:
        self.stage_duration.labels(stage=stage).observe(seconds)

    def reject(self, reason: str) -> None:
        self.rejected.labels(reason=reason).inc()

    def set_gate(self, queued: int, running: int) -> None:
        self.queue_depth.set(queued)
        self.running.set(running)

    def set_uploads(self, active: int) -> None:
        self.uploads.set(active)

    def set_ready(self) -> None:
        self.ready.set(1)

    def render(self) -> bytes:
        """The exposition text: this process's registry, or in multiprocess mode the aggregate of every worker."""
        if not self.multiprocess:
            return generate_latest(self._registry)
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        return generate_latest(registry)

    def process_exited(self) -> None:
        """In multiprocess mode: drop this process's live gauges from the aggregate (called at shutdown)."""
        if self.multiprocess:
            multiprocess.mark_process_dead(os.getpid())
