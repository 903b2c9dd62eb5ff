"""The SQLite job store: life cycle, transitions with reasons, steps, WAL, concurrency."""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from station.store import (
    ALLOWED_TRANSITIONS,
    DuplicateStep,
    IdempotencyConflict,
    InvalidTransition,
    JobNotFound,
    JobState,
    JobStore,
    StepRecord,
)

REQUEST = {"start_mm": 0.0, "stop_mm": 9.0, "step_mm": 1.0, "frames": 10}


@pytest.fixture
def store(tmp_path: Path) -> Iterator[JobStore]:
    s = JobStore(tmp_path / "db" / "jobs.sqlite3")
    yield s
    s.close()


def _step(job_id: int, index: int) -> StepRecord:
    return StepRecord(
        job_id,
        index,
        float(index),
        index + 1e-4,
        f"frames/{index:04d}.png",
        "ab" * 32,
        1.0,
        2.0,
        3.0,
    )


def test_a_job_moves_through_its_life_cycle_with_every_transition_stored(
    store: JobStore, tmp_path: Path
) -> None:
    job, created = store.create_job(REQUEST, archive_root=tmp_path, frames_total=10)
    assert created and job.state is JobState.QUEUED and job.request == REQUEST
    assert job.archive_dir.parent == tmp_path and job.archive_dir.name.startswith("job-000001-")
    store.transition(job.id, JobState.RUNNING, "started")
    store.transition(job.id, JobState.PAUSED, "operator")
    store.transition(job.id, JobState.RUNNING, "resumed")
    done = store.transition(job.id, JobState.SUCCEEDED, "calibrated", result={"a_mm": 10.9})
    assert done.has_result and done.updated_at >= job.created_at
    trans = store.transitions(job.id)
    assert [(t.from_state, t.to_state, t.reason) for t in trans] == [
        (None, JobState.QUEUED, "submitted"),
        (JobState.QUEUED, JobState.RUNNING, "started"),
        (JobState.RUNNING, JobState.PAUSED, "operator"),
        (JobState.PAUSED, JobState.RUNNING, "resumed"),
        (JobState.RUNNING, JobState.SUCCEEDED, "calibrated"),
    ]
    assert [t.at for t in trans] == sorted(t.at for t in trans)
    # status reads skip the result (it can be megabytes); it is there on request
    brief = store.get_job(job.id)
    assert brief.has_result and brief.result is None and brief.state is JobState.SUCCEEDED
    assert store.get_job(job.id, with_result=True).result == {"a_mm": 10.9}
    listed = store.list_jobs()
    assert [(j.id, j.has_result, j.result) for j in listed] == [(job.id, True, None)]


def test_every_transition_outside_the_table_is_refused_and_changes_nothing(
    store: JobStore, tmp_path: Path
) -> None:
    # reach every state, then try every target from it
    paths = {
        JobState.QUEUED: [],
        JobState.RUNNING: [JobState.RUNNING],
        JobState.PAUSED: [JobState.RUNNING, JobState.PAUSED],
        JobState.SUCCEEDED: [JobState.RUNNING, JobState.SUCCEEDED],
        JobState.FAILED: [JobState.RUNNING, JobState.FAILED],
        JobState.CANCELLED: [JobState.CANCELLED],
        JobState.INTERRUPTED: [JobState.RUNNING, JobState.INTERRUPTED],
    }
    for state, path in paths.items():
        for target in JobState:
            job, _ = store.create_job(REQUEST, archive_root=tmp_path, frames_total=10)
            for step in path:
                store.transition(job.id, step, "setup")
            before = store.transitions(job.id)
            if target in ALLOWED_TRANSITIONS[state]:
                assert store.transition(job.id, target, "ok").state is target
            else:
                with pytest.raises(InvalidTransition) as info:
                    store.transition(job.id, target, "refused", last_error="x")
                assert info.value.from_state is state and info.value.to_state is target
                assert f"is {state.value}: cannot" in str(info.value)
                assert store.get_job(job.id).state is state
                assert store.get_job(job.id).last_error is None
                assert store.transitions(job.id) == before
    with pytest.raises(JobNotFound):
        store.transition(9999, JobState.RUNNING, "x")


def test_steps_are_recorded_once(store: JobStore, tmp_path: Path) -> None:
    job, _ = store.create_job(REQUEST, archive_root=tmp_path, frames_total=10)
    for i in (2, 0, 1):
        store.record_step(_step(job.id, i))
    with pytest.raises(DuplicateStep):
        store.record_step(_step(job.id, 1))
    assert [s.index for s in store.steps(job.id)] == [0, 1, 2]
    assert [s.index for s in store.steps(job.id, after=0)] == [1, 2]
    store.set_step_summary(job.id, 1, {"Q": 0.2, "Ls_px": None})
    step = store.step(job.id, 1)
    assert step is not None and step.summary == {"Q": 0.2, "Ls_px": None}
    store.delete_steps(job.id, [0, 2])
    assert store.step_count(job.id) == 1


def test_a_real_wal_database_that_survives_reopening(tmp_path: Path) -> None:
    path = tmp_path / "jobs.sqlite3"
    with JobStore(path) as store:
        job, _ = store.create_job(REQUEST, archive_root=tmp_path, frames_total=10)
        store.record_step(_step(job.id, 0))
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    conn.close()
    with JobStore(path) as again:
        assert again.get_job(job.id).state is JobState.QUEUED
        assert again.step_count(job.id) == 1


def test_idempotency_keys(store: JobStore, tmp_path: Path) -> None:
    first, created = store.create_job(
        REQUEST, archive_root=tmp_path, frames_total=10, idempotency_key="k1"
    )
    again, created_again = store.create_job(
        REQUEST, archive_root=tmp_path, frames_total=10, idempotency_key="k1"
    )
    assert created and not created_again and again.id == first.id
    with pytest.raises(IdempotencyConflict, match="different request"):
        store.create_job(
            dict(REQUEST, step_mm=2.0), archive_root=tmp_path, frames_total=5, idempotency_key="k1"
        )
    assert len(store.list_jobs()) == 1


def test_readers_and_writers_in_threads(store: JobStore, tmp_path: Path) -> None:
    job, _ = store.create_job(REQUEST, archive_root=tmp_path, frames_total=200)
    errors: list[BaseException] = []
    stop = threading.Event()

    def write() -> None:
        try:
            for i in range(200):
                store.record_step(_step(job.id, i))
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)
        finally:
            stop.set()

    def read() -> None:
        try:
            last = 0
            while not stop.is_set():
                n = store.step_count(job.id)
                assert n >= last
                last = n
                store.get_job(job.id)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=write)] + [threading.Thread(target=read) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors
    assert store.step_count(job.id) == 200


def _open_fds() -> int:
    return len(list(Path("/proc/self/fd").iterdir()))


def test_thread_churn_cannot_leak_connections(tmp_path: Path) -> None:
    """500 short-lived threads (as a server's thread pool replaces its threads) use the
    store: at most ``pool_size`` connections are ever open, and the descriptors of the
    process are the same before and after."""
    store = JobStore(tmp_path / "jobs.sqlite3", pool_size=4)
    job, _ = store.create_job(REQUEST, archive_root=tmp_path, frames_total=10)
    try:
        with contextlib.ExitStack() as stack:  # fill the pool: 4 connections lent at once
            for _ in range(4):
                stack.enter_context(store.pool.read())
        assert store.health.open_connections == 4
        before = _open_fds()
        peak = 0
        for _ in range(50):
            threads = [threading.Thread(target=store.step_count, args=(job.id,)) for _ in range(10)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            peak = max(peak, store.health.open_connections)
        assert peak <= 4
        assert _open_fds() == before
    finally:
        store.close()
    assert store.health.open_connections == 0


def test_a_full_disk_and_an_io_error_are_named(tmp_path: Path) -> None:
    from station.db import StorageFull, StoreUnavailable, sqlite_error

    full = sqlite3.OperationalError("database or disk is full")
    full.sqlite_errorcode = 13  # type: ignore[attr-defined]
    error = sqlite_error(full, tmp_path / "jobs.sqlite3", "write")
    assert isinstance(error, StorageFull) and "bytes free" in str(error)
    assert str(tmp_path) in str(error) and error.free_bytes is not None
    io = sqlite3.OperationalError("disk I/O error")
    io.sqlite_errorcode = 10  # type: ignore[attr-defined]
    error = sqlite_error(io, tmp_path / "jobs.sqlite3", "write")
    assert type(error) is StoreUnavailable and "cannot be written" in str(error)
    assert "check the disk" in str(error)
