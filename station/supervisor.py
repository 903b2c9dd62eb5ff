"""The station's health: which component is down, why, and whether jobs can run.

:meth:`Supervisor.health` looks at every component of an
:class:`station.orchestrator.Orchestrator` (cheaply: memory, one ``statvfs`` per
disk, at most one probe write of the database per second while it is failing)::

    {"status": "ok" | "degraded", "can_run_jobs": bool, "problems": [str, ...],
     "components": {
        "worker":   {"state": "running" | "stopping" | "down", "active_job", "recent_faults"},
        "store":    {"state": "ok" | "down", "error", "since", "unrecorded_jobs",
                     "station_id", "backend", "ownership": "held" | "lost"},
        "storage":  {"state": "ok" | "full", "error", "database_free_bytes",
                     "data_dir_free_bytes", "needed_bytes"},
        "analysis": {"state": "ok" | "down" | "off", "workers", "restarts", "last_fault"}}}

``can_run_jobs`` is false while the worker is down or stopping, the store cannot
be written, a disk is full or the station lost its ownership of a shared job
database (:mod:`station.ownership`: another process may now run its jobs); the
web layer adds the devices and answers 503 then. A component that is down makes
``status`` ``degraded`` and adds one sentence to ``problems``.

Also here: :class:`Unrecorded` (a final state the store refused, kept in memory
until it can be written), :func:`storage_problem` (the free-space check of
``POST /jobs`` and ``resume``) and :func:`white_problem` (``white_from_job``
checked at submission).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from calibration.archive import DEFAULT_RESERVE_BYTES, MANIFEST_NAME, read_manifest
from station.config import StationConfig
from station.db import StorageFull, StoreError, free_bytes
from station.store import JobRecord, JobState

if TYPE_CHECKING:
    from station.orchestrator import Orchestrator

PROBE_INTERVAL_S = 1.0
"""At most one probe write of a failing database per this many seconds."""


@dataclass(frozen=True)
class Unrecorded:
    """A job's final state that the store refused to record.

    Attributes:
        state: the state clients are shown (``interrupted``).
        reason: why, including the store's error.
        at: Unix time (s) it ended.
        error: the store's error (raised again by resume and cancel until written).
    """

    state: JobState
    reason: str
    at: float
    error: Exception


def frame_bytes(config: StationConfig) -> int:
    """Largest size of one stored frame (bytes): the ROI (or sensor) at 16 bits, unpacked."""
    cam = config.camera
    if cam.roi is not None:
        width, height = cam.roi.width, cam.roi.height
    else:
        width, height = cam.sensor_size_px
    return int(width) * int(height) * 2


def storage_problem(config: StationConfig, database: Path, data_dir: Path) -> StorageFull | None:
    """A :class:`StorageFull` when the disk of the database or of the archives has
    less free space than one frame plus the archive's reserve
    (:data:`calibration.archive.DEFAULT_RESERVE_BYTES`), else None."""
    needed = frame_bytes(config) + DEFAULT_RESERVE_BYTES
    for what, path in (("archives", data_dir), ("job database", database)):
        free = free_bytes(path)
        if free is not None and free < needed:
            return StorageFull(
                f"the disk holding the {what} ({path}) is full: {free} bytes free, a frame "
                f"needs {needed} bytes (one {frame_bytes(config)}-byte frame plus the "
                f"{DEFAULT_RESERVE_BYTES}-byte reserve); free space there and try again",
                path=path,
                free_bytes=free,
            )
    return None


def white_problem(job: JobRecord) -> str | None:
    """Why the white image of ``job`` cannot be reused (None: it can)."""
    directory = Path(job.archive_dir)
    if not (directory / MANIFEST_NAME).is_file():
        return f"job {job.id} has no archive (it is {job.state.value}): it has no white image"
    try:
        manifest = read_manifest(directory)
    except Exception as exc:  # noqa: BLE001 - any unreadable manifest is the same answer
        return f"the archive of job {job.id} cannot be read: {exc}"
    if manifest.white_sha256 is None or not (directory / manifest.white).is_file():
        return f"job {job.id} has no white image (it is {job.state.value})"
    return None


class Supervisor:
    """Recent faults of the station's components and the health report."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._faults: dict[str, collections.deque[tuple[float, str]]] = {}
        self._last_probe = 0.0

    def note(self, component: str, message: str) -> None:
        """Remember a fault a component recovered from (the last 5 per component)."""
        with self._lock:
            self._faults.setdefault(component, collections.deque(maxlen=5)).append(
                (time.time(), message)
            )

    def recent(self, component: str) -> list[dict[str, Any]]:
        with self._lock:
            return [{"at": at, "message": m} for at, m in self._faults.get(component, ())]

    def _store_state(self, station: Orchestrator) -> dict[str, Any]:
        store = station.store
        health = store.health
        if not health.ok:
            now = time.monotonic()
            if now - self._last_probe >= PROBE_INTERVAL_S:  # has it come back?
                self._last_probe = now
                try:
                    store.probe_write()
                except StoreError:
                    pass
                health = store.health
        unrecorded = station.unrecorded_jobs
        out: dict[str, Any] = {
            "state": "ok" if health.ok and not unrecorded else "down",
            "error": health.error,
            "since": health.since,
            "unrecorded_jobs": sorted(unrecorded),
            "open_connections": health.open_connections,
        }
        if health.ok and unrecorded:
            out["error"] = "final states not yet recorded: " + "; ".join(
                f"job {k}: {v}" for k, v in sorted(unrecorded.items())
            )
        return out

    def health(self, station: Orchestrator) -> dict[str, Any]:
        """The report of the module docstring."""
        problems: list[str] = []
        components: dict[str, Any] = {}
        worker: dict[str, Any]
        if station.stopping:
            worker = {"state": "stopping"}
            problems.append("the station is shutting down")
        elif not station.worker_alive:
            worker = {"state": "down"}
            problems.append("the hardware worker is not running")
        else:
            worker = {"state": "running"}
        worker["active_job"] = station.active_job
        worker["recent_faults"] = self.recent("worker")
        components["worker"] = worker

        store = self._store_state(station)
        components["store"] = store
        if store["state"] != "ok":
            problems.append(f"job store: {store['error']}")

        full = storage_problem(station.config, station.db_path, station.data_dir)
        components["storage"] = {
            "state": "ok" if full is None else "full",
            "error": None if full is None else str(full),
            "database_free_bytes": free_bytes(station.db_path),
            "data_dir_free_bytes": free_bytes(station.data_dir),
            "needed_bytes": frame_bytes(station.config) + DEFAULT_RESERVE_BYTES,
        }
        if full is not None:
            problems.append(str(full))

        components["store"]["station_id"] = station.store.station_id
        components["store"]["backend"] = "postgresql" if station.store.postgres else "sqlite"
        lost = station.ownership_problem
        components["store"]["ownership"] = "held" if lost is None else "lost"
        if lost is not None:  # another process may run this station's jobs: run none here
            problems.append(lost)
        uploader = getattr(station, "uploader", None)
        if uploader is None:
            components["archives"] = {"state": "local"}
        else:  # an object-store outage delays uploads; frames stay local, jobs go on
            upload = uploader.status()
            upload["state"] = "ok" if upload["error"] is None else "behind"
            components["archives"] = upload
            if upload["error"] is not None:
                problems.append(
                    f"archives: {upload['error']} ({len(upload['pending_jobs'])} jobs waiting "
                    "for upload; their frames are kept on the local disk)"
                )

        pool = station.analysis_pool
        if pool is None:
            components["analysis"] = {"state": "off"}
        else:
            analysis = pool.health()
            components["analysis"] = analysis
            if analysis["state"] != "ok":
                problems.append(f"analysis: {analysis['last_fault']}")

        can_run = (
            worker["state"] == "running" and store["state"] == "ok" and full is None and not lost
        )
        return {
            "status": "ok" if not problems else "degraded",
            "can_run_jobs": can_run,
            "problems": problems,
            "components": components,
        }


__all__ = [
    "PROBE_INTERVAL_S",
    "Supervisor",
    "Unrecorded",
    "frame_bytes",
    "storage_problem",
    "white_problem",
]
