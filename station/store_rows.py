"""The rows of the job store as records, and how they are read from and written to SQL.

:class:`JobRecord` is a row of ``jobs``, :class:`Transition` one of ``transitions``,
:class:`StepRecord` one of ``steps`` (the tables: :mod:`station.store`). JSON columns
(a job's request and result, a step's summary) are stored as compact text
(:func:`encode_json`) and parsed when read (:func:`decode_json`); :func:`select_jobs`
builds the query of a filtered job list. Times are Unix epoch seconds (float),
positions mm.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.job_states import JobState


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


JOB_COLUMNS = (
    "id, state, request, created_at, updated_at, last_error, archive_dir, frames_total, "
    "idempotency_key, result IS NOT NULL AS has_result, station_id, camera_serial, "
    "archive_url, archive_uploaded_at"
)
"""The ``jobs`` columns of a :class:`JobRecord` without its result (``has_result`` instead)."""

JOB_COLUMNS_WITH_RESULT = JOB_COLUMNS + ", result"
"""The ``jobs`` columns of a :class:`JobRecord` with its result."""


def select_jobs(
    states: set[JobState] | frozenset[JobState] | None = None,
    station: str | None = None,
    camera_serial: str | None = None,
    since: float | None = None,
    limit: int | None = None,
) -> tuple[str, list[Any]]:
    """The ``SELECT`` of :data:`JOB_COLUMNS` and its arguments for the jobs in id order,
    optionally only those in ``states``, of ``station``, of the camera ``camera_serial``,
    created at or after ``since`` (Unix s), at most ``limit``
    (:meth:`station.store.JobStore.list_jobs`)."""
    sql = f"SELECT {JOB_COLUMNS} FROM jobs"
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
    return sql, args


def encode_json(value: Any) -> str:
    """``value`` as compact JSON text (NaN and infinities refused: ``ValueError``)."""
    return json.dumps(value, allow_nan=False, separators=(",", ":"))


def decode_json(text: str | None) -> Any:
    """The value of a JSON column (None for SQL ``NULL``)."""
    return None if text is None else json.loads(text)


def job_from_row(row: Any) -> JobRecord:
    """A record from a row of :data:`JOB_COLUMNS` (plus ``result`` if it was selected)."""
    return JobRecord(
        id=int(row["id"]),
        state=JobState(row["state"]),
        request=decode_json(row["request"]),
        created_at=float(row["created_at"]),
        updated_at=float(row["updated_at"]),
        result=decode_json(row["result"]) if "result" in row.keys() else None,
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


def transition_from_row(row: Any) -> Transition:
    """A record from a row of ``transitions`` (``SELECT *``)."""
    return Transition(
        job_id=row["job_id"],
        from_state=None if row["from_state"] is None else JobState(row["from_state"]),
        to_state=JobState(row["to_state"]),
        at=row["at"],
        reason=row["reason"],
    )


def step_from_row(row: Any) -> StepRecord:
    """A record from a row of ``steps`` (``SELECT *``)."""
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
        summary=decode_json(row["summary"]),
    )


__all__ = [
    "JOB_COLUMNS",
    "JOB_COLUMNS_WITH_RESULT",
    "JobRecord",
    "StepRecord",
    "Transition",
    "decode_json",
    "encode_json",
    "job_from_row",
    "select_jobs",
    "step_from_row",
    "transition_from_row",
]
