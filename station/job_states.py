"""The states of a job and the life cycle that links them.

Job life cycle (:data:`ALLOWED_TRANSITIONS`)::

    queued ──> running <──> paused
      │          │            │
      │          ├──> succeeded | failed | cancelled | interrupted
      │          │
      └──> cancelled          interrupted | failed ──(resume)──> queued

``interrupted`` is what a job found ``running`` or ``paused`` at start-up
becomes (the process died under it); ``resume`` re-queues an interrupted or
failed job, which then continues from its first missing step. A change the
table does not allow raises :class:`station.store_errors.InvalidTransition`
(the web layer answers 409) and changes nothing
(:class:`station.job_transitions.JobTransitions` stores the allowed ones).
"""

from __future__ import annotations

from enum import StrEnum


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
"""Which state may follow which (anything else raises
:class:`station.store_errors.InvalidTransition`)."""

TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.CANCELLED})
"""States a job never leaves."""

ACTIVE_STATES = frozenset({JobState.RUNNING, JobState.PAUSED})
"""States in which the hardware worker holds the job."""


__all__ = ["ACTIVE_STATES", "ALLOWED_TRANSITIONS", "TERMINAL_STATES", "JobState"]
