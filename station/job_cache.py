"""The job rows that status polling reads, kept in memory.

``GET /api/v1/jobs/{id}`` is what operators' pages and scripts poll (50 pollers
at 10 Hz in ``bench/bench_web.py``), and it is answered on the HTTP server's
event loop. Reading the job's row from SQLite there costs little CPU, but every
query lets go of the GIL and has to take it back; on a busy 2-core machine the
thread that took it meanwhile may be waiting for a CPU, and the event loop waits
with it (5-30 ms per read were measured during a sweep). :class:`JobRecordCache`
keeps the rows (without their results) and, for jobs the hardware worker does
not hold, their step counts, so a status read is a dictionary lookup.

It is correct because a station's process is the only writer of its jobs' rows
(one process per station: a file lock on SQLite, an advisory lock per station on
a shared PostgreSQL database, :mod:`station.ownership`), and every write of such a
row in that process is followed, before it is announced, by
:meth:`JobRecordCache.put` with the row the store returned (submissions and every
state change, :class:`station.orchestrator.Orchestrator`) or by
:meth:`JobRecordCache.forget` (a recorded step moves ``updated_at``: the run calls
it before the step's event; the camera serial; a write whose outcome is unknown
because the store raised). Other stations' jobs on a shared database are never
kept. A read that raced with a write is not cached: every write advances a
generation counter, and a row read from the store is kept only if no write
happened while it was being read.

Step counts are cached only for jobs that are not ``running``/``paused``: a step is
recorded only by the writer thread of the running job, which is closed before the
job leaves that state, and a job that runs again goes through a transition first
(which drops the cached count).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable

from station.store import ACTIVE_STATES, JobRecord

MAX_CACHED_JOBS = 256
"""Jobs kept; the least recently stored are dropped first (read again when asked)."""


class JobRecordCache:
    """Job rows (without results) and step counts of finished or queued jobs
    (see the module docstring). Thread-safe.

    Args:
        max_jobs: most jobs kept.
    """

    def __init__(self, max_jobs: int = MAX_CACHED_JOBS) -> None:
        self._max = max(1, int(max_jobs))
        self._lock = threading.Lock()
        self._records: OrderedDict[int, JobRecord] = OrderedDict()
        self._steps: dict[int, int] = {}
        self._generation = 0

    def record(
        self,
        job_id: int,
        read: Callable[[], JobRecord],
        keep: Callable[[JobRecord], bool] | None = None,
    ) -> JobRecord:
        """The job's row: from memory, else ``read()``, kept unless a write raced it or
        ``keep(row)`` is false (another station's job)."""
        job = self._records.get(job_id)
        if job is not None:
            return job
        generation = self._generation
        job = read()
        if keep is not None and not keep(job):
            return job
        with self._lock:
            if self._generation == generation:
                self._keep(job)
        return job

    def step_count(self, job: JobRecord, read: Callable[[], int]) -> int:
        """Recorded steps of ``job`` (a row this cache returned): from memory when the
        job is not ``running``/``paused``, else (and on a miss) ``read()``."""
        if job.state in ACTIVE_STATES:
            return read()
        count = self._steps.get(job.id)
        if count is not None:
            return count
        generation = self._generation
        count = read()
        with self._lock:
            if self._generation == generation and self._records.get(job.id) is job:
                self._steps[job.id] = count
        return count

    def put(self, job: JobRecord) -> None:
        """The row the store returned from a write of this job (before it is announced)."""
        with self._lock:
            self._generation += 1
            self._steps.pop(job.id, None)
            self._keep(job)

    def forget(self, job_id: int) -> None:
        """Drop the job (a write whose outcome is unknown); the next read goes to the store."""
        with self._lock:
            self._generation += 1
            self._records.pop(job_id, None)
            self._steps.pop(job_id, None)

    def clear(self) -> None:
        """Drop every job."""
        with self._lock:
            self._generation += 1
            self._records.clear()
            self._steps.clear()

    def _keep(self, job: JobRecord) -> None:
        self._records[job.id] = job
        self._records.move_to_end(job.id)
        while len(self._records) > self._max:
            old, _ = self._records.popitem(last=False)
            self._steps.pop(old, None)


__all__ = ["MAX_CACHED_JOBS", "JobRecordCache"]
