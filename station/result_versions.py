"""Versions of a job's calibration result: the station's own, and later recalibrations.

Version 0 is the result the station computed when the job ran (``jobs.result``);
each ``lfcal recalibrate`` adds a row to ``results`` with the next version number,
the software version that computed it, the date and its source. Nothing is
overwritten, so results of different software versions stay side by side and can
be queried (``lfcal jobs JOB --results``, ``GET /api/v1/jobs/{id}/results``).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any

from station.db import UniqueViolation
from station.store import JobNotFound, JobStore


@dataclass(frozen=True)
class ResultVersion:
    """One version of a job's result.

    Attributes:
        job_id: the job.
        version: 0 for the station's own result, then 1, 2, ...
        software_version: the lfcal-station version that computed it.
        created_at: Unix time (s) it was stored.
        source: ``station`` (version 0) or ``recalibrate``.
        result: the result JSON (None unless asked for).
    """

    job_id: int
    version: int
    software_version: str
    created_at: float
    source: str
    result: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _software_of(result: dict[str, Any] | None) -> str:
    software = (result or {}).get("software") or {}
    return str(software.get("version") or "unknown")


def add_result_version(
    store: JobStore,
    job_id: int,
    result: dict[str, Any],
    *,
    software_version: str | None = None,
    source: str = "recalibrate",
) -> ResultVersion:
    """Store ``result`` as the job's next version (never replacing an earlier one)."""
    text = json.dumps(result, allow_nan=False, separators=(",", ":"))
    software = software_version or _software_of(result)
    for _attempt in range(3):  # two writers may pick the same number: try the next one
        now = time.time()
        try:
            with store.pool.write() as db:
                if db.execute("SELECT id FROM jobs WHERE id = ?", (job_id,)).fetchone() is None:
                    raise JobNotFound(job_id)
                row = db.execute(
                    "SELECT COALESCE(MAX(version), 0) AS v FROM results WHERE job_id = ?",
                    (job_id,),
                ).fetchone()
                version = int(row["v"]) + 1
                db.execute(
                    "INSERT INTO results (job_id, version, software_version, created_at, "
                    "source, result) VALUES (?, ?, ?, ?, ?, ?)",
                    (job_id, version, software, now, source, text),
                )
            return ResultVersion(job_id, version, software, now, source, result)
        except UniqueViolation:
            continue
    raise UniqueViolation(f"job {job_id}: could not number a new result version")


def result_versions(
    store: JobStore,
    job_id: int,
    *,
    with_results: bool = False,
    software_version: str | None = None,
) -> list[ResultVersion]:
    """Every version of the job's result, oldest first (optionally only those of
    ``software_version``)."""
    job = store.get_job(job_id, with_result=True)
    out: list[ResultVersion] = []
    if job.result is not None:
        out.append(
            ResultVersion(
                job_id,
                0,
                _software_of(job.result),
                job.updated_at,
                "station",
                job.result if with_results else None,
            )
        )
    columns = "job_id, version, software_version, created_at, source"
    if with_results:
        columns += ", result"
    with store.pool.read() as db:
        rows = db.execute(
            f"SELECT {columns} FROM results WHERE job_id = ? ORDER BY version", (job_id,)
        ).fetchall()
    for r in rows:
        out.append(
            ResultVersion(
                int(r["job_id"]),
                int(r["version"]),
                str(r["software_version"]),
                float(r["created_at"]),
                str(r["source"]),
                json.loads(r["result"]) if with_results else None,
            )
        )
    if software_version is not None:
        out = [v for v in out if v.software_version == software_version]
    return out


def latest_result(store: JobStore, job_id: int) -> ResultVersion | None:
    """The newest version of the job's result (with its JSON), or None."""
    versions = result_versions(store, job_id, with_results=True)
    return versions[-1] if versions else None


def jobs_with_software(store: JobStore, software_version: str) -> set[int]:
    """Jobs that already have a recalibrated result of ``software_version``."""
    with store.pool.read() as db:
        rows = db.execute(
            "SELECT DISTINCT job_id FROM results WHERE software_version = ?", (software_version,)
        ).fetchall()
    return {int(r["job_id"]) for r in rows}


__all__ = [
    "ResultVersion",
    "add_result_version",
    "jobs_with_software",
    "latest_result",
    "result_versions",
]
