"""Persistent job store: a real SQLite database file in WAL mode.

Tables::

    jobs         id, state, request (JSON), created_at, updated_at, result (JSON),
                 last_error, archive_dir, frames_total, idempotency_key
    transitions  job_id, from_state, to_state, at, reason   (every state change)
    steps        job_id, idx, commanded_mm, actual_mm, file, sha256,
                 started_at, captured_at, written_at, summary (JSON)

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
thread-safe: each thread gets its own connection (WAL lets readers run while
one writer commits); writes use ``BEGIN IMMEDIATE`` and ``synchronous=FULL``, so
a step that :meth:`JobStore.record_step` returned for is on disk.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any


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


class StoreError(Exception):
    """Base class of the job store's errors."""


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


_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    state           TEXT NOT NULL,
    request         TEXT NOT NULL,
    created_at      REAL NOT NULL,
    updated_at      REAL NOT NULL,
    result          TEXT,
    last_error      TEXT,
    archive_dir     TEXT NOT NULL,
    frames_total    INTEGER NOT NULL,
    idempotency_key TEXT UNIQUE
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state);
CREATE TABLE IF NOT EXISTS transitions (
    seq        INTEGER PRIMARY KEY AUTOINCREMENT,
    job_id     INTEGER NOT NULL REFERENCES jobs(id),
    from_state TEXT,
    to_state   TEXT NOT NULL,
    at         REAL NOT NULL,
    reason     TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS transitions_job ON transitions(job_id, seq);
CREATE TABLE IF NOT EXISTS steps (
    job_id       INTEGER NOT NULL REFERENCES jobs(id),
    idx          INTEGER NOT NULL,
    commanded_mm REAL NOT NULL,
    actual_mm    REAL NOT NULL,
    file         TEXT NOT NULL,
    sha256       TEXT NOT NULL,
    started_at   REAL NOT NULL,
    captured_at  REAL NOT NULL,
    written_at   REAL NOT NULL,
    summary      TEXT,
    PRIMARY KEY (job_id, idx)
);
"""

SCHEMA_VERSION = 1


def _dumps(value: Any) -> str:
    return json.dumps(value, allow_nan=False, separators=(",", ":"))


def _loads(text: str | None) -> Any:
    return None if text is None else json.loads(text)


class JobStore:
    """The job database (see the module docstring).

    Args:
        path: the SQLite file (created with its directory if missing).
        busy_timeout_s: how long a writer waits for another writer's lock (s).
    """

    def __init__(self, path: str | Path, *, busy_timeout_s: float = 10.0) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._busy_ms = int(busy_timeout_s * 1000)
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._all_lock = threading.Lock()
        self._closed = False
        conn = self._conn()
        conn.executescript(_SCHEMA)  # idempotent (IF NOT EXISTS); commits by itself
        conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")

    # ------------------------------------------------------------------ connections

    def _conn(self) -> sqlite3.Connection:
        if self._closed:
            raise StoreError(f"job store {self.path} is closed")
        conn: sqlite3.Connection | None = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(
                self.path,
                timeout=self._busy_ms / 1000,
                isolation_level=None,
                check_same_thread=False,
            )
            conn.execute(f"PRAGMA busy_timeout = {self._busy_ms}")
            conn.execute("PRAGMA journal_mode = WAL")
            conn.execute("PRAGMA synchronous = FULL")
            conn.execute("PRAGMA foreign_keys = ON")
            conn.row_factory = sqlite3.Row
            self._local.conn = conn
            with self._all_lock:
                self._all.append(conn)
        return conn

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """A write transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``; rolled back on error)."""
        conn = self._conn()
        conn.execute("BEGIN IMMEDIATE")
        try:
            yield conn
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        conn.execute("COMMIT")

    def close(self) -> None:
        """Close every connection (the store cannot be used afterwards)."""
        self._closed = True
        with self._all_lock:
            conns, self._all = self._all, []
        for conn in conns:
            try:
                conn.close()
            except sqlite3.Error:
                pass

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
    ) -> tuple[JobRecord, bool]:
        """Store a new queued job; return ``(job, created)``.

        The archive directory is ``archive_root/job-000123-20250101T120000`` (UTC). With an
        ``idempotency_key`` already used for the same request, the existing job is
        returned with ``created=False``; with a different request
        :class:`IdempotencyConflict` is raised.
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
                    if _loads(row["request"]) != json.loads(req_text):
                        raise IdempotencyConflict(idempotency_key, row["id"])
                    return _job(row), False
            cur = db.execute(
                "INSERT INTO jobs (state, request, created_at, updated_at, archive_dir, "
                "frames_total, idempotency_key) VALUES (?, ?, ?, ?, '', ?, ?)",
                (JobState.QUEUED.value, req_text, now, now, frames_total, idempotency_key),
            )
            job_id = int(cur.lastrowid or 0)
            stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(now))
            archive = Path(archive_root) / f"job-{job_id:06d}-{stamp}"
            db.execute("UPDATE jobs SET archive_dir = ? WHERE id = ?", (str(archive), job_id))
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
        row = self._conn().execute(f"SELECT {columns} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFound(job_id)
        return _job(row)

    def list_jobs(
        self, *, states: set[JobState] | frozenset[JobState] | None = None, limit: int | None = None
    ) -> list[JobRecord]:
        """Jobs in id order (oldest first), optionally only those in ``states``
        (without their results, see :meth:`get_job`)."""
        sql = f"SELECT {_JOB_COLUMNS} FROM jobs"
        args: list[Any] = []
        if states:
            sql += f" WHERE state IN ({', '.join('?' * len(states))})"
            args.extend(s.value for s in states)
        sql += " ORDER BY id"
        if limit is not None:
            sql += " LIMIT ?"
            args.append(int(limit))
        return [_job(r) for r in self._conn().execute(sql, args).fetchall()]

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

    def transitions(self, job_id: int) -> list[Transition]:
        """Every state change of the job, oldest first."""
        rows = (
            self._conn()
            .execute("SELECT * FROM transitions WHERE job_id = ? ORDER BY seq", (job_id,))
            .fetchall()
        )
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
            except sqlite3.IntegrityError as exc:
                if "UNIQUE" in str(exc) or "PRIMARY KEY" in str(exc):
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
        rows = self._conn().execute(sql + " ORDER BY idx", args).fetchall()
        return [_step(r) for r in rows]

    def step(self, job_id: int, index: int) -> StepRecord | None:
        """One recorded step, or None."""
        row = (
            self._conn()
            .execute("SELECT * FROM steps WHERE job_id = ? AND idx = ?", (job_id, index))
            .fetchone()
        )
        return None if row is None else _step(row)

    def step_count(self, job_id: int) -> int:
        """Number of recorded steps of the job."""
        row = (
            self._conn()
            .execute("SELECT COUNT(*) AS n FROM steps WHERE job_id = ?", (job_id,))
            .fetchone()
        )
        return int(row["n"])


_JOB_COLUMNS = (
    "id, state, request, created_at, updated_at, last_error, archive_dir, frames_total, "
    "idempotency_key, result IS NOT NULL AS has_result"
)
_JOB_COLUMNS_WITH_RESULT = _JOB_COLUMNS + ", result"


def _job(row: sqlite3.Row) -> JobRecord:
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
    )


def _step(row: sqlite3.Row) -> StepRecord:
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
    "StoreError",
    "Transition",
]
