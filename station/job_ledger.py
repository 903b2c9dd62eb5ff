"""What clients are shown of every job's state, kept in step with the store.

:class:`JobLedger` is the one place a job's row changes state in a station's
process (:meth:`JobLedger.transition`; submissions put their new row through
:meth:`JobLedger.rows` themselves) and the one place a client reads it
(:meth:`JobLedger.record`). It holds:

- the station's lock and its condition (``lock``, ``changed``): submissions,
  control requests, the hardware worker's queue and every state change take the
  lock, so ``state`` events leave in the order the store records the
  transitions, and every change is followed by ``changed.notify_all()``;
- the rows that status polling reads (:class:`station.job_cache.JobRecordCache`),
  updated before a change is announced;
- the final states the store refused to record (:class:`station.supervisor.Unrecorded`):
  shown to clients instead of the stored row (``interrupted`` with the store's
  error), written by :meth:`JobLedger.flush_unrecorded` once the store accepts
  writes again (the next start's recovery finds them otherwise).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from station.events import EventHub, JobEvent
from station.job_cache import JobRecordCache
from station.store import (
    ACTIVE_STATES,
    InvalidTransition,
    JobRecord,
    JobState,
    JobStore,
    StoreError,
    StoreUnavailable,
)
from station.supervisor import Supervisor, Unrecorded


class JobLedger:
    """The jobs' states as clients see them (see the module docstring).

    Args:
        store: returns the job store, or None before it is opened / after it is closed.
        hub: where ``state`` events are published.
        supervisor: told when a final state cannot be recorded.
    """

    def __init__(
        self,
        store: Callable[[], JobStore | None],
        hub: EventHub,
        supervisor: Supervisor,
    ) -> None:
        self._store_of = store
        self.hub = hub
        self._supervisor = supervisor
        self.lock = threading.RLock()
        self.changed = threading.Condition(self.lock)
        #: The job rows status polling reads (without results).
        self.rows = JobRecordCache()
        self._unrecorded: dict[int, Unrecorded] = {}

    @property
    def store(self) -> JobStore:
        store = self._store_of()
        if store is None:
            raise RuntimeError("the orchestrator is not started")
        return store

    # ------------------------------------------------------------------ reading

    def record(self, job_id: int, *, with_result: bool = False, cached: bool = False) -> JobRecord:
        """The job as clients must see it: the store's row, unless its final state
        could not be stored (then that state, from memory). ``cached``: the row
        from :attr:`rows` (without the result), read from the store on a miss."""
        store = self.store
        if cached and not with_result:
            # another station's jobs (a shared PostgreSQL database) change behind our back
            job = self.rows.record(job_id, lambda: store.get_job(job_id), store.owns)
        else:
            job = store.get_job(job_id, with_result=with_result)
        pending = self._unrecorded.get(job_id)
        if pending is None:
            return job
        return dataclasses.replace(
            job, state=pending.state, last_error=pending.reason, updated_at=pending.at
        )

    def wait_for(self, job_id: int, states: Iterable[JobState], timeout_s: float) -> JobRecord:
        """Block until the job is in one of ``states``; ``TimeoutError`` after ``timeout_s``."""
        wanted = set(states)
        deadline = time.monotonic() + timeout_s
        with self.changed:
            while True:
                job = self.record(job_id)
                if job.state in wanted:
                    return job
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"job {job_id} is still {job.state.value} after {timeout_s:g} s "
                        f"(waiting for {', '.join(sorted(s.value for s in wanted))})"
                    )
                self.changed.wait(min(left, 1.0))

    # ------------------------------------------------------------------ changing

    def publish_state(self, job: JobRecord, previous: JobState | None, reason: str) -> None:
        """Announce the job's new state (``job`` as the store returned it from the
        transition); callers hold :attr:`lock`, so events keep the store's order."""
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

    def transition(self, job_id: int, state: JobState, reason: str, **kwargs: Any) -> JobRecord:
        """Store the change, announce it (``state`` event) and wake the waiters."""
        with self.lock:
            before = self.store.get_job(job_id).state
            job = self.store_transition(job_id, state, reason, **kwargs)
            # state events leave in the order the store records the transitions
            self.publish_state(job, before, reason)
            self.changed.notify_all()
        return job

    def store_transition(
        self, job_id: int, state: JobState, reason: str, **kwargs: Any
    ) -> JobRecord:
        """``store.transition`` (every change of a job row goes through here or a
        submission), keeping :attr:`rows` up to date before the change is announced."""
        try:
            job = self.store.transition(job_id, state, reason, **kwargs)
        except InvalidTransition:
            raise  # nothing changed
        except BaseException:
            self.rows.forget(job_id)  # stored or not: read it again
            raise
        self.rows.put(job)
        return job

    # ------------------------------------------------------------------ refused final states

    def end_unrecorded(self, job_id: int, state: JobState, reason: str, error: Exception) -> None:
        """The store refused the job's final state: keep it in memory (and say so)."""
        text = (
            f"{reason}; the job store cannot record this ({error}): the job is interrupted "
            "(resumable once the store can be written again)"
        )
        with self.lock:
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
            self.changed.notify_all()
        self._supervisor.note("worker", f"job {job_id}: {text}")

    def flush_unrecorded(self) -> bool:
        """Store the final states the store refused earlier; True when none is left."""
        with self.lock:
            pending = dict(self._unrecorded)
        if not pending or self._store_of() is None:
            return True
        for job_id, entry in pending.items():
            try:
                job = self.store.get_job(job_id)
                if job.state in ACTIVE_STATES:
                    self.store_transition(
                        job_id, entry.state, entry.reason, last_error=entry.reason
                    )
            except StoreUnavailable:
                return False
            except (StoreError, KeyError):
                pass  # the job is gone or no longer active: nothing left to record
            with self.lock:
                self._unrecorded.pop(job_id, None)
                self.changed.notify_all()
        return True

    def refused_error(self, job_id: int) -> Exception | None:
        """The store's error for a job whose final state is still unrecorded, else None."""
        entry = self._unrecorded.get(job_id)
        return None if entry is None else entry.error

    @property
    def any_unrecorded(self) -> bool:
        """Some final state still waits to be written."""
        return bool(self._unrecorded)

    @property
    def unrecorded_jobs(self) -> dict[int, str]:
        """Jobs whose final state the store refused (job id -> reason)."""
        with self.lock:
            return {k: v.reason for k, v in self._unrecorded.items()}
