"""The station orchestrator: the job queue, the one hardware worker, and the API.

:class:`Orchestrator` is what the web layer and ``lfcal sweep`` use::

    station = Orchestrator(load_config("config/simulated.toml")).start()
    job = station.submit({"start_mm": 0, "stop_mm": 99, "step_mm": 1})
    with station.subscribe(job.id) as events:        # step / analysis / state / phase
        ...
    station.wait_for(job.id, {JobState.SUCCEEDED, JobState.FAILED}, timeout_s=600)
    station.result(job.id)                            # the calibration (JSON object)
    station.close()

Threads: **one hardware worker** (:class:`station.hardware_worker.HardwareWorker`)
owns the devices (opens them, runs one job at a time in submission order, closes
them); one archive-writer thread per running
job; the analysis runs in worker processes. Every public method is thread-safe
and returns quickly: status comes from memory for the active job and from the
SQLite store otherwise (:class:`station.job_ledger.JobLedger` keeps what clients
are shown of every job's state in step with the store).

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

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from station.analysis import AnalysisPool
from station.archive_source import ArchiveReader
from station.config import StationConfig
from station.device_holder import DeviceHolder
from station.events import EventHub
from station.hardware_worker import HardwareWorker
from station.job_ledger import JobLedger
from station.job_reads import JobReads
from station.job_records import (
    FrameNotFound,
    JobStatus,
    ResultNotReady,
)
from station.ownership import ForeignJob, Ownership, StationBusy, claim_station, open_store
from station.recovery import VerifyReport, interrupt_orphaned_jobs
from station.store import (
    ACTIVE_STATES,
    InvalidTransition,
    JobRecord,
    JobState,
    JobStore,
)
from station.supervisor import Supervisor, storage_problem, white_problem
from station.sweep import RequestInvalid, SweepPlan, SweepRequest, plan_sweep

FINAL_STATES = frozenset(
    {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
)
"""States in which a job is not (or no longer) being worked on."""


class Orchestrator(JobReads):
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
        self._ownership: Ownership | None = None
        #: Start-up verification of the jobs found running or paused (job id -> report).
        self.recovery_reports: dict[int, VerifyReport] = {}
        self.supervisor = Supervisor()
        self._ledger = JobLedger(lambda: self._store, self.hub, self.supervisor)
        self._lock = self._ledger.lock
        self._worker = HardwareWorker(
            config=config,
            ledger=self._ledger,
            hardware=self._hardware,
            pool=self._pool,
            supervisor=self.supervisor,
            ownership_problem=lambda: self.ownership_problem,
            open_at_start=open_devices_at_start,
        )

    # ------------------------------------------------------------------ lifecycle

    @property
    def store(self) -> JobStore:
        """The job store (opened by :meth:`start`)."""
        if self._store is None:
            raise RuntimeError("the orchestrator is not started")
        return self._store

    def start(self) -> Orchestrator:
        """Lock the database, recover interrupted jobs, start the hardware worker."""
        if self._worker.started:
            return self
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._ownership = claim_station(self.config)
        try:
            if self._store is None:
                self._store = open_store(self.config)
            self.recovery_reports = interrupt_orphaned_jobs(
                self._store, self._ledger.store_transition
            )
            if self._run_queued:
                mine = self._store.own_station
                with self._lock:
                    for job in self._store.list_jobs(states={JobState.QUEUED}, station=mine):
                        self._worker.enqueue(job.id)
            if self.config.storage.archive_url is not None:
                from station.archive_sync import start_uploader

                self._uploader = start_uploader(self._store, self.config.storage, self.data_dir)
        except BaseException:
            if self._own_store and self._store is not None:
                self._store.close()
                self._store = None
            self._release_lock()
            raise
        self._worker.start()
        return self

    def stop_jobs(self, timeout_s: float = 30.0) -> bool:
        """Begin a shut-down: refuse new jobs, stop the active job at its next step
        boundary (``interrupted``, resumable) and wait up to ``timeout_s`` for it to
        reach that state (its ``state`` event is published). True if no job is active."""
        return self._worker.stop(timeout_s)

    @property
    def stopping(self) -> bool:
        """A shut-down has begun (new jobs are refused)."""
        return self._worker.stopping

    def close(self, timeout_s: float = 120.0) -> None:
        """Stop: the active job stops at its next step boundary (``interrupted``),
        the devices are closed, the analysis processes stopped (idempotent)."""
        self.stop_jobs(0.0)
        self._worker.join(timeout_s)
        self._ledger.flush_unrecorded()
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

    @property
    def uploader(self) -> Any:
        """The archive uploader (None without object storage)."""
        return self._uploader

    def _own(self, job: JobRecord) -> None:
        """Raise :class:`station.ownership.ForeignJob` for another station's job."""
        if not self.store.owns(job):
            raise ForeignJob(job.id, job.station_id, self.store.station_id, job.state)

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
        if self._open_at_start and self._worker.started:
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
            if self._worker.stopping:
                raise RuntimeError("the station is shutting down")
            job, created = self.store.create_job(
                plan.to_dict(),
                archive_root=self.data_dir,
                frames_total=plan.frames,
                idempotency_key=idempotency_key,
                camera_serial=self._hardware.camera_serial,
            )
            self._ledger.rows.put(job)
            if created:
                # published under the lock, so that no worker's "running" can overtake it
                self._ledger.publish_state(job, None, "submitted")
                self._worker.enqueue(job.id)
        return self.status(job.id)

    def pause(self, job_id: int, reason: str = "paused by the operator") -> JobStatus:
        """Ask the running job to pause at the next step boundary (409 unless running)."""
        with self._lock:
            job = self._ledger.record(job_id)
            self._own(job)
            active = self._worker.active_for(job_id)
            if job.state is not JobState.RUNNING or active is None:
                if job.state is JobState.PAUSED:
                    return self.status(job_id)
                raise InvalidTransition(job_id, job.state, JobState.PAUSED, "pause")
            active.control.request_pause(reason)
            with self._worker.progress_lock:
                active.progress.pause_requested = True
        return self.status(job_id)

    def resume(self, job_id: int, reason: str = "resumed by the operator") -> JobStatus:
        """Resume a paused job, or re-queue an interrupted or failed one (409 otherwise).

        Raises :class:`station.store.StorageFull` (507) when the disk of the database
        or the archives is full, :class:`station.store.StoreUnavailable` (503) when
        the database cannot be written."""
        self._ledger.flush_unrecorded()
        with self._lock:
            job = self._ledger.record(job_id)
            self._own(job)
            refused = self._ledger.refused_error(job_id)
            if refused is not None:
                raise refused
            active = self._worker.active_for(job_id)
            if active is not None and job.state in ACTIVE_STATES:
                active.control.request_resume(reason)
                with self._worker.progress_lock:
                    active.progress.pause_requested = False
                return self.status(job_id)
            if job.state in (JobState.INTERRUPTED, JobState.FAILED):
                if self._worker.stopping:
                    raise RuntimeError("the station is shutting down")
                self.check_storage()
                requeued = self._ledger.store_transition(
                    job_id, JobState.QUEUED, f"{reason}: queued again"
                )
                self._ledger.publish_state(requeued, job.state, f"{reason}: queued again")
                self._worker.enqueue(job_id)
            else:
                raise InvalidTransition(job_id, job.state, JobState.RUNNING, "resume")
        return self.status(job_id)

    def cancel(self, job_id: int, reason: str = "cancelled by the operator") -> JobStatus:
        """Cancel a job: queued or interrupted at once, running or paused at the next
        step boundary (every captured frame is kept). 409 for a finished job."""
        self._ledger.flush_unrecorded()
        with self._lock:
            job = self._ledger.record(job_id)
            self._own(job)
            refused = self._ledger.refused_error(job_id)
            if refused is not None:
                raise refused
            active = self._worker.active_for(job_id)
            if active is not None and job.state in ACTIVE_STATES:
                active.control.request_cancel(reason)
                with self._worker.progress_lock:
                    active.progress.cancel_requested = True
                return self.status(job_id)
            if job.state not in (JobState.QUEUED, JobState.INTERRUPTED):
                raise InvalidTransition(job_id, job.state, JobState.CANCELLED, "cancel")
            cancelled = self._ledger.store_transition(job_id, JobState.CANCELLED, reason)
            self._worker.discard(job_id)
            self._ledger.publish_state(cancelled, job.state, reason)
            self._ledger.changed.notify_all()
        return self.status(job_id)

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
        active = self._worker.active
        out = self._hardware.describe_busy()
        if active is not None:
            with self._worker.progress_lock:
                out["active_job"] = active.job_id
                out["rail_mm"] = active.progress.rail_mm
        return out

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
        return self._worker.alive

    @property
    def unrecorded_jobs(self) -> dict[int, str]:
        """Jobs whose final state the store refused (job id -> reason)."""
        return self._ledger.unrecorded_jobs

    @property
    def active_job(self) -> int | None:
        """The job the hardware worker holds, or None."""
        active = self._worker.active
        return None if active is None else active.job_id


__all__ = [
    "FINAL_STATES",
    "FrameNotFound",
    "JobStatus",
    "Orchestrator",
    "ResultNotReady",
    "StationBusy",
]
