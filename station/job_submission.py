"""New jobs: the ``jobs`` row of a submitted sweep, its archive's place, its idempotency key.

:func:`store_new_job` stores a new ``queued`` job of a station, with its first
transition, in one transaction. Its archive directory is
``archive_root/job-000123-20250101T120000`` (the id, then the UTC time of the
submission), and with object storage its URL ``archive_url/STATION/job-000123-...``.
A client's idempotency key makes a submission repeatable: the same request with a
key already used returns the existing job; a different request (or another
station's job) with that key raises :class:`station.store_errors.IdempotencyConflict`.
:class:`station.store.JobStore` offers it as :meth:`~station.store.JobStore.create_job`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from station.db import ConnectionPool
from station.job_states import JobState
from station.job_transitions import JobTransitions
from station.store_errors import IdempotencyConflict
from station.store_rows import JOB_COLUMNS, JobRecord, decode_json, encode_json, job_from_row


def store_new_job(
    pool: ConnectionPool,
    request: Mapping[str, Any],
    *,
    station_id: str,
    archive_url: str | None,
    archive_root: str | Path,
    frames_total: int,
    idempotency_key: str | None = None,
    reason: str = "submitted",
    camera_serial: str | None = None,
) -> tuple[JobRecord, bool]:
    """Store a new queued job of ``station_id`` through ``pool``; return ``(job, created)``.

    ``archive_url`` is the station's object-storage prefix (without a trailing
    ``/``), or None; the other arguments are those of
    :meth:`station.store.JobStore.create_job`.
    """
    req_text = encode_json(dict(request))
    now = time.time()
    with pool.write() as db:
        if idempotency_key is not None:
            row = db.execute(
                f"SELECT {JOB_COLUMNS} FROM jobs WHERE idempotency_key = ?",
                (idempotency_key,),
            ).fetchone()
            if row is not None:
                if (
                    decode_json(row["request"]) != json.loads(req_text)
                    or row["station_id"] != station_id
                ):
                    raise IdempotencyConflict(idempotency_key, row["id"])
                return job_from_row(row), False
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
                station_id,
                camera_serial,
            ),
        )
        job_id = int(cur.fetchone()["id"])
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(now))
        name = f"job-{job_id:06d}-{stamp}"
        archive = Path(archive_root) / name
        url = None if archive_url is None else f"{archive_url}/{station_id}/{name}"
        db.execute(
            "UPDATE jobs SET archive_dir = ?, archive_url = ? WHERE id = ?",
            (str(archive), url, job_id),
        )
        JobTransitions.record_submitted(db, job_id, now, reason)
        row = db.execute(f"SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
    return job_from_row(row), True


__all__ = ["store_new_job"]
