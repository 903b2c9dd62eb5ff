"""The station orchestrator: the job queue, the one hardware worker, and the API.

:class:`Orchestrator` is what the web layer and ``lfcal sweep`` use::

    station = Orchestrator(load_config("config/simulated.toml")).start()
    job = station.submit({"start_mm": 0, "stop_mm": 99, "step_mm": 1})
    with station.subscribe(job.id) as events:        # step / analysis / state / phase
        ...
    station.wait_for(job.id, {JobState.SUCCEEDED, JobState.FAILED}, timeout_s=600)
    station.result(job.id)                            # the calibration (JSON object)
    station.close()

Threads: **one hardware worker** owns the devices (opens them, runs one job at a
time in submission order, closes them); one archive-writer thread per running
job; the analysis runs in worker processes. Every public method is thread-safe
and returns quickly: status comes from memory for the active job and from the
SQLite store otherwise.

Pause and cancel of the active job are *requests*: the job changes state at
the next step boundary (the rail is stopped and every captured frame written
first); :attr:`JobStatus.pause_requested` / ``cancel_requested`` show a pending
request. A paused job keeps the hardware worker (later jobs wait) until it is
resumed or cancelled. A queued or interrupted job is cancelled at once.
``resume`` continues a paused job, or re-queues an interrupted or failed one,
which then continues from its first missing frame.

Start-up (:meth:`Orchestrator.start`): the station's ownership
(:mod:`station.ownership`: an exclusive lock on a SQLite file, or this station's
advisory lock on a shared PostgreSQL database; it dies with the process), the job
store (schema migrated), then every job *of this station* found ``running`` or
``paused`` -- the previous process died under it -- has its frames verified
against the stored checksums (:func:`station.recovery.reconcile`) and becomes
``interrupted``; this station's queued jobs are run in order. Jobs of other
stations sharing the database are visible but never run, paused, resumed or
cancelled here (:class:`station.ownership.ForeignJob`, 409). With ``[storage]
archive_url`` the archives are uploaded by :class:`station.archive_sync.ArchiveUploader`
(the object store must be reachable at start-up).

**Supervision** (:mod:`station.supervisor`): the hardware worker never dies
of an exception. Whatever escapes a run (a bug, the store refusing a write)
ends the job in a final state with the reason -- ``failed``, or
``interrupted`` when the store itself cannot be written: that state is then
kept in memory (:meth:`Orchestrator.status` and the event streams show it),
written as soon as the store accepts writes again, and in any case found by
the next start's recovery. The worker then goes on serving the queue (a job
that cannot be marked ``running`` stays ``queued`` until the store can be
written). :meth:`Orchestrator.health` says what is down and whether jobs can
run.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.analysis import AnalysisPool
from station.archive_source import ArchiveReader
from station.config import StationConfig
from station.device_holder import DeviceHolder
from station.events import EventHub, JobEvent, LiveProgress, Subscription
from station.job_cache import JobRecordCache
from station.job_records import (
    FrameNotFound,
    JobStatus,
    ResultNotReady,
    archive_dir_of,
    frame_path_of,
    read_frame_of,
    replay_events,
    result_of,
    status_of,
)
from station.ownership import ForeignJob, Ownership, StationBusy, claim_station, open_store
from station.recovery import VerifyReport, reconcile
from station.run_control import JobControl, Outcome, RunContext, StepTiming
from station.runner import SweepRun
from station.store import (
    ACTIVE_STATES,
    InvalidTransition,
    JobRecord,
    JobState,
    JobStore,
    StepRecord,
    StoreError,
    StoreUnavailable,
    Transition,
)
from station.supervisor import Supervisor, Unrecorded, storage_problem, white_problem
from station.sweep import RequestInvalid, SweepPlan, SweepRequest, plan_sweep

FINAL_STATES = frozenset(
    {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
)
"""States in which a job is not (or no longer) being worked on."""


@dataclass
class _Active:
    job_id: int
    control: JobControl
    progress: LiveProgress


class Orchestrator:
    """The station (see the module docstring).

    Args:
        config: the station configuration (``storage`` gives the database and data dir).
        devices_factory: opens the devices (default:
            ``station.devices.open_devices(config, emulator_speedup=...)``).
        store: a job store (default: ``config.storage.database``).
        analysis_workers: analysis processes (None: one per core, at most 4; 0: no
            analysis pool -- jobs can only acquire, ``calibrate`` is ignored).
        emulator_speedup: emulated stages move this many times faster (simulation).
        run_queued: run jobs found queued in the database at start-up (the CLI
            passes False: it runs only what it submits).
        open_devices_at_start: open the devices as soon as the worker starts
            (else at the first job).
    """

    def __init__(
        self,
        config: StationConfig,
        *,
        devices_factory: Callable[[], Any] | None = None,
        store: JobStore | None = None,
        analysis_workers: int | None = None,
        emulator_speedup: float = 1.0,
        run_queued: bool = True,
        open_devices_at_start: bool = True,
    ) -> None:
        self.config = config
        self.data_dir = Path(config.storage.data_dir)
        self._db_path = config.storage.database_path or self.data_dir
        self._archives = ArchiveReader(config.storage.cache_dir, config.storage.s3)
        self._uploader: Any = None
        self._store = store
        self._own_store = store is None
        if devices_factory is None:

            def devices_factory() -> Any:
                from station.devices import open_devices

                return open_devices(config, emulator_speedup=emulator_speedup)

        self._hardware = DeviceHolder(devices_factory)
        self._pool = AnalysisPool(analysis_workers) if analysis_workers != 0 else None
        self._run_queued = run_queued
        self._open_at_start = open_devices_at_start
        self.hub = EventHub()
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._queue: collections.deque[int] = collections.deque()
        self._active: _Active | None = None
        self._progress_lock = threading.Lock()
        self._timings: dict[int, list[StepTiming]] = {}
        self._jobs = JobRecordCache()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._ownership: Ownership | None = None
        self._held_for_ownership = False  # queued jobs held while the ownership is lost
        self._pp_cache: dict[str, tuple[float, float]] = {}
        #: Start-up verification of the jobs found running or paused (job id -> report).
        self.recovery_reports: dict[int, VerifyReport] = {}
        #: Final states the store refused to record (job id -> state and reason).
        self._unrecorded: dict[int, Unrecorded] = {}
        self.supervisor = Supervisor()

    # ------------------------------------------------------------------ lifecycle

    @property
    def store(self) -> JobStore:
        """The job store (opened by :meth:`start`)."""
        if self._store is None:
            raise RuntimeError("the orchestrator is not started")
        return self._store

    def start(self) -> Orchestrator:
        """Lock the database, recover interrupted jobs, start the hardware worker."""
        if self._thread is not None:
            return self
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._ownership = claim_station(self.config)
        try:
            if self._store is None:
                self._store = open_store(self.config)
            self._recover()
            if self._run_queued:
                mine = self._store.own_station
                for job in self._store.list_jobs(states={JobState.QUEUED}, station=mine):
                    self._queue.append(job.id)
            self._uploader = self._start_uploader()
        except BaseException:
            if self._own_store and self._store is not None:
                self._store.close()
                self._store = None
            self._release_lock()
            raise
        self._thread = threading.Thread(target=self._worker, name="hardware-worker", daemon=True)
        self._thread.start()
        return self

    def stop_jobs(self, timeout_s: float = 30.0) -> bool:
        """Begin a shut-down: refuse new jobs, stop the active job at its next step
        boundary (``interrupted``, resumable) and wait up to ``timeout_s`` for it to
        reach that state (its ``state`` event is published). True if no job is active."""
        with self._lock:
            self._stopping = True
            active = self._active
            self._changed.notify_all()
        if active is not None:
            active.control.request_shutdown()
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while self._active is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._changed.wait(min(left, 0.5))
        return True

    @property
    def stopping(self) -> bool:
        """A shut-down has begun (new jobs are refused)."""
        return self._stopping

    def close(self, timeout_s: float = 120.0) -> None:
        """Stop: the active job stops at its next step boundary (``interrupted``),
        the devices are closed, the analysis processes stopped (idempotent)."""
        self.stop_jobs(0.0)
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self._flush_unrecorded()
        if self._pool is not None:
            self._pool.close()
        self._hardware.close()
        if self._uploader is not None:
            self._uploader.stop()
            self._uploader = None
        if self._own_store and self._store is not None:
            self._store.close()
        self._release_lock()

    def __enter__(self) -> Orchestrator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _release_lock(self) -> None:
        ownership, self._ownership = self._ownership, None
        if ownership is not None:
            ownership.release()

    def _start_uploader(self) -> Any:
        """The archive uploader when ``[storage] archive_url`` is set (the object store
        must answer now: :class:`station.objectstore.ObjectStoreUnavailable` otherwise)."""
        storage = self.config.storage
        if storage.archive_url is None:
            return None
        from station.archive_sync import ArchiveUploader
        from station.objectstore import ObjectStore

        objects = ObjectStore(storage.archive_url, storage.s3)
        objects.check()
        return ArchiveUploader(
            self.store,
            objects,
            self.data_dir,
            keep_local=storage.keep_local_archives,
            retry_s=storage.s3.upload_retry_s,
        ).start()

    @property
    def uploader(self) -> Any:
        """The archive uploader (None without object storage)."""
        return self._uploader

    def _own(self, job: JobRecord) -> None:
        """Raise :class:`station.ownership.ForeignJob` for another station's job."""
        if not self.store.owns(job):
            raise ForeignJob(job.id, job.station_id, self.store.station_id, job.state)

    def _recover(self) -> None:
        store = self.store
        for job in store.list_jobs(states=set(ACTIVE_STATES), station=store.own_station):
            try:
                report = reconcile(store, job.id, Path(job.archive_dir))
                self.recovery_reports[job.id] = report
                summary = report.summary(job.frames_total)
            except Exception as exc:  # noqa: BLE001 - the job must still become interrupted
                summary = f"its archive could not be verified: {exc}"
            reason = (
                f"the station process ended while the job was {job.state.value} "
                f"(found at start-up); {summary}"
            )
            self._store_transition(job.id, JobState.INTERRUPTED, reason, last_error=reason)

    # ------------------------------------------------------------------ submit / control

    def wait_ready(self, timeout_s: float = 60.0) -> bool:
        """Wait until the first attempt to open the devices has ended (True) or ``timeout_s``."""
        return self._hardware.tried.wait(timeout_s)

    def validate(self, request: SweepRequest | Mapping[str, Any] | None) -> SweepPlan:
        """Check a request without submitting it (raises :class:`station.sweep.RequestInvalid`).

        The rail travel and the camera's exposure range are checked once the
        devices have been opened (this waits up to 10 s for the first opening);
        otherwise against the configuration, and again when the job starts.
        """
        if self._open_at_start and self._thread is not None:
            self._hardware.tried.wait(10.0)
        return plan_sweep(
            dict(request) if isinstance(request, Mapping) else request,
            self.config,
            rail_limits_mm=self._hardware.rail_limits_mm,
            exposure_limits_us=self._hardware.exposure_limits_us,
        )

    def submit(
        self,
        request: SweepRequest | Mapping[str, Any] | None = None,
        *,
        idempotency_key: str | None = None,
    ) -> JobStatus:
        """Validate and queue a sweep; returns the (new or, for a repeated
        ``idempotency_key`` with the same request, existing) job.

        Raises :class:`station.sweep.RequestInvalid` (422) or
        :class:`station.store.IdempotencyConflict` (409).
        """
        plan = self.validate(request)
        if plan.white_from_job is not None:
            source = self.store.get_job(plan.white_from_job)  # JobNotFound if unknown
            problem = white_problem(source)
            if problem is not None:
                raise RequestInvalid([("white_from_job", problem)])
        self.check_storage()
        with self._lock:
            if self._stopping:
                raise RuntimeError("the station is shutting down")
            job, created = self.store.create_job(
                plan.to_dict(),
                archive_root=self.data_dir,
                frames_total=plan.frames,
                idempotency_key=idempotency_key,
                camera_serial=self._hardware.camera_serial,
            )
            self._jobs.put(job)
            if created:
                # published under the lock, so that no worker's "running" can overtake it
                self._publish_state(job, None, "submitted")
                self._queue.append(job.id)
                self._changed.notify_all()
        return self.status(job.id)

    def pause(self, job_id: int, reason: str = "paused by the operator") -> JobStatus:
        """Ask the running job to pause at the next step boundary (409 unless running)."""
        with self._lock:
            job = self._record(job_id)
            self._own(job)
            active = self._active if self._active and self._active.job_id == job_id else None
            if job.state is not JobState.RUNNING or active is None:
                if job.state is JobState.PAUSED:
                    return self.status(job_id)
                raise InvalidTransition(job_id, job.state, JobState.PAUSED, "pause")
            active.control.request_pause(reason)
            with self._progress_lock:
                active.progress.pause_requested = True
        return self.status(job_id)

    def resume(self, job_id: int, reason: str = "resumed by the operator") -> JobStatus:
        """Resume a paused job, or re-queue an interrupted or failed one (409 otherwise).

        Raises :class:`station.store.StorageFull` (507) when the disk of the database
        or the archives is full, :class:`station.store.StoreUnavailable` (503) when
        the database cannot be written."""
        self._flush_unrecorded()
        with self._lock:
            job = self._record(job_id)
            self._own(job)
            if job_id in self._unrecorded:
                raise self._unrecorded[job_id].error
            active = self._active if self._active and self._active.job_id == job_id else None
            if active is not None and job.state in ACTIVE_STATES:
                active.control.request_resume(reason)
                with self._progress_lock:
                    active.progress.pause_requested = False
                return self.status(job_id)
            if job.state in (JobState.INTERRUPTED, JobState.FAILED):
                if self._stopping:
                    raise RuntimeError("the station is shutting down")
                self.check_storage()
                requeued = self._store_transition(
                    job_id, JobState.QUEUED, f"{reason}: queued again"
                )
                self._publish_state(requeued, job.state, f"{reason}: queued again")
                self._queue.append(job_id)
                self._changed.notify_all()
            else:
                raise InvalidTransition(job_id, job.state, JobState.RUNNING, "resume")
        return self.status(job_id)

    def cancel(self, job_id: int, reason: str = "cancelled by the operator") -> JobStatus:
        """Cancel a job: queued or interrupted at once, running or paused at the next
        step boundary (every captured frame is kept). 409 for a finished job."""
        self._flush_unrecorded()
        with self._lock:
            job = self._record(job_id)
            self._own(job)
            if job_id in self._unrecorded:
                raise self._unrecorded[job_id].error
            active = self._active if self._active and self._active.job_id == job_id else None
            if active is not None and job.state in ACTIVE_STATES:
                active.control.request_cancel(reason)
                with self._progress_lock:
                    active.progress.cancel_requested = True
                return self.status(job_id)
            if job.state not in (JobState.QUEUED, JobState.INTERRUPTED):
                raise InvalidTransition(job_id, job.state, JobState.CANCELLED, "cancel")
            cancelled = self._store_transition(job_id, JobState.CANCELLED, reason)
            if job_id in self._queue:
                self._queue.remove(job_id)
            self._publish_state(cancelled, job.state, reason)
            self._changed.notify_all()
        return self.status(job_id)

    # ------------------------------------------------------------------ queries

    def status(self, job_id: int) -> JobStatus:
        """The job's state and progress (:class:`station.store.JobNotFound` if unknown).

        Polled from the HTTP server's event loop: it reads memory only (the job's
        row from :class:`station.job_cache.JobRecordCache`, the active job's live
        progress; the store only on a cache miss) and takes no lock that the
        worker holds while it stores a result.
        """
        job = self._record(job_id, cached=True)
        # one atomic read of the reference, no lock (see above)
        active = self._active
        if active is not None and active.job_id != job_id:
            active = None
        if active is None or job.state not in ACTIVE_STATES:
            steps = self._jobs.step_count(job, lambda: self.store.step_count(job_id))
            return status_of(job, steps)
        with self._progress_lock:
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
        records = self.store.list_jobs(states=set(states) if states else None)
        return [self.status(job.id) for job in records]

    def record(self, job_id: int) -> JobRecord:
        """The job's stored row, with its result (or a failed calibration's partial one)."""
        return self._record(job_id, with_result=True)

    def transitions(self, job_id: int) -> list[Transition]:
        """Every state change of the job with its time and reason."""
        self.store.get_job(job_id)
        return self.store.transitions(job_id)

    def steps(self, job_id: int) -> list[StepRecord]:
        """The job's recorded steps in index order."""
        self.store.get_job(job_id)
        return self.store.steps(job_id)

    def result(self, job_id: int) -> dict[str, Any]:
        """The calibration result (JSON object) of a succeeded job (:func:`station.job_records.result_of`:
        :class:`ResultNotReady` while it runs or when it ended without one)."""
        return result_of(self._record(job_id, with_result=True), self.store)

    def archive_dir(self, job_id: int) -> Path:
        """The job's ``lfcal-sweep/1`` directory, local or fetched from object storage."""
        return archive_dir_of(self.store, self._archives, job_id)

    def frame_path(self, job_id: int, index: int) -> Path:
        """The file of a recorded frame (:class:`FrameNotFound` otherwise)."""
        return frame_path_of(self.store, self._archives, job_id, index)

    def read_frame(self, job_id: int, index: int) -> Any:
        """A recorded frame as counts (:func:`station.job_records.read_frame_of`)."""
        return read_frame_of(self.store, self._archives, job_id, index)

    def step_timings(self, job_id: int) -> list[StepTiming]:
        """Hardware-thread timings of the steps this process ran for the job."""
        with self._lock:
            return list(self._timings.get(job_id, []))

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
            self.store,
            self._record(job_id),
            after,
            reference_gap_mm=self.config.board.reference_gap_mm,
        )

    def wait_for(self, job_id: int, states: Iterable[JobState], timeout_s: float) -> JobStatus:
        """Block until the job is in one of ``states``; ``TimeoutError`` after ``timeout_s``."""
        wanted = set(states)
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                job = self._record(job_id)
                if job.state in wanted:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"job {job_id} is still {job.state.value} after {timeout_s:g} s "
                        f"(waiting for {', '.join(sorted(s.value for s in wanted))})"
                    )
                self._changed.wait(min(left, 1.0))
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

    # ------------------------------------------------------------------ devices

    @property
    def devices(self) -> Any | None:
        """The open ``StationDevices`` (None when not open). Use only while no job runs."""
        return self._hardware.devices

    def devices_info(self) -> dict[str, Any]:
        """Connection, identity, position and homed state of every device (JSON-ready).

        While a job runs the devices belong to the hardware worker: the last
        description is returned with ``busy: true`` and the live rail position.
        """
        idle = self._hardware.describe_if_idle()
        if idle is not None:
            return idle
        with self._lock:
            active = self._active
        out = self._hardware.describe_busy()
        if active is not None:
            with self._progress_lock:
                out["active_job"] = active.job_id
                out["rail_mm"] = active.progress.rail_mm
        return out

    # ------------------------------------------------------------------ the worker

    def _publish_state(self, job: JobRecord, previous: JobState | None, reason: str) -> None:
        """Announce the job's new state (``job`` as the store returned it from the
        transition); callers hold ``self._lock``, so events keep the store's order."""
        self.hub.publish(
            JobEvent(
                job.id,
                "state",
                None,
                {
                    "state": job.state.value,
                    "from": None if previous is None else previous.value,
                    "reason": reason,
                    "last_error": job.last_error,
                },
            )
        )

    def _transition(
        self,
        job_id: int,
        state: JobState,
        reason: str,
        **kwargs: Any,
    ) -> JobRecord:
        with self._lock:
            before = self.store.get_job(job_id).state
            job = self._store_transition(job_id, state, reason, **kwargs)
            # state events leave in the order the store records the transitions
            self._publish_state(job, before, reason)
            self._changed.notify_all()
        return job

    def _store_transition(
        self, job_id: int, state: JobState, reason: str, **kwargs: Any
    ) -> JobRecord:
        """``store.transition`` (every change of a job row goes through here or
        ``submit``), keeping :attr:`_jobs` up to date before the change is announced."""
        try:
            job = self.store.transition(job_id, state, reason, **kwargs)
        except InvalidTransition:
            raise  # nothing changed
        except BaseException:
            self._jobs.forget(job_id)  # stored or not: read it again
            raise
        self._jobs.put(job)
        return job

    def _run_transition(self, job_id: int, state: JobState, reason: str) -> None:
        self._transition(job_id, state, reason)

    # ------------------------------------------------------------------ supervision

    def _record(self, job_id: int, *, with_result: bool = False, cached: bool = False) -> JobRecord:
        """The job as clients must see it: the store's row, unless its final state
        could not be stored (then that state, from memory). ``cached``: the row
        from :attr:`_jobs` (without the result), read from the store on a miss."""
        if cached and not with_result:
            # another station's jobs (a shared PostgreSQL database) change behind our back
            job = self._jobs.record(job_id, lambda: self.store.get_job(job_id), self.store.owns)
        else:
            job = self.store.get_job(job_id, with_result=with_result)
        pending = self._unrecorded.get(job_id)
        if pending is None:
            return job
        return dataclasses.replace(
            job, state=pending.state, last_error=pending.reason, updated_at=pending.at
        )

    def _end_unrecorded(self, job_id: int, state: JobState, reason: str, error: Exception) -> None:
        """The store refused the job's final state: keep it in memory (and say so)."""
        text = (
            f"{reason}; the job store cannot record this ({error}): the job is interrupted "
            "(resumable once the store can be written again)"
        )
        with self._lock:
            entry = Unrecorded(JobState.INTERRUPTED, text, time.time(), error)
            self._unrecorded[job_id] = entry
            self.hub.publish(
                JobEvent(
                    job_id,
                    "state",
                    None,
                    {
                        "state": entry.state.value,
                        "from": state.value if state in ACTIVE_STATES else "running",
                        "reason": text,
                        "last_error": text,
                        "recorded": False,
                    },
                )
            )
            self._changed.notify_all()
        self.supervisor.note("worker", f"job {job_id}: {text}")

    def _flush_unrecorded(self) -> bool:
        """Store the final states the store refused earlier; True when none is left."""
        with self._lock:
            pending = dict(self._unrecorded)
        if not pending or self._store is None:
            return True
        for job_id, entry in pending.items():
            try:
                job = self.store.get_job(job_id)
                if job.state in ACTIVE_STATES:
                    self._store_transition(
                        job_id, entry.state, entry.reason, last_error=entry.reason
                    )
            except StoreUnavailable:
                return False
            except (StoreError, KeyError):
                pass  # the job is gone or no longer active: nothing left to record
            with self._lock:
                self._unrecorded.pop(job_id, None)
                self._changed.notify_all()
        return True

    def check_storage(self) -> None:
        """Raise :class:`station.store.StorageFull` when the disk holding the database
        or the archives has less free space than one frame needs."""
        error = storage_problem(self.config, self._db_path, self.data_dir)
        if error is not None:
            raise error

    def health(self) -> dict[str, Any]:
        """What is down, and whether the station can run jobs (JSON-ready; see
        :meth:`station.supervisor.Supervisor.health`)."""
        return self.supervisor.health(self)

    @property
    def db_path(self) -> Path:
        """The job database file (PostgreSQL: the data directory, for the disk check)."""
        return self._db_path

    @property
    def analysis_pool(self) -> AnalysisPool | None:
        """The analysis worker processes (None: no analysis)."""
        return self._pool

    @property
    def ownership_problem(self) -> str | None:
        """Why this station no longer holds its ownership of the job database (a shared
        PostgreSQL database restarted and another process took it); None while held."""
        problem = getattr(self._ownership, "problem", None)
        return None if problem is None else str(problem)

    @property
    def worker_alive(self) -> bool:
        """The hardware worker thread is running."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def unrecorded_jobs(self) -> dict[int, str]:
        """Jobs whose final state the store refused (job id -> reason)."""
        with self._lock:
            return {k: v.reason for k, v in self._unrecorded.items()}

    @property
    def active_job(self) -> int | None:
        """The job the hardware worker holds, or None."""
        active = self._active
        return None if active is None else active.job_id

    # ------------------------------------------------------------------ the worker

    def _next_job(self) -> JobRecord | None:
        """Wait for the next queued job and mark it running (under the lock).

        A job the store cannot mark running stays at the head of the queue (retried
        every second), as does every queued job while the station has lost its
        ownership of a shared job database; one that cannot be started for another
        reason fails.
        """
        with self._changed:
            while True:
                if self._stopping:
                    return None
                retry = bool(self._unrecorded)
                lost = self.ownership_problem
                if self._queue and lost is not None:
                    # another process may hold this station now: start nothing until it is back
                    retry = True
                    if not self._held_for_ownership:
                        self._held_for_ownership = True
                        self.supervisor.note(
                            "worker", f"queued jobs wait until the ownership is back: {lost}"
                        )
                elif lost is None:
                    self._held_for_ownership = False
                while self._queue and lost is None:
                    job_id = self._queue[0]
                    try:
                        job = self.store.get_job(job_id)
                        if job.state is not JobState.QUEUED:
                            self._queue.popleft()
                            continue
                        steps = self.store.step_count(job_id)
                        reason = (
                            "started"
                            if steps == 0 and job.last_error is None
                            else f"resumed with {steps} of {job.frames_total} frames recorded"
                        )
                        job = self._store_transition(
                            job_id, JobState.RUNNING, reason, clear_error=True
                        )
                    except StoreUnavailable as exc:
                        self.supervisor.note("worker", f"cannot start job {job_id}: {exc}")
                        retry = True
                        break
                    except Exception as exc:  # noqa: BLE001 - the job fails, the queue goes on
                        self._queue.popleft()
                        self._fail_unstartable(job_id, exc)
                        continue
                    self._queue.popleft()
                    self._active = _Active(
                        job_id,
                        JobControl(),
                        LiveProgress(job_id, frames_total=job.frames_total, frames_done=steps),
                    )
                    self._changed.notify_all()
                    self._publish_state(job, JobState.QUEUED, reason)
                    return job
                self._changed.wait(1.0 if retry else None)
                if retry:
                    self._flush_unrecorded()

    def _fail_unstartable(self, job_id: int, exc: BaseException) -> None:
        reason = f"the job could not be started: internal error: {type(exc).__name__}: {exc}"
        try:
            self._transition(job_id, JobState.FAILED, reason, last_error=reason)
        except InvalidTransition:
            try:
                self._transition(job_id, JobState.CANCELLED, reason)
            except Exception:  # noqa: BLE001 - nothing more to record
                pass
        except Exception:  # noqa: BLE001 - the store refuses: nothing more to record
            pass

    def _worker(self) -> None:
        """The hardware worker: supervised, it only returns when the station stops."""
        if self._open_at_start:
            with self._hardware.hw_lock:
                try:
                    self._hardware.ensure()
                except Exception:  # noqa: BLE001 - reported by devices_info and the first job
                    pass
        self._hardware.tried.set()
        while True:
            try:
                if not self._serve_one():
                    return
            except Exception as exc:  # noqa: BLE001 - the supervisor: never die, say why
                self.supervisor.note("worker", f"recovered from {type(exc).__name__}: {exc}")
                with self._changed:
                    self._changed.wait(1.0)

    def _serve_one(self) -> bool:
        """Run the next job to a final state; False when the station stops."""
        self._flush_unrecorded()
        job = self._next_job()
        if job is None:
            return False
        try:
            with self._hardware.hw_lock:
                outcome = self._run(job)
        except Exception as exc:  # noqa: BLE001 - SweepRun.execute catches; this is a bug
            message = f"internal error: {type(exc).__name__}: {exc}"
            outcome = Outcome(JobState.FAILED, message, last_error=message)
        self._finish(job.id, outcome)
        if outcome.devices_broken:
            with self._hardware.hw_lock:  # learn at once whether the devices can be reopened
                try:
                    self._hardware.ensure()
                except Exception:  # noqa: BLE001 - reported by devices_info
                    pass
        return True

    def _run(self, job: JobRecord) -> Outcome:
        assert self._active is not None
        active = self._active
        try:
            devices = self._hardware.ensure()
        except Exception as exc:  # noqa: BLE001
            msg = f"the devices cannot be opened: {exc}"
            return Outcome(JobState.FAILED, msg, last_error=msg)
        serial = self._hardware.camera_serial
        if serial and serial != job.camera_serial:
            try:
                self.store.set_camera_serial(job.id, serial)
            finally:
                self._jobs.forget(job.id)  # the row changed: read it again
        timings: list[StepTiming] = []
        with self._lock:
            self._timings[job.id] = timings
            while len(self._timings) > 20:
                self._timings.pop(next(iter(self._timings)))
        ctx = RunContext(
            config=self.config,
            store=self.store,
            pool=self._pool,
            publish=self.hub.publish,
            transition=self._run_transition,
            progress=active.progress,
            progress_lock=self._progress_lock,
            control=active.control,
            timings=timings,
            principal_point_cache=self._pp_cache,
            row_changed=self._jobs.forget,
            ownership_problem=lambda: self.ownership_problem,
        )
        return SweepRun(job, devices, ctx).execute()

    def _finish(self, job_id: int, outcome: Outcome) -> None:
        """Store the run's final state; if the store refuses, keep it in memory."""
        if outcome.devices_broken:
            self._hardware.close()
        kwargs: dict[str, Any] = {}
        if outcome.last_error is not None:
            kwargs["last_error"] = outcome.last_error
        if outcome.result is not None:
            kwargs["result"] = outcome.result
        try:
            self._transition(job_id, outcome.state, outcome.reason, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the job must not stay running
            state = JobState.RUNNING
            try:
                state = self.store.get_job(job_id).state
            except Exception:  # noqa: BLE001
                pass
            if state in ACTIVE_STATES:
                why = outcome.last_error or outcome.reason
                self._end_unrecorded(job_id, state, why, exc)
        finally:
            with self._lock:
                self._active = None
                self._changed.notify_all()


__all__ = [
    "FINAL_STATES",
    "FrameNotFound",
    "JobStatus",
    "Orchestrator",
    "ResultNotReady",
    "StationBusy",
]
