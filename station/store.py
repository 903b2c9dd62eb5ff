"""Persistent job store: a SQLite database file in WAL mode, or a PostgreSQL database.

Tables (schema version :data:`station.schema.HEAD`, created and upgraded by the
alembic migrations of :mod:`station.schema` when the store opens)::

    jobs         id, state, request (JSON), created_at, updated_at, result (JSON),
                 last_error, archive_dir, frames_total, idempotency_key,
                 station_id, camera_serial, archive_url, archive_uploaded_at
    transitions  job_id, from_state, to_state, at, reason   (every state change)
    steps        job_id, idx, commanded_mm, actual_mm, file, sha256,
                 started_at, captured_at, written_at, summary (JSON)
    results      job_id, version, software_version, created_at, source, result (JSON)
                 (results computed again later: :mod:`station.result_versions`)

**Backends.** ``JobStore("data/lfcal.sqlite3")`` opens a SQLite file
(:class:`station.db.SQLitePool`), ``JobStore("postgresql://user@host/db")`` a
PostgreSQL database (:class:`station.db_postgres.PostgresPool`); the store's SQL
is the same for both (the PostgreSQL pool takes the ``?`` placeholders).

**Stations.** Every job carries the ``station_id`` of the store that created it
(``[storage] station_id``) and the serial of the camera that took its frames. Several
stations may share one PostgreSQL database: each lists, recovers and runs only its
own jobs (``list_jobs(station=...)``; :mod:`station.ownership` keeps two processes
of one station apart), and every station can read every job (the fleet view).

Job life cycle (:data:`ALLOWED_TRANSITIONS`)::

    queued ──> running <──> paused
      │          │            │
      │          ├──> succeeded | failed | cancelled | interrupted
      │          │
      └──> cancelled          interrupted | failed ──(resume)──> queued

``interrupted`` is what a job found ``running`` or ``paused`` at start-up
becomes (the process died under it); ``resume`` re-queues an interrupted or
failed job, which then continues from its first missing step. Every change is
stored with its time and reason in the same transaction as the new state; a
change the table does not allow raises :class:`InvalidTransition` (the web
layer answers 409) and changes nothing.

Times are Unix epoch seconds (float). Positions are mm. The store is
thread-safe: every operation borrows a connection from a bounded pool
(:class:`station.db.SQLitePool`, at most 8 connections whatever the number of
threads) and gives it back at once, so no connection outlives its use (WAL
lets readers run while one writer commits); writes use ``BEGIN IMMEDIATE`` and
``synchronous=FULL``, so a step that :meth:`JobStore.record_step` returned for
is on disk. A database that cannot be written raises
:class:`station.db.StoreUnavailable`, a full disk :class:`station.db.StorageFull`
(with the path and the free space); :attr:`JobStore.health` keeps the last
such error until an operation succeeds again.
"""

from __future__ import annotations

import json
import os
import sqlite3
import time
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from station.db import (
    ConnectionPool,
    SQLitePool,
    StorageFull,
    StoreError,
    StoreHealth,
    StoreUnavailable,
    UniqueViolation,
)
from station.schema import HEAD as SCHEMA_HEAD
from station.schema import ensure_schema


class JobState(StrEnum):
    """States of a job."""

    QUEUED = "queued"
    RUNNING = "running"
    PAUSED = "paused"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    INTERRUPTED = "interrupted"


ALLOWED_TRANSITIONS: dict[JobState, frozenset[JobState]] = {
    JobState.QUEUED: frozenset({JobState.RUNNING, JobState.CANCELLED}),
    JobState.RUNNING: frozenset(
        {
            JobState.PAUSED,
            JobState.SUCCEEDED,
            JobState.FAILED,
            JobState.CANCELLED,
            JobState.INTERRUPTED,
        }
    ),
    JobState.PAUSED: frozenset(
        {JobState.RUNNING, JobState.CANCELLED, JobState.FAILED, JobState.INTERRUPTED}
    ),
    JobState.INTERRUPTED: frozenset({JobState.QUEUED, JobState.CANCELLED}),
    JobState.FAILED: frozenset({JobState.QUEUED}),
    JobState.SUCCEEDED: frozenset(),
    JobState.CANCELLED: frozenset(),
}
"""Which state may follow which (anything else raises :class:`InvalidTransition`)."""

TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.CANCELLED})
"""States a job never leaves."""

ACTIVE_STATES = frozenset({JobState.RUNNING, JobState.PAUSED})
"""States in which the hardware worker holds the job."""


# --------------------------------------------------------------------------- errors


class JobNotFound(StoreError, KeyError):
    """No job with this id (the web layer answers 404)."""

    def __init__(self, job_id: int) -> None:
        self.job_id = job_id
        super().__init__(f"no job {job_id}")

    def __str__(self) -> str:
        return f"no job {self.job_id}"


class InvalidTransition(StoreError):
    """A state change the life cycle does not allow (the web layer answers 409).

    Attributes:
        job_id: the job.
        from_state: its state when the change was asked for.
        to_state: the state that was asked for.
    """

    def __init__(
        self, job_id: int, from_state: JobState, to_state: JobState, action: str = ""
    ) -> None:
        self.job_id = job_id
        self.from_state = from_state
        self.to_state = to_state
        self.action = action or f"move to {to_state.value}"
        allowed = sorted(s.value for s in ALLOWED_TRANSITIONS[from_state])
        tail = (
            f"; from {from_state.value} it can only go to {', '.join(allowed)}"
            if allowed
            else (f"; {from_state.value} is final")
        )
        super().__init__(f"job {job_id} is {from_state.value}: cannot {self.action}{tail}")


class DuplicateStep(StoreError):
    """A step index that is already recorded for the job (never recorded twice)."""


class IdempotencyConflict(StoreError):
    """An idempotency key that was already used with a different request."""

    def __init__(self, key: str, job_id: int) -> None:
        self.key = key
        self.job_id = job_id
        super().__init__(
            f"idempotency key {key!r} was already used for job {job_id} with a different request"
        )


# --------------------------------------------------------------------------- records


@dataclass(frozen=True)
class JobRecord:
    """One row of ``jobs``.

    Attributes:
        id: job id (1, 2, ...).
        state: current state.
        request: the validated sweep request (JSON object).
        created_at, updated_at: Unix time (s).
        result: the calibration result (JSON object), or the partial result of a
            failed calibration, or None; only loaded on request
            (``get_job(..., with_result=True)``): it can be megabytes of JSON.
        has_result: a result is stored (whether or not it was loaded).
        last_error: why the job last failed / was interrupted (None if it did not).
        archive_dir: directory of the job's ``lfcal-sweep/1`` archive.
        frames_total: number of rail positions of the sweep.
        idempotency_key: the client's key, if one was given.
        station_id: the station that owns the job (runs, recovers and resumes it).
        camera_serial: serial number of the camera that took (or will take) the frames.
        archive_url: where the archive is uploaded (``s3://...``), or None.
        archive_uploaded_at: Unix time (s) the final archive was uploaded and
            verified, or None.
    """

    id: int
    state: JobState
    request: dict[str, Any]
    created_at: float
    updated_at: float
    result: dict[str, Any] | None
    last_error: str | None
    archive_dir: Path
    frames_total: int
    idempotency_key: str | None = None
    has_result: bool = False
    station_id: str = ""
    camera_serial: str | None = None
    archive_url: str | None = None
    archive_uploaded_at: float | None = None


@dataclass(frozen=True)
class Transition:
    """One row of ``transitions``: a state change with its time (Unix s) and reason."""

    job_id: int
    from_state: JobState | None
    to_state: JobState
    at: float
    reason: str


@dataclass(frozen=True)
class StepRecord:
    """One row of ``steps``: a captured, written frame.

    Attributes:
        job_id: the job.
        index: frame index in the sweep (0-based).
        commanded_mm: rail position that was commanded (mm).
        actual_mm: rail position read back after the move (mm).
        file: frame file relative to the archive (``frames/0007.png``).
        sha256: SHA-256 of that file (64 hex digits).
        started_at: Unix time (s) the step's move started.
        captured_at: Unix time (s) the frame arrived.
        written_at: Unix time (s) the frame was on disk and in the manifest.
        summary: the frame's analysis summary (JSON object), once analysed.
    """

    job_id: int
    index: int
    commanded_mm: float
    actual_mm: float
    file: str
    sha256: str
    started_at: float
    captured_at: float
    written_at: float
    summary: dict[str, Any] | None = None


SCHEMA_VERSION = SCHEMA_HEAD
"""The schema version this software writes (:data:`station.schema.HEAD`)."""


def _dumps(value: Any) -> str:
    return json.dumps(value, allow_nan=False, separators=(",", ":"))


def _loads(text: str | None) -> Any:
    return None if text is None else json.loads(text)


class JobStore:
    """The job database (see the module docstring).

    Args:
        path: the SQLite file (created with its directory if missing), a
            ``postgresql://`` URL, or an open :class:`station.db.ConnectionPool`.
        busy_timeout_s: how long a writer waits for another writer's lock (s).
        pool_size: most connections open at once.
        station_id: the station whose jobs this store creates (``[storage]
            station_id``); a SQLite store also adopts the jobs of a database made
            before stations existed (``station_id = ''``).
        archive_url: the object-storage prefix of this station's archives
            (``s3://bucket/prefix``), or None: each new job's archive then goes to
            ``archive_url/station_id/job-...``.

    Raises :class:`station.schema.SchemaTooNew` for a database of a newer
    software version, :class:`station.db.StoreUnavailable` when it cannot be
    reached or written.
    """

    def __init__(
        self,
        path: str | Path | ConnectionPool,
        *,
        busy_timeout_s: float = 10.0,
        pool_size: int = 8,
        station_id: str | None = None,
        archive_url: str | None = None,
    ) -> None:
        from station.db_postgres import PostgresPool, is_postgres_url

        self._db: ConnectionPool
        if isinstance(path, str | Path) and is_postgres_url(path):
            self._db = PostgresPool(str(path), size=pool_size, busy_timeout_s=busy_timeout_s)
            self.path = Path(self._db.path)
        elif isinstance(path, str | Path):
            self._db = SQLitePool(path, size=pool_size, busy_timeout_s=busy_timeout_s)
            self.path = Path(path)
        else:
            self._db = path
            self.path = Path(getattr(path, "path", ""))
        self.postgres = hasattr(self._db, "url")
        self.station_id = station_id if station_id is not None else default_station_id()
        self.archive_url = archive_url.rstrip("/") if archive_url else None
        try:
            ensure_schema(self._db)
            if not self.postgres:
                with self._db.write() as conn:
                    conn.execute(
                        "UPDATE jobs SET station_id = ? WHERE station_id = ''", (self.station_id,)
                    )
        except BaseException:
            self._db.close()
            raise

    # ------------------------------------------------------------------ connections

    @property
    def pool(self) -> ConnectionPool:
        """The connection pool (its size, for tests and diagnostics)."""
        return self._db

    @property
    def health(self) -> StoreHealth:
        """The last read or write error, if no operation succeeded since."""
        return self._db.health

    def _write(self) -> Any:
        """A write transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``; rolled back on error)."""
        return self._db.write()

    def _read(self) -> Any:
        return self._db.read()

    @property
    def own_station(self) -> str | None:
        """The station whose jobs this process recovers, runs and uploads: this store's
        station on a shared PostgreSQL database; None (every job) on a SQLite file,
        which only one station ever uses (its file lock)."""
        return self.station_id if self.postgres else None

    def stations_holding_advisory_lock(self, classid: int) -> set[str]:
        """PostgreSQL: the jobs' station ids for which a database session holds the
        advisory lock ``(classid, hashtext(station_id))`` (:mod:`station.ownership`)."""
        with self._read() as db:
            rows = db.execute(
                "SELECT DISTINCT j.station_id FROM jobs j JOIN pg_locks l "
                "ON l.locktype = 'advisory' AND l.granted AND l.classid = ? "
                "AND l.objid = hashtext(j.station_id)::oid AND l.objsubid = 2",
                (classid,),
            ).fetchall()
        return {str(r["station_id"]) for r in rows}

    def owns(self, job: JobRecord) -> bool:
        """This station may run, pause, resume and cancel ``job``."""
        return self.own_station is None or job.station_id == self.own_station

    def probe_write(self) -> None:
        """Write the database once (SQLite: its header's ``user_version``; PostgreSQL:
        the schema version row, unchanged): raises :class:`StoreUnavailable` /
        :class:`StorageFull` if it cannot be written."""
        with self._db.write() as conn:
            if self.postgres:
                conn.execute("UPDATE alembic_version SET version_num = version_num")
            else:
                conn.execute("PRAGMA user_version = 2")

    def close(self) -> None:
        """Close every connection (the store cannot be used afterwards)."""
        self._db.close()

    def __enter__(self) -> JobStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ jobs

    def create_job(
        self,
        request: Mapping[str, Any],
        *,
        archive_root: str | Path,
        frames_total: int,
        idempotency_key: str | None = None,
        reason: str = "submitted",
        camera_serial: str | None = None,
    ) -> tuple[JobRecord, bool]:
        """Store a new queued job of this store's station; return ``(job, created)``.

        The archive directory is ``archive_root/job-000123-20250101T120000`` (UTC), and
        with object storage its URL ``archive_url/STATION/job-000123-...``. With an
        ``idempotency_key`` already used for the same request, the existing job is
        returned with ``created=False``; with a different request (or by another
        station) :class:`IdempotencyConflict` is raised.
        """
        req_text = _dumps(dict(request))
        now = time.time()
        with self._write() as db:
            if idempotency_key is not None:
                row = db.execute(
                    f"SELECT {_JOB_COLUMNS} FROM jobs WHERE idempotency_key = ?",
                    (idempotency_key,),
                ).fetchone()
                if row is not None:
                    if (
                        _loads(row["request"]) != json.loads(req_text)
                        or row["station_id"] != self.station_id
                    ):
                        raise IdempotencyConflict(idempotency_key, row["id"])
                    return _job(row), False
            cur = db.execute(
                "INSERT INTO jobs (state, request, created_at, updated_at, archive_dir, "
                "frames_total, idempotency_key, station_id, camera_serial) "
                "VALUES (?, ?, ?, ?, '', ?, ?, ?, ?) RETURNING id",
                (
                    JobState.QUEUED.value,
                    req_text,
                    now,
                    now,
                    frames_total,
                    idempotency_key,
                    self.station_id,
                    camera_serial,
                ),
            )
            job_id = int(cur.fetchone()["id"])
            stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(now))
            name = f"job-{job_id:06d}-{stamp}"
            archive = Path(archive_root) / name
            url = (
                None if self.archive_url is None else f"{self.archive_url}/{self.station_id}/{name}"
            )
            db.execute(
                "UPDATE jobs SET archive_dir = ?, archive_url = ? WHERE id = ?",
                (str(archive), url, job_id),
            )
            db.execute(
                "INSERT INTO transitions (job_id, from_state, to_state, at, reason) "
                "VALUES (?, NULL, ?, ?, ?)",
                (job_id, JobState.QUEUED.value, now, reason),
            )
            row = db.execute(f"SELECT {_JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _job(row), True

    def get_job(self, job_id: int, *, with_result: bool = False) -> JobRecord:
        """The job; :class:`JobNotFound` if there is none.

        The result is read and parsed only ``with_result`` (``has_result`` tells
        whether there is one): status polling must not parse megabytes of JSON.
        """
        columns = _JOB_COLUMNS_WITH_RESULT if with_result else _JOB_COLUMNS
        with self._read() as db:
            row = db.execute(f"SELECT {columns} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFound(job_id)
        return _job(row)

    def list_jobs(
        self,
        *,
        states: set[JobState] | frozenset[JobState] | None = None,
        limit: int | None = None,
        station: str | None = None,
        camera_serial: str | None = None,
        since: float | None = None,
    ) -> list[JobRecord]:
        """Jobs in id order (oldest first), optionally only those in ``states``, of
        ``station``, of the camera ``camera_serial``, created at or after ``since``
        (Unix s); without their results (see :meth:`get_job`)."""
        sql = f"SELECT {_JOB_COLUMNS} FROM jobs"
        where: list[str] = []
        args: list[Any] = []
        if states:
            where.append(f"state IN ({', '.join('?' * len(states))})")
            args.extend(s.value for s in states)
        if station is not None:
            where.append("station_id = ?")
            args.append(station)
        if camera_serial is not None:
            where.append("camera_serial = ?")
            args.append(camera_serial)
        if since is not None:
            where.append("created_at >= ?")
            args.append(float(since))
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY id"
        if limit is not None:
            sql += " LIMIT ?"
            args.append(int(limit))
        with self._read() as db:
            rows = db.execute(sql, args).fetchall()
        return [_job(r) for r in rows]

    def transition(
        self,
        job_id: int,
        to_state: JobState,
        reason: str,
        *,
        expect: set[JobState] | frozenset[JobState] | None = None,
        last_error: str | None = None,
        clear_error: bool = False,
        result: dict[str, Any] | None = None,
        action: str = "",
    ) -> JobRecord:
        """Change the state of a job and store the change with its time and reason.

        ``expect`` narrows the allowed *from* states further (e.g. pause only
        from running). ``last_error`` / ``result`` are stored in the same
        transaction. Raises :class:`JobNotFound` / :class:`InvalidTransition`
        (nothing changes then). Returns the job without its result (see
        :meth:`get_job`).
        """
        now = time.time()
        result_json = None if result is None else _dumps(result)  # before the write lock
        with self._write() as db:
            row = db.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                raise JobNotFound(job_id)
            current = JobState(row["state"])
            allowed = ALLOWED_TRANSITIONS[current]
            if to_state not in allowed or (expect is not None and current not in expect):
                raise InvalidTransition(job_id, current, to_state, action)
            sets = ["state = ?", "updated_at = ?"]
            args: list[Any] = [to_state.value, now]
            if last_error is not None:
                sets.append("last_error = ?")
                args.append(last_error)
            elif clear_error:
                sets.append("last_error = NULL")
            if result_json is not None:
                sets.append("result = ?")
                args.append(result_json)
            if to_state is JobState.QUEUED:  # resumed: more frames to upload
                sets.append("archive_uploaded_at = NULL")
            args.append(job_id)
            db.execute(f"UPDATE jobs SET {', '.join(sets)} WHERE id = ?", args)
            db.execute(
                "INSERT INTO transitions (job_id, from_state, to_state, at, reason) "
                "VALUES (?, ?, ?, ?, ?)",
                (job_id, current.value, to_state.value, now, reason),
            )
            new = db.execute(f"SELECT {_JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return _job(new)

    def set_error(self, job_id: int, message: str | None) -> None:
        """Store (or clear, with None) the job's last error without changing its state."""
        with self._write() as db:
            cur = db.execute(
                "UPDATE jobs SET last_error = ?, updated_at = ? WHERE id = ?",
                (message, time.time(), job_id),
            )
            if cur.rowcount == 0:
                raise JobNotFound(job_id)

    def set_result(self, job_id: int, result: dict[str, Any] | None) -> None:
        """Store the job's calibration result (JSON object) without changing its state."""
        with self._write() as db:
            cur = db.execute(
                "UPDATE jobs SET result = ?, updated_at = ? WHERE id = ?",
                (None if result is None else _dumps(result), time.time(), job_id),
            )
            if cur.rowcount == 0:
                raise JobNotFound(job_id)

    def set_camera_serial(self, job_id: int, serial: str | None) -> None:
        """Record the serial of the camera that takes the job's frames."""
        with self._write() as db:
            db.execute("UPDATE jobs SET camera_serial = ? WHERE id = ?", (serial, job_id))

    def mark_archive_uploaded(
        self, job_id: int, at: float | None = None, *, as_of: JobRecord | None = None
    ) -> bool:
        """Record that every file of the job's final archive is uploaded and verified.

        With ``as_of`` (the job as read when the upload pass began) the mark is
        only written if the job has not changed since (same state and
        ``updated_at``): a job resumed during the pass has new frames to upload.
        Returns whether the mark was written.
        """
        sql = "UPDATE jobs SET archive_uploaded_at = ? WHERE id = ?"
        args: list[Any] = [time.time() if at is None else at, job_id]
        if as_of is not None:
            sql += " AND state = ? AND updated_at = ?"
            args += [as_of.state.value, as_of.updated_at]
        with self._write() as db:
            cur = db.execute(sql, args)
            return bool(cur.rowcount)

    def jobs_to_upload(self) -> list[JobRecord]:
        """This station's jobs with an archive URL whose archive is not completely
        uploaded yet (oldest first)."""
        sql = f"SELECT {_JOB_COLUMNS} FROM jobs WHERE archive_url IS NOT NULL"
        sql += " AND archive_uploaded_at IS NULL"
        args: list[Any] = []
        if self.own_station is not None:
            sql += " AND station_id = ?"
            args.append(self.own_station)
        with self._read() as db:
            rows = db.execute(sql + " ORDER BY id", args).fetchall()
        return [_job(r) for r in rows]

    def stations(self) -> list[dict[str, Any]]:
        """Every station with jobs in the database: id, jobs, active jobs, last change."""
        with self._read() as db:
            rows = db.execute(
                "SELECT station_id, COUNT(*) AS jobs, MAX(updated_at) AS last_change "
                "FROM jobs GROUP BY station_id ORDER BY station_id"
            ).fetchall()
        return [dict(r) for r in rows]

    def transitions(self, job_id: int) -> list[Transition]:
        """Every state change of the job, oldest first."""
        with self._read() as db:
            rows = db.execute(
                "SELECT * FROM transitions WHERE job_id = ? ORDER BY seq", (job_id,)
            ).fetchall()
        return [
            Transition(
                job_id=r["job_id"],
                from_state=None if r["from_state"] is None else JobState(r["from_state"]),
                to_state=JobState(r["to_state"]),
                at=r["at"],
                reason=r["reason"],
            )
            for r in rows
        ]

    # ------------------------------------------------------------------ steps

    def record_step(self, step: StepRecord) -> None:
        """Store a written frame. :class:`DuplicateStep` if the index is already recorded."""
        with self._write() as db:
            try:
                db.execute(
                    "INSERT INTO steps (job_id, idx, commanded_mm, actual_mm, file, sha256, "
                    "started_at, captured_at, written_at, summary) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        step.job_id,
                        step.index,
                        step.commanded_mm,
                        step.actual_mm,
                        step.file,
                        step.sha256,
                        step.started_at,
                        step.captured_at,
                        step.written_at,
                        None if step.summary is None else _dumps(step.summary),
                    ),
                )
            except (sqlite3.IntegrityError, UniqueViolation) as exc:
                if (
                    isinstance(exc, UniqueViolation)
                    or "UNIQUE" in str(exc)
                    or "PRIMARY KEY" in str(exc)
                ):
                    raise DuplicateStep(
                        f"job {step.job_id}: step {step.index} is already recorded"
                    ) from None
                raise
            db.execute("UPDATE jobs SET updated_at = ? WHERE id = ?", (time.time(), step.job_id))

    def set_step_summary(self, job_id: int, index: int, summary: dict[str, Any]) -> None:
        """Attach the analysis summary (JSON object) to a recorded step."""
        with self._write() as db:
            db.execute(
                "UPDATE steps SET summary = ? WHERE job_id = ? AND idx = ?",
                (_dumps(summary), job_id, index),
            )

    def delete_steps(self, job_id: int, indices: list[int]) -> None:
        """Forget recorded steps (their frames failed verification and will be re-captured)."""
        if not indices:
            return
        with self._write() as db:
            db.executemany(
                "DELETE FROM steps WHERE job_id = ? AND idx = ?", [(job_id, i) for i in indices]
            )

    def steps(self, job_id: int, *, after: int | None = None) -> list[StepRecord]:
        """Recorded steps of the job in index order (only ``index > after`` if given)."""
        sql = "SELECT * FROM steps WHERE job_id = ?"
        args: list[Any] = [job_id]
        if after is not None:
            sql += " AND idx > ?"
            args.append(after)
        with self._read() as db:
            rows = db.execute(sql + " ORDER BY idx", args).fetchall()
        return [_step(r) for r in rows]

    def step(self, job_id: int, index: int) -> StepRecord | None:
        """One recorded step, or None."""
        with self._read() as db:
            row = db.execute(
                "SELECT * FROM steps WHERE job_id = ? AND idx = ?", (job_id, index)
            ).fetchone()
        return None if row is None else _step(row)

    def step_count(self, job_id: int) -> int:
        """Number of recorded steps of the job."""
        with self._read() as db:
            row = db.execute(
                "SELECT COUNT(*) AS n FROM steps WHERE job_id = ?", (job_id,)
            ).fetchone()
        return int(row["n"])


_JOB_COLUMNS = (
    "id, state, request, created_at, updated_at, last_error, archive_dir, frames_total, "
    "idempotency_key, result IS NOT NULL AS has_result, station_id, camera_serial, "
    "archive_url, archive_uploaded_at"
)
_JOB_COLUMNS_WITH_RESULT = _JOB_COLUMNS + ", result"


def _job(row: Any) -> JobRecord:
    """A record from a row of ``_JOB_COLUMNS`` (plus ``result`` if it was selected)."""
    return JobRecord(
        id=int(row["id"]),
        state=JobState(row["state"]),
        request=_loads(row["request"]),
        created_at=float(row["created_at"]),
        updated_at=float(row["updated_at"]),
        result=_loads(row["result"]) if "result" in row.keys() else None,
        last_error=row["last_error"],
        archive_dir=Path(row["archive_dir"]),
        frames_total=int(row["frames_total"]),
        idempotency_key=row["idempotency_key"],
        has_result=bool(row["has_result"]),
        station_id=row["station_id"],
        camera_serial=row["camera_serial"],
        archive_url=row["archive_url"],
        archive_uploaded_at=row["archive_uploaded_at"],
    )


def default_station_id() -> str:
    """The station id when none is configured: ``$LFCAL_STATION_ID`` or the host name."""
    return os.environ.get("LFCAL_STATION_ID") or os.uname().nodename or "station"


def _step(row: Any) -> StepRecord:
    return StepRecord(
        job_id=int(row["job_id"]),
        index=int(row["idx"]),
        commanded_mm=float(row["commanded_mm"]),
        actual_mm=float(row["actual_mm"]),
        file=row["file"],
        sha256=row["sha256"],
        started_at=float(row["started_at"]),
        captured_at=float(row["captured_at"]),
        written_at=float(row["written_at"]),
        summary=_loads(row["summary"]),
    )


__all__ = [
    "ACTIVE_STATES",
    "ALLOWED_TRANSITIONS",
    "TERMINAL_STATES",
    "DuplicateStep",
    "IdempotencyConflict",
    "InvalidTransition",
    "JobNotFound",
    "JobRecord",
    "JobState",
    "JobStore",
    "StepRecord",
    "StorageFull",
    "StoreError",
    "StoreHealth",
    "StoreUnavailable",
    "Transition",
    "default_station_id",
]
