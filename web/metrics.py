"""``GET /metrics``: the station in the Prometheus text format (prometheus-client).

Metrics (one registry per app, not the process-global one):

``lfcal_jobs{state}``
    jobs in the job store by state (gauge, read from the store at each scrape).
``lfcal_frames_captured_total``
    frames written and recorded since the server started (counter; ``step`` events).
``lfcal_step_seconds``
    wall time of a sweep step on the hardware thread: move, settle, grab and
    bookkeeping (histogram; from the station's step timings, each step once).
``lfcal_faults_total{kind}``
    device faults the station recovered from, by what it did about them
    (``retry``, ``rehome``, ``reconnect``), and ``lfcal_jobs_failed_total`` for
    jobs that ended failed (counters; ``fault`` and ``state`` events).
``lfcal_analysis_backlog_frames``
    frames recorded but not yet analysed by the streaming analysis, over the
    active jobs (gauge, read at each scrape).
``lfcal_info{version}``
    the software version (always 1).

Counts go through the station's public API (the job store's reads, the event
listener, ``status`` and ``step_timings``), never its internals.
"""

from __future__ import annotations

import threading
from collections import Counter as CountOf
from collections.abc import Iterable
from typing import Any

from fastapi import APIRouter, Depends
from fastapi.responses import Response
from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from calibration.version import software_version
from station.events import JobEvent
from station.orchestrator import Orchestrator
from station.store import ACTIVE_STATES, JobState
from web.security import check_key

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
STEP_BUCKETS_S = (0.05, 0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0)


def fault_kind(data: dict[str, Any]) -> str:
    """The kind of a recovered fault: the event's ``kind`` when it has one, else the first
    word of its ``action`` (``retry``, ``rehome``, ``reconnect``)."""
    kind = data.get("kind")
    if isinstance(kind, str) and kind:
        return kind
    action = str(data.get("action") or "unknown").strip()
    return action.split(" ", 1)[0] or "unknown"


class StationMetrics(Collector):
    """The metrics of one station (see the module docstring); call :meth:`close` to detach."""

    def __init__(self, station: Orchestrator) -> None:
        self.station = station
        self.registry = CollectorRegistry(auto_describe=True)
        self.frames = Counter(
            "lfcal_frames_captured",
            "Frames written and recorded since the server started",
            registry=self.registry,
        )
        self.faults = Counter(
            "lfcal_faults",
            "Device faults the station recovered from, by kind",
            ["kind"],
            registry=self.registry,
        )
        self.failed = Counter(
            "lfcal_jobs_failed",
            "Jobs that ended failed since the server started",
            registry=self.registry,
        )
        self.step_time = Histogram(
            "lfcal_step_seconds",
            "Wall time of one sweep step on the hardware thread (move, settle, grab, bookkeeping)",
            buckets=STEP_BUCKETS_S,
            registry=self.registry,
        )
        self._lock = threading.Lock()
        self._timed: dict[int, int] = {}  # job id -> step timings already observed
        self.registry.register(self)
        station.add_listener(self._on_event)

    def close(self) -> None:
        """Stop listening to the station."""
        self.station.remove_listener(self._on_event)

    def _on_event(self, event: JobEvent) -> None:
        """Station thread: count frames, faults and failed jobs (must not block)."""
        if event.type == "step" and not event.data.get("replayed"):
            self.frames.inc()
            with self._lock:
                self._timed.setdefault(event.job_id, 0)
        elif event.type == "fault":
            self.faults.labels(kind=fault_kind(event.data)).inc()
        elif event.type == "state" and event.data.get("state") == JobState.FAILED.value:
            self.failed.inc()

    def _observe_step_times(self) -> None:
        with self._lock:
            jobs = dict(self._timed)
        for job_id, seen in jobs.items():
            timings = self.station.step_timings(job_id)
            for t in timings[seen:]:
                self.step_time.observe(t.total_s)
            with self._lock:
                self._timed[job_id] = max(seen, len(timings))

    def describe(self) -> Iterable[Metric]:
        return []

    def collect(self) -> Iterable[Metric]:
        """The store-derived gauges (the counters and the histogram collect themselves)."""
        jobs = GaugeMetricFamily("lfcal_jobs", "Jobs in the job store by state", labels=["state"])
        counts = CountOf(job.state for job in self.station.store.list_jobs())
        for state in JobState:
            jobs.add_metric([state.value], counts.get(state, 0))
        yield jobs
        backlog = 0
        for job in self.station.store.list_jobs(states=set(ACTIVE_STATES)):
            status = self.station.status(job.id)
            if status.frames_analysed is not None:
                backlog += max(0, status.frames_done - status.frames_analysed)
        yield GaugeMetricFamily(
            "lfcal_analysis_backlog_frames",
            "Frames recorded but not yet analysed (active jobs)",
            value=backlog,
        )
        info = GaugeMetricFamily("lfcal_info", "lfcal-station version", labels=["version"])
        info.add_metric([software_version()], 1)
        yield info

    def exposition(self) -> bytes:
        """The Prometheus text exposition of every metric (new step times observed first)."""
        self._observe_step_times()
        return bytes(generate_latest(self.registry))


def build_metrics_router(metrics: StationMetrics, *, read_key: bool) -> APIRouter:
    """``GET /metrics`` (keyed when ``read_key``)."""
    router = APIRouter(tags=["station"])
    deps = [Depends(check_key)] if read_key else []

    @router.get(
        "/metrics",
        response_class=Response,
        dependencies=deps,
        responses={200: {"content": {CONTENT_TYPE: {}}, "description": "Prometheus text format"}},
        summary="Station metrics in the Prometheus text format",
    )
    def metrics_route() -> Response:
        """Jobs by state, frames captured, step time, recovered faults by kind, analysis
        backlog (see :mod:`web.metrics`)."""
        return Response(content=metrics.exposition(), media_type=CONTENT_TYPE)

    return router


__all__ = ["StationMetrics", "build_metrics_router", "fault_kind"]
