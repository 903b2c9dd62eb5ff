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

Job life cycle: :mod:`station.job_states` (states and :data:`ALLOWED_TRANSITIONS`),
:mod:`station.job_transitions` (every change stored with its time and reason in the
same transaction as the new state; a change the table does not allow raises
:class:`InvalidTransition`, the web layer answers 409, and changes nothing). The
records are in :mod:`station.store_rows`, the errors in :mod:`station.store_errors`
(all importable from here), new jobs in :mod:`station.job_submission`, the steps'
queries in :mod:`station.job_steps`.

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

import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from station.db import (
    ConnectionPool,
    SQLitePool,
    StorageFull,
    StoreError,
    StoreHealth,
    StoreUnavailable,
)
from station.job_states import ACTIVE_STATES, ALLOWED_TRANSITIONS, TERMINAL_STATES, JobState
from station.job_steps import JobSteps
from station.job_submission import store_new_job
from station.job_transitions import JobTransitions
from station.schema import HEAD as SCHEMA_HEAD
from station.schema import ensure_schema
from station.store_errors import DuplicateStep, IdempotencyConflict, InvalidTransition, JobNotFound
from station.store_rows import (
    JOB_COLUMNS,
    JOB_COLUMNS_WITH_RESULT,
    JobRecord,
    StepRecord,
    Transition,
    encode_json,
    job_from_row,
    select_jobs,
)

SCHEMA_VERSION = SCHEMA_HEAD
"""The schema version this software writes (:data:`station.schema.HEAD`)."""


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
        self._transitions = JobTransitions(self._db)
        self._steps = JobSteps(self._db)
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

    @property
    def own_station(self) -> str | None:
        """The station whose jobs this process recovers, runs and uploads: this store's
        station on a shared PostgreSQL database; None (every job) on a SQLite file,
        which only one station ever uses (its file lock)."""
        return self.station_id if self.postgres else None

    def stations_holding_advisory_lock(self, classid: int) -> set[str]:
        """PostgreSQL: the jobs' station ids for which a database session holds the
        advisory lock ``(classid, hashtext(station_id))`` (:mod:`station.ownership`)."""
        with self._db.read() as db:
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

        Its archive directory is ``archive_root/job-000123-20250101T120000`` (UTC);
        an ``idempotency_key`` already used returns that job (``created=False``) or
        raises :class:`IdempotencyConflict` (:mod:`station.job_submission`).
        """
        return store_new_job(
            self._db,
            request,
            station_id=self.station_id,
            archive_url=self.archive_url,
            archive_root=archive_root,
            frames_total=frames_total,
            idempotency_key=idempotency_key,
            reason=reason,
            camera_serial=camera_serial,
        )

    def get_job(self, job_id: int, *, with_result: bool = False) -> JobRecord:
        """The job; :class:`JobNotFound` if there is none.

        The result is read and parsed only ``with_result`` (``has_result`` tells
        whether there is one): status polling must not parse megabytes of JSON.
        """
        columns = JOB_COLUMNS_WITH_RESULT if with_result else JOB_COLUMNS
        with self._db.read() as db:
            row = db.execute(f"SELECT {columns} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFound(job_id)
        return job_from_row(row)

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
        sql, args = select_jobs(states, station, camera_serial, since, limit)
        with self._db.read() as db:
            rows = db.execute(sql, args).fetchall()
        return [job_from_row(r) for r in rows]

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
        return self._transitions.change(
            job_id,
            to_state,
            reason,
            expect=expect,
            last_error=last_error,
            clear_error=clear_error,
            result=result,
            action=action,
        )

    def set_error(self, job_id: int, message: str | None) -> None:
        """Store (or clear, with None) the job's last error without changing its state."""
        with self._db.write() as db:
            cur = db.execute(
                "UPDATE jobs SET last_error = ?, updated_at = ? WHERE id = ?",
                (message, time.time(), job_id),
            )
            if cur.rowcount == 0:
                raise JobNotFound(job_id)

    def set_result(self, job_id: int, result: dict[str, Any] | None) -> None:
        """Store the job's calibration result (JSON object) without changing its state."""
        with self._db.write() as db:
            cur = db.execute(
                "UPDATE jobs SET result = ?, updated_at = ? WHERE id = ?",
                (None if result is None else encode_json(result), time.time(), job_id),
            )
            if cur.rowcount == 0:
                raise JobNotFound(job_id)

    def set_camera_serial(self, job_id: int, serial: str | None) -> None:
        """Record the serial of the camera that takes the job's frames."""
        with self._db.write() as db:
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
        with self._db.write() as db:
            cur = db.execute(sql, args)
            return bool(cur.rowcount)

    def jobs_to_upload(self) -> list[JobRecord]:
        """This station's jobs with an archive URL whose archive is not completely
        uploaded yet (oldest first)."""
        sql = f"SELECT {JOB_COLUMNS} FROM jobs WHERE archive_url IS NOT NULL"
        sql += " AND archive_uploaded_at IS NULL"
        args: list[Any] = []
        if self.own_station is not None:
            sql += " AND station_id = ?"
            args.append(self.own_station)
        with self._db.read() as db:
            rows = db.execute(sql + " ORDER BY id", args).fetchall()
        return [job_from_row(r) for r in rows]

    def stations(self) -> list[dict[str, Any]]:
        """Every station with jobs in the database: id, jobs, active jobs, last change."""
        with self._db.read() as db:
            rows = db.execute(
                "SELECT station_id, COUNT(*) AS jobs, MAX(updated_at) AS last_change "
                "FROM jobs GROUP BY station_id ORDER BY station_id"
            ).fetchall()
        return [dict(r) for r in rows]

    def transitions(self, job_id: int) -> list[Transition]:
        """Every state change of the job, oldest first."""
        return self._transitions.history(job_id)

    # ------------------------------------------------------------------ steps

    def record_step(self, step: StepRecord) -> None:
        """Store a written frame. :class:`DuplicateStep` if the index is already recorded."""
        self._steps.record(step)

    def set_step_summary(self, job_id: int, index: int, summary: dict[str, Any]) -> None:
        """Attach the analysis summary (JSON object) to a recorded step."""
        self._steps.set_summary(job_id, index, summary)

    def delete_steps(self, job_id: int, indices: list[int]) -> None:
        """Forget recorded steps (their frames failed verification and will be re-captured)."""
        self._steps.delete(job_id, indices)

    def steps(self, job_id: int, *, after: int | None = None) -> list[StepRecord]:
        """Recorded steps of the job in index order (only ``index > after`` if given)."""
        return self._steps.of_job(job_id, after=after)

    def step(self, job_id: int, index: int) -> StepRecord | None:
        """One recorded step, or None."""
        return self._steps.get(job_id, index)

    def step_count(self, job_id: int) -> int:
        """Number of recorded steps of the job."""
        return self._steps.count(job_id)


def default_station_id() -> str:
    """The station id when none is configured: ``$LFCAL_STATION_ID`` or the host name."""
    return os.environ.get("LFCAL_STATION_ID") or os.uname().nodename or "station"


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
