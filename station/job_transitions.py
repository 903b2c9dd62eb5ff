"""The jobs' state changes: checked against the life cycle and stored with their history.

:class:`JobTransitions` moves a job from one state to another only along
:data:`station.job_states.ALLOWED_TRANSITIONS`, and stores every change (table
``transitions``: job, from, to, time, reason) in the same transaction as the new
state; a change the table does not allow raises
:class:`station.store_errors.InvalidTransition` and changes nothing.
:class:`station.store.JobStore` offers it as :meth:`~station.store.JobStore.transition`
and :meth:`~station.store.JobStore.transitions`. Times are Unix epoch seconds (float).
"""

from __future__ import annotations

import time
from typing import Any

from station.db import ConnectionPool
from station.job_states import ALLOWED_TRANSITIONS, JobState
from station.store_errors import InvalidTransition, JobNotFound
from station.store_rows import (
    JOB_COLUMNS,
    JobRecord,
    Transition,
    encode_json,
    job_from_row,
    transition_from_row,
)


class JobTransitions:
    """State changes of the jobs in one database (see the module docstring).

    Args:
        pool: the job store's connection pool.
    """

    def __init__(self, pool: ConnectionPool) -> None:
        self._db = pool

    def change(
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
        """Change the state of a job and store the change with its time and reason
        (:meth:`station.store.JobStore.transition` documents the arguments)."""
        now = time.time()
        result_json = None if result is None else encode_json(result)  # before the write lock
        with self._db.write() as db:
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
            new = db.execute(f"SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return job_from_row(new)

    @staticmethod
    def record_submitted(db: Any, job_id: int, at: float, reason: str) -> None:
        """Store a new job's first change (none -> ``queued`` at ``at``, Unix s) on the
        connection ``db`` of the transaction that creates the job."""
        db.execute(
            "INSERT INTO transitions (job_id, from_state, to_state, at, reason) "
            "VALUES (?, NULL, ?, ?, ?)",
            (job_id, JobState.QUEUED.value, at, reason),
        )

    def history(self, job_id: int) -> list[Transition]:
        """Every state change of the job, oldest first."""
        with self._db.read() as db:
            rows = db.execute(
                "SELECT * FROM transitions WHERE job_id = ? ORDER BY seq", (job_id,)
            ).fetchall()
        return [transition_from_row(r) for r in rows]


__all__ = ["JobTransitions"]
