"""The in-memory job rows behind status polling (:class:`station.job_cache.JobRecordCache`):
kept after one read, replaced by every write, never filled by a read that raced a write."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from station.job_cache import JobRecordCache
from station.store import JobRecord, JobState


def row(job_id: int, state: JobState = JobState.QUEUED, error: str | None = None) -> JobRecord:
    return JobRecord(
        id=job_id,
        state=state,
        request={"start_mm": 0.0},
        created_at=1.0,
        updated_at=2.0,
        result=None,
        last_error=error,
        archive_dir=Path("/data/job"),
        frames_total=10,
    )


class Reads:
    """A stand-in for the store's reads that counts them."""

    def __init__(self, value: JobRecord) -> None:
        self.value = value
        self.count = 0

    def __call__(self) -> JobRecord:
        self.count += 1
        return self.value


def test_a_row_is_read_once_then_served_from_memory() -> None:
    cache = JobRecordCache()
    reads = Reads(row(1))
    assert cache.record(1, reads) == row(1)
    assert cache.record(1, reads) == row(1)
    assert reads.count == 1


def test_a_write_replaces_the_row_before_anyone_reads_it_again() -> None:
    cache = JobRecordCache()
    reads = Reads(row(1))
    cache.record(1, reads)
    cache.put(row(1, JobState.RUNNING))
    assert cache.record(1, reads).state is JobState.RUNNING
    assert reads.count == 1
    cache.forget(1)  # a write whose outcome is unknown: read the store again
    reads.value = row(1, JobState.FAILED, "disk I/O error")
    assert cache.record(1, reads).last_error == "disk I/O error"
    assert reads.count == 2


def test_a_read_that_raced_a_write_is_not_kept() -> None:
    cache = JobRecordCache()
    newer = row(1, JobState.RUNNING)

    def stale_read() -> JobRecord:
        cache.put(newer)  # the worker stores a transition while the old row is read
        return row(1, JobState.QUEUED)

    assert cache.record(1, stale_read).state is JobState.QUEUED  # this caller's read
    # ... but the cache kept the written row, not the stale one
    assert cache.record(1, Reads(row(1, JobState.FAILED))).state is JobState.RUNNING


def test_step_counts_are_kept_only_while_no_step_can_be_recorded() -> None:
    cache = JobRecordCache()
    counted: list[int] = []

    def count(n: int) -> int:
        counted.append(n)
        return n

    running = row(1, JobState.RUNNING)
    cache.put(running)
    assert cache.step_count(running, lambda: count(3)) == 3
    assert cache.step_count(running, lambda: count(4)) == 4  # running: always read
    done = row(1, JobState.SUCCEEDED)
    cache.put(done)
    assert cache.step_count(done, lambda: count(10)) == 10
    assert cache.step_count(done, lambda: count(99)) == 10  # finished: from memory
    requeued = dataclasses.replace(done, state=JobState.QUEUED)
    cache.put(requeued)  # resumed: the count is read again
    assert cache.step_count(requeued, lambda: count(10)) == 10
    assert counted == [3, 4, 10, 10]


def test_the_cache_is_bounded() -> None:
    cache = JobRecordCache(max_jobs=3)
    for job_id in range(1, 6):
        cache.put(row(job_id))
    reads = Reads(row(1))
    cache.record(1, reads)  # dropped: read again
    cache.record(5, Reads(row(5)))
    assert reads.count == 1
    assert cache.record(5, Reads(row(5, JobState.FAILED))).state is JobState.QUEUED


def test_another_stations_jobs_are_never_kept() -> None:
    """On a shared PostgreSQL database, other stations write their jobs' rows."""
    cache = JobRecordCache()
    foreign = dataclasses.replace(row(1), station_id="bench-2")
    reads = Reads(foreign)

    def mine(job: JobRecord) -> bool:
        return job.station_id != "bench-2"

    cache.record(1, reads, mine)
    cache.record(1, reads, mine)
    assert reads.count == 2
    assert cache.step_count(foreign, lambda: 5) == 5
    assert cache.step_count(foreign, lambda: 6) == 6
