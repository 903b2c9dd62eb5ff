"""The read side of the station's API: job status, records, results, frames and events.

:class:`JobReads` is what :class:`station.orchestrator.Orchestrator` answers without
changing anything: every method is thread-safe and returns quickly (status from memory
for the active job, the store otherwise), except the two ``wait_for*`` methods, which
block until a condition holds or their timeout passes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from station.archive_source import ArchiveReader
from station.config import StationConfig
from station.events import EventHub, JobEvent, Subscription
from station.hardware_worker import HardwareWorker
from station.job_ledger import JobLedger
from station.job_records import (
    JobStatus,
    archive_dir_of,
    frame_path_of,
    read_frame_of,
    replay_events,
    result_of,
    status_of,
)
from station.run_control import StepTiming
from station.store import ACTIVE_STATES, JobRecord, JobState, StepRecord, Transition


class JobReads:
    """Queries and event streams over the ledger, the worker and the store (a base of
    :class:`station.orchestrator.Orchestrator`, which sets the attributes below; the store
    is the ledger's, so reading before the station started raises ``RuntimeError``)."""

    config: StationConfig
    hub: EventHub
    _ledger: JobLedger
    _worker: HardwareWorker
    _archives: ArchiveReader

    # ------------------------------------------------------------------ queries

    def status(self, job_id: int) -> JobStatus:
        """The job's state and progress (:class:`station.store.JobNotFound` if unknown).

        Polled from the HTTP server's event loop: it reads memory only (the job's
        row from :class:`station.job_cache.JobRecordCache`, the active job's live
        progress; the store only on a cache miss) and takes no lock that the
        worker holds while it stores a result.
        """
        job = self._ledger.record(job_id, cached=True)
        active = self._worker.active_for(job_id)  # no lock (see above)
        if active is None or job.state not in ACTIVE_STATES:
            steps = self._ledger.rows.step_count(job, lambda: self._ledger.store.step_count(job_id))
            return status_of(job, steps)
        with self._worker.progress_lock:
            p = active.progress
            return status_of(
                job,
                p.frames_done,
                frames_analysed=p.frames_analysed,
                phase=p.phase,
                rail_mm=p.rail_mm,
                eta_s=p.eta_s(),
                pause_requested=p.pause_requested,
                cancel_requested=p.cancel_requested,
                recent_fault=p.last_error,
            )

    def jobs(self, states: Iterable[JobState] | None = None) -> list[JobStatus]:
        """Every job (oldest first), optionally only those in ``states``."""
        records = self._ledger.store.list_jobs(states=set(states) if states else None)
        return [self.status(job.id) for job in records]

    def record(self, job_id: int) -> JobRecord:
        """The job's stored row, with its result (or a failed calibration's partial one)."""
        return self._ledger.record(job_id, with_result=True)

    def transitions(self, job_id: int) -> list[Transition]:
        """Every state change of the job with its time and reason."""
        self._ledger.store.get_job(job_id)
        return self._ledger.store.transitions(job_id)

    def steps(self, job_id: int) -> list[StepRecord]:
        """The job's recorded steps in index order."""
        self._ledger.store.get_job(job_id)
        return self._ledger.store.steps(job_id)

    def result(self, job_id: int) -> dict[str, Any]:
        """The calibration result (JSON object) of a succeeded job (:func:`station.job_records.result_of`:
        :class:`ResultNotReady` while it runs or when it ended without one)."""
        return result_of(self._ledger.record(job_id, with_result=True), self._ledger.store)

    def archive_dir(self, job_id: int) -> Path:
        """The job's ``lfcal-sweep/1`` directory, local or fetched from object storage."""
        return archive_dir_of(self._ledger.store, self._archives, job_id)

    def frame_path(self, job_id: int, index: int) -> Path:
        """The file of a recorded frame (:class:`FrameNotFound` otherwise)."""
        return frame_path_of(self._ledger.store, self._archives, job_id, index)

    def read_frame(self, job_id: int, index: int) -> Any:
        """A recorded frame as counts (:func:`station.job_records.read_frame_of`)."""
        return read_frame_of(self._ledger.store, self._archives, job_id, index)

    def step_timings(self, job_id: int) -> list[StepTiming]:
        """Hardware-thread timings of the steps this process ran for the job."""
        return self._worker.step_timings(job_id)

    # ------------------------------------------------------------------ events

    def subscribe(self, job_id: int | None = None) -> Subscription:
        """Live events of one job (or all); combine with :meth:`replay` for SSE."""
        return self.hub.subscribe(job_id)

    def add_listener(self, callback: Callable[[JobEvent], None]) -> None:
        """Call ``callback(event)`` for every event, in the publishing thread (must not block)."""
        self.hub.add_callback(callback)

    def remove_listener(self, callback: Callable[[JobEvent], None]) -> None:
        self.hub.remove_callback(callback)

    def replay(self, job_id: int, after: int | None = None) -> list[JobEvent]:
        """The job's recorded steps after ``after`` and its current state as events
        (:func:`station.job_records.replay_events`; the SSE recipe is there)."""
        return replay_events(
            self._ledger.store,
            self._ledger.record(job_id),
            after,
            reference_gap_mm=self.config.board.reference_gap_mm,
        )

    def wait_for(self, job_id: int, states: Iterable[JobState], timeout_s: float) -> JobStatus:
        """Block until the job is in one of ``states``; ``TimeoutError`` after ``timeout_s``."""
        self._ledger.wait_for(job_id, states, timeout_s)
        return self.status(job_id)

    def wait_for_frames(self, job_id: int, count: int, timeout_s: float) -> JobStatus:
        """Block until at least ``count`` frames are recorded (or the job stopped)."""
        deadline = time.monotonic() + timeout_s
        with self.subscribe(job_id) as sub:
            while True:
                status = self.status(job_id)
                if status.frames_done >= count:
                    return status
                if status.state not in (JobState.QUEUED, *ACTIVE_STATES):
                    raise RuntimeError(
                        f"job {job_id} is {status.state.value} with {status.frames_done} "
                        f"frames: {status.last_error}"
                    )
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"job {job_id} has {status.frames_done} of {count} frames after "
                        f"{timeout_s:g} s"
                    )
                sub.get(min(left, 1.0))
