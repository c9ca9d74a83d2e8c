"""Prometheus metrics in the text exposition format (version 0.0.4), written by hand: no extra dependency.

Metrics are per process: with ``--workers N`` each worker keeps and serves its own counters (a scrape reaches one
worker), so run one worker per container/pod when the numbers matter, or sum across scrapes.

- ``occflownet_http_requests_total{route,method,status}``       counter
- ``occflownet_http_request_duration_seconds{route}``            histogram (whole request, server side)
- ``occflownet_stage_duration_seconds{stage}``                   histogram, stage ∈ decode, queue, inference, encode
- ``occflownet_http_requests_in_flight``                         gauge
- ``occflownet_inference_queue_depth`` / ``_inferences_running`` gauges (admitted, waiting / running)
- ``occflownet_rejected_total{reason}``                          counter (saturated, not_ready)
- ``occflownet_model_ready``                                     gauge 0/1
"""
from __future__ import annotations

import bisect
import threading
import time

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
STAGES = ("decode", "queue", "inference", "encode")


def _labels(pairs: tuple) -> str:
    if not pairs:
        return ""
    text = ",".join(f'{k}="{str(v).replace(chr(92), chr(92) * 2).replace(chr(34), chr(92) + chr(34))}"'
                    for k, v in pairs)
    return "{" + text + "}"


class _Histogram:
    def __init__(self):
        self.counts = [0] * (len(BUCKETS) + 1)
        self.sum = 0.0

    def observe(self, seconds: float) -> None:
        self.counts[bisect.bisect_left(BUCKETS, seconds)] += 1
        self.sum += seconds

    def lines(self, name: str, labels: tuple) -> list[str]:
        out, running = [], 0
        for bound, count in zip((*BUCKETS, float("inf")), self.counts):
            running += count
            le = "+Inf" if bound == float("inf") else repr(bound)
            out.append(f"{name}_bucket{_labels((*labels, ('le', le)))} {running}")
        out.append(f"{name}_sum{_labels(labels)} {self.sum!r}")
        out.append(f"{name}_count{_labels(labels)} {running}")
        return out


class Metrics:
    """Thread-safe registry of the server's metrics; :meth:`render` gives the exposition text."""

    def __init__(self):
        self._lock = threading.Lock()
        self.requests: dict[tuple, int] = {}
        self.request_duration: dict[str, _Histogram] = {}
        self.stage_duration = {stage: _Histogram() for stage in STAGES}
        self.rejected: dict[str, int] = {}
        self.in_flight = 0
        self.queue_depth = 0
        self.running = 0
        self.ready = 0
        self.started = time.time()

    def request_started(self) -> None:
        with self._lock:
            self.in_flight += 1

    def request_finished(self, route: str, method: str, status: int, seconds: float) -> None:
        with self._lock:
            self.in_flight -= 1
            key = (route, method, str(status))
            self.requests[key] = self.requests.get(key, 0) + 1
            self.request_duration.setdefault(route, _Histogram()).observe(seconds)

    def observe_stage(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.stage_duration[stage].observe(seconds)

    def reject(self, reason: str) -> None:
        with self._lock:
            self.rejected[reason] = self.rejected.get(reason, 0) + 1

    def set_gate(self, queued: int, running: int) -> None:
        with self._lock:
            self.queue_depth, self.running = queued, running

    def render(self) -> str:
        with self._lock:
            lines = [
                "# HELP occflownet_http_requests_total HTTP requests answered, by route, method and status.",
                "# TYPE occflownet_http_requests_total counter",
            ]
            for (route, method, status), n in sorted(self.requests.items()):
                lines.append(f"occflownet_http_requests_total"
                             f"{_labels((('route', route), ('method', method), ('status', status)))} {n}")
            lines += ["# HELP occflownet_http_request_duration_seconds Server-side request duration by route.",
                      "# TYPE occflownet_http_request_duration_seconds histogram"]
            for route, hist in sorted(self.request_duration.items()):
                lines += hist.lines("occflownet_http_request_duration_seconds", (("route", route),))
            lines += ["# HELP occflownet_stage_duration_seconds Time per stage of POST /v1/occupancy.",
                      "# TYPE occflownet_stage_duration_seconds histogram"]
            for stage in STAGES:
                lines += self.stage_duration[stage].lines("occflownet_stage_duration_seconds", (("stage", stage),))
            lines += ["# HELP occflownet_rejected_total Occupancy requests refused with 503, by reason.",
                      "# TYPE occflownet_rejected_total counter"]
            for reason in ("saturated", "not_ready"):
                lines.append(f"occflownet_rejected_total{_labels((('reason', reason),))} "
                             f"{self.rejected.get(reason, 0)}")
            for name, help_text, value in (
                ("occflownet_http_requests_in_flight", "HTTP requests being handled now.", self.in_flight),
                ("occflownet_inference_queue_depth", "Admitted occupancy requests not yet running inference.",
                 self.queue_depth),
                ("occflownet_inferences_running", "Inferences running now.", self.running),
                ("occflownet_model_ready", "1 once the warm-up inference has succeeded.", self.ready),
                ("occflownet_process_start_time_seconds", "Start time of the process (Unix time).", self.started),
            ):
                lines += [f"# HELP {name} {help_text}", f"# TYPE {name} gauge", f"{name} {value}"]
        return "\n".join(lines) + "\n"
