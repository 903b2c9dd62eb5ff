"""The station's one hardware worker: the job queue and the thread that runs it.

:class:`HardwareWorker` owns the devices (opens them, runs one job at a time in
submission order with :class:`station.runner.SweepRun`, closes them when a run
broke them) and never dies of an exception (:mod:`station.supervisor`): whatever
escapes a run ends the job in a final state with the reason -- ``failed``, or
``interrupted`` kept in memory when the store cannot record it
(:meth:`station.job_ledger.JobLedger.end_unrecorded`) -- and the worker goes on
serving the queue. A job the store cannot mark ``running`` stays at the head of
the queue (retried every second), as does every queued job while the station has
lost its ownership of a shared job database.

The queue, :attr:`HardwareWorker.active` and :attr:`HardwareWorker.stopping` are
guarded by the ledger's lock (``JobLedger.lock``); the active job's live progress
by :attr:`HardwareWorker.progress_lock`.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from station.analysis import AnalysisPool
from station.config import StationConfig
from station.device_holder import DeviceHolder
from station.events import LiveProgress
from station.job_ledger import JobLedger
from station.run_control import JobControl, Outcome, RunContext, StepTiming
from station.runner import SweepRun
from station.store import ACTIVE_STATES, InvalidTransition, JobRecord, JobState, StoreUnavailable
from station.supervisor import Supervisor

MAX_TIMED_JOBS = 20
"""Jobs whose step timings are kept in memory (the oldest dropped first)."""


@dataclass
class ActiveJob:
    """The job the hardware worker holds: its control requests and live progress."""

    job_id: int
    control: JobControl
    progress: LiveProgress


class HardwareWorker:
    """The job queue and the thread that runs it (see the module docstring).

    Args:
        config: the station configuration.
        ledger: the jobs' states (its lock guards the queue and :attr:`active`).
        hardware: opens, describes and closes the devices.
        pool: the analysis processes (None: acquisition only).
        supervisor: told what the worker recovered from.
        ownership_problem: why the station no longer owns its job database, or None.
        open_at_start: open the devices as soon as the thread starts (else at the first job).
    """

    def __init__(
        self,
        *,
        config: StationConfig,
        ledger: JobLedger,
        hardware: DeviceHolder,
        pool: AnalysisPool | None,
        supervisor: Supervisor,
        ownership_problem: Callable[[], str | None],
        open_at_start: bool,
    ) -> None:
        self._config = config
        self._ledger = ledger
        self._hardware = hardware
        self._pool = pool
        self._supervisor = supervisor
        self._ownership_problem = ownership_problem
        self._open_at_start = open_at_start
        self._queue: collections.deque[int] = collections.deque()
        #: The job being run (None between jobs); read without the lock as one reference.
        self.active: ActiveJob | None = None
        #: Guards the active job's :class:`station.events.LiveProgress`.
        self.progress_lock = threading.Lock()
        #: A shut-down has begun: no job is started any more.
        self.stopping = False
        self._timings: dict[int, list[StepTiming]] = {}
        self._held_for_ownership = False  # queued jobs held while the ownership is lost
        self._pp_cache: dict[str, tuple[float, float]] = {}
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="hardware-worker", daemon=True)
            self._thread.start()

    @property
    def alive(self) -> bool:
        """The thread is running."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def started(self) -> bool:
        return self._thread is not None

    def stop(self, timeout_s: float) -> bool:
        """Start no more jobs, ask the active one to stop at its next step boundary
        (``interrupted``) and wait up to ``timeout_s`` for it. True if none is active."""
        with self._ledger.lock:
            self.stopping = True
            active = self.active
            self._ledger.changed.notify_all()
        if active is not None:
            active.control.request_shutdown()
        deadline = time.monotonic() + timeout_s
        with self._ledger.changed:
            while self.active is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._ledger.changed.wait(min(left, 0.5))
        return True

    def join(self, timeout_s: float) -> None:
        """Wait for the thread to end (after :meth:`stop`)."""
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    # ------------------------------------------------------------------ the queue

    def enqueue(self, job_id: int) -> None:
        """Queue a job (the caller holds the ledger's lock)."""
        self._queue.append(job_id)
        self._ledger.changed.notify_all()

    def discard(self, job_id: int) -> None:
        """Take a queued job off the queue (the caller holds the ledger's lock)."""
        if job_id in self._queue:
            self._queue.remove(job_id)

    def active_for(self, job_id: int) -> ActiveJob | None:
        """The active job if it is ``job_id``, else None."""
        active = self.active  # one atomic read of the reference
        return active if active is not None and active.job_id == job_id else None

    def step_timings(self, job_id: int) -> list[StepTiming]:
        """Hardware-thread timings of the steps this process ran for the job."""
        with self._ledger.lock:
            return list(self._timings.get(job_id, []))

    # ------------------------------------------------------------------ the thread

    def _loop(self) -> None:
        """Supervised: it only returns when the station stops."""
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
                self._supervisor.note("worker", f"recovered from {type(exc).__name__}: {exc}")
                with self._ledger.changed:
                    self._ledger.changed.wait(1.0)

    def _serve_one(self) -> bool:
        """Run the next job to a final state; False when the station stops."""
        self._ledger.flush_unrecorded()
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

    def _ownership_lost(self) -> str | None:
        """Why queued jobs must wait for the ownership (noted once per loss), or None."""
        lost = self._ownership_problem()
        if lost is None:
            self._held_for_ownership = False
        elif self._queue and not self._held_for_ownership:
            self._held_for_ownership = True
            self._supervisor.note("worker", f"queued jobs wait until the ownership is back: {lost}")
        return lost

    def _next_job(self) -> JobRecord | None:
        """Wait for the next queued job and mark it running (under the lock).

        A job the store cannot mark running stays at the head of the queue (retried
        every second), as does every queued job while the station has lost its
        ownership of a shared job database; one that cannot be started for another
        reason fails.
        """
        ledger = self._ledger
        with ledger.changed:
            while True:
                if self.stopping:
                    return None
                lost = self._ownership_lost()
                # another process may hold this station now: start nothing until it is back
                retry = ledger.any_unrecorded or (bool(self._queue) and lost is not None)
                while self._queue and lost is None:
                    job_id = self._queue[0]
                    try:
                        job = ledger.store.get_job(job_id)
                        if job.state is not JobState.QUEUED:
                            self._queue.popleft()
                            continue
                        steps = ledger.store.step_count(job_id)
                        reason = (
                            "started"
                            if steps == 0 and job.last_error is None
                            else f"resumed with {steps} of {job.frames_total} frames recorded"
                        )
                        job = ledger.store_transition(
                            job_id, JobState.RUNNING, reason, clear_error=True
                        )
                    except StoreUnavailable as exc:
                        self._supervisor.note("worker", f"cannot start job {job_id}: {exc}")
                        retry = True
                        break
                    except Exception as exc:  # noqa: BLE001 - the job fails, the queue goes on
                        self._queue.popleft()
                        self._fail_unstartable(job_id, exc)
                        continue
                    self._queue.popleft()
                    self.active = ActiveJob(
                        job_id,
                        JobControl(),
                        LiveProgress(job_id, frames_total=job.frames_total, frames_done=steps),
                    )
                    ledger.changed.notify_all()
                    ledger.publish_state(job, JobState.QUEUED, reason)
                    return job
                ledger.changed.wait(1.0 if retry else None)
                if retry:
                    ledger.flush_unrecorded()

    def _fail_unstartable(self, job_id: int, exc: BaseException) -> None:
        reason = f"the job could not be started: internal error: {type(exc).__name__}: {exc}"
        try:
            self._ledger.transition(job_id, JobState.FAILED, reason, last_error=reason)
        except InvalidTransition:
            try:
                self._ledger.transition(job_id, JobState.CANCELLED, reason)
            except Exception:  # noqa: BLE001 - nothing more to record
                pass
        except Exception:  # noqa: BLE001 - the store refuses: nothing more to record
            pass

    def _run(self, job: JobRecord) -> Outcome:
        active = self.active
        assert active is not None
        try:
            devices = self._hardware.ensure()
        except Exception as exc:  # noqa: BLE001
            msg = f"the devices cannot be opened: {exc}"
            return Outcome(JobState.FAILED, msg, last_error=msg)
        store = self._ledger.store
        serial = self._hardware.camera_serial
        if serial and serial != job.camera_serial:
            try:
                store.set_camera_serial(job.id, serial)
            finally:
                self._ledger.rows.forget(job.id)  # the row changed: read it again
        timings: list[StepTiming] = []
        with self._ledger.lock:
            self._timings[job.id] = timings
            while len(self._timings) > MAX_TIMED_JOBS:
                self._timings.pop(next(iter(self._timings)))
        ctx = RunContext(
            config=self._config,
            store=store,
            pool=self._pool,
            publish=self._ledger.hub.publish,
            transition=self._run_transition,
            progress=active.progress,
            progress_lock=self.progress_lock,
            control=active.control,
            timings=timings,
            principal_point_cache=self._pp_cache,
            row_changed=self._ledger.rows.forget,
            ownership_problem=self._ownership_problem,
        )
        return SweepRun(job, devices, ctx).execute()

    def _run_transition(self, job_id: int, state: JobState, reason: str) -> None:
        self._ledger.transition(job_id, state, reason)

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
            self._ledger.transition(job_id, outcome.state, outcome.reason, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the job must not stay running
            state = JobState.RUNNING
            try:
                state = self._ledger.store.get_job(job_id).state
            except Exception:  # noqa: BLE001
                pass
            if state in ACTIVE_STATES:
                why = outcome.last_error or outcome.reason
                self._ledger.end_unrecorded(job_id, state, why, exc)
        finally:
            with self._ledger.lock:
                self.active = None
                self._ledger.changed.notify_all()
