"""The recorded steps of the jobs (table ``steps``): one row per captured, written frame.

:class:`JobSteps` stores and reads them; :class:`station.store.JobStore` offers it as
:meth:`~station.store.JobStore.record_step`, :meth:`~station.store.JobStore.steps`
and the other step methods. A step index is recorded once per job
(:class:`station.store_errors.DuplicateStep` otherwise); recording a step also
moves its job's ``updated_at`` (Unix s), in the same transaction.
"""

from __future__ import annotations

import sqlite3
import time
from typing import Any

from station.db import ConnectionPool, UniqueViolation
from station.store_errors import DuplicateStep
from station.store_rows import StepRecord, encode_json, step_from_row


class JobSteps:
    """Recorded steps of the jobs in one database (see the module docstring).

    Args:
        pool: the job store's connection pool.
    """

    def __init__(self, pool: ConnectionPool) -> None:
        self._db = pool

    def record(self, step: StepRecord) -> None:
        """Store a written frame. :class:`DuplicateStep` if the index is already recorded."""
        with self._db.write() as db:
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
                        None if step.summary is None else encode_json(step.summary),
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

    def set_summary(self, job_id: int, index: int, summary: dict[str, Any]) -> None:
        """Attach the analysis summary (JSON object) to a recorded step."""
        with self._db.write() as db:
            db.execute(
                "UPDATE steps SET summary = ? WHERE job_id = ? AND idx = ?",
                (encode_json(summary), job_id, index),
            )

    def delete(self, job_id: int, indices: list[int]) -> None:
        """Forget recorded steps (their frames failed verification and will be re-captured)."""
        if not indices:
            return
        with self._db.write() as db:
            db.executemany(
                "DELETE FROM steps WHERE job_id = ? AND idx = ?", [(job_id, i) for i in indices]
            )

    def of_job(self, job_id: int, *, after: int | None = None) -> list[StepRecord]:
        """Recorded steps of the job in index order (only ``index > after`` if given)."""
        sql = "SELECT * FROM steps WHERE job_id = ?"
        args: list[Any] = [job_id]
        if after is not None:
            sql += " AND idx > ?"
            args.append(after)
        with self._db.read() as db:
            rows = db.execute(sql + " ORDER BY idx", args).fetchall()
        return [step_from_row(r) for r in rows]

    def get(self, job_id: int, index: int) -> StepRecord | None:
        """One recorded step, or None."""
        with self._db.read() as db:
            row = db.execute(
                "SELECT * FROM steps WHERE job_id = ? AND idx = ?", (job_id, index)
            ).fetchone()
        return None if row is None else step_from_row(row)

    def count(self, job_id: int) -> int:
        """Number of recorded steps of the job."""
        with self._db.read() as db:
            row = db.execute(
                "SELECT COUNT(*) AS n FROM steps WHERE job_id = ?", (job_id,)
            ).fetchone()
        return int(row["n"])


__all__ = ["JobSteps"]
