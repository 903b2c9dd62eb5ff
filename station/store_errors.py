"""The job store's own errors (the database's are in :mod:`station.db`).

All derive from :class:`station.db.StoreError`; the web layer maps
:class:`JobNotFound` to 404, :class:`InvalidTransition` and
:class:`IdempotencyConflict` to 409.
"""

from __future__ import annotations

from station.db import StoreError
from station.job_states import ALLOWED_TRANSITIONS, JobState


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


__all__ = ["DuplicateStep", "IdempotencyConflict", "InvalidTransition", "JobNotFound"]
