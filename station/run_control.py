"""How a sweep run is steered and how it ends: the operator's requests, the outcome, the
step timings, and what the orchestrator hands the run (:class:`RunContext`).

:class:`station.runner.SweepRun` raises :class:`JobFailed` or :class:`StopRequested`
inside and returns an :class:`Outcome`; :class:`JobControl` carries pause, resume,
cancel and shut-down requests from any thread to the hardware worker, which honours
them at the next step boundary.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from station.analysis import AnalysisPool
from station.config import StationConfig
from station.events import JobEvent, LiveProgress
from station.store import JobState, JobStore

# --------------------------------------------------------------------------- outcomes


class JobFailed(Exception):
    """The job cannot go on. ``devices_broken``: close and reopen the devices before the next job."""

    def __init__(
        self, message: str, *, devices_broken: bool = False, result: dict[str, Any] | None = None
    ) -> None:
        self.message = message
        self.devices_broken = devices_broken
        self.result = result
        super().__init__(message)


class StopRequested(Exception):
    """Cancel, shut-down or a lost ownership reached a step boundary; ``error``: the
    reason is also the job's ``last_error`` (a fault, not an operator's request)."""

    def __init__(self, state: JobState, reason: str, *, error: bool = False) -> None:
        self.state = state
        self.reason = reason
        self.error = error
        super().__init__(reason)


@dataclass
class Outcome:
    """How a run ended: the state to store, why, and the result (if any)."""

    state: JobState
    reason: str
    last_error: str | None = None
    result: dict[str, Any] | None = None
    devices_broken: bool = False


@dataclass(frozen=True)
class StepTiming:
    """Wall times of one sweep step on the hardware thread (s).

    ``overhead_s`` is everything but the rail move (including the driver's wait
    for IDLE and read-back), the settle wait and the camera grab (exposure,
    transfer; in simulation the rendering): sanity check, hand-off to the
    writer (including back-pressure), bookkeeping.
    """

    index: int
    move_s: float
    settle_s: float
    grab_s: float
    total_s: float

    @property
    def overhead_s(self) -> float:
        return self.total_s - self.move_s - self.settle_s - self.grab_s


# --------------------------------------------------------------------------- control


class JobControl:
    """Pause / resume / cancel / shut-down requests for the active job (thread-safe)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.pause = False
        self.cancel = False
        self.shutdown = False
        self.cancel_reason = "cancelled by the operator"
        self.pause_reason = "paused by the operator"
        self.resume_reason = "resumed by the operator"

    def request_pause(self, reason: str) -> None:
        with self._cond:
            self.pause = True
            self.pause_reason = reason
            self._cond.notify_all()

    def request_resume(self, reason: str) -> None:
        with self._cond:
            self.pause = False
            self.resume_reason = reason
            self._cond.notify_all()

    def request_cancel(self, reason: str) -> None:
        with self._cond:
            self.cancel = True
            self.cancel_reason = reason
            self._cond.notify_all()

    def request_shutdown(self) -> None:
        with self._cond:
            self.shutdown = True
            self._cond.notify_all()

    def wait_paused(self) -> str:
        """Block while paused; return ``"resume"``, ``"cancel"`` or ``"shutdown"``."""
        with self._cond:
            while self.pause and not self.cancel and not self.shutdown:
                self._cond.wait()
            if self.shutdown:
                return "shutdown"
            return "cancel" if self.cancel else "resume"


@dataclass
class RunContext:
    """Everything a run needs from the orchestrator."""

    config: StationConfig
    store: JobStore
    pool: AnalysisPool | None
    publish: Callable[[JobEvent], None]
    transition: Callable[[int, JobState, str], None]
    progress: LiveProgress
    progress_lock: threading.Lock
    control: JobControl
    timings: list[StepTiming] = field(default_factory=list)
    principal_point_cache: dict[str, tuple[float, float]] = field(default_factory=dict)
    row_changed: Callable[[int], None] = lambda job_id: None
    """Called with the job's id after the run changed its row in the store without a
    transition (a recorded step moves ``updated_at``; see :mod:`station.job_cache`)."""
    ownership_problem: Callable[[], str | None] = lambda: None
    """Why the station no longer owns its jobs on a shared database (None: it does);
    checked at every step boundary (:mod:`station.ownership`)."""
