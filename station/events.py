"""Job events and live progress, observable from any thread (for the web layer).

Events (:class:`JobEvent`):

``step``
    a frame was written and recorded; ``id`` is the **step index** (the SSE
    event id, replayable from the job store after any restart). ``data``:
    index, commanded and actual rail position (mm), file, sha256,
    frames_done, frames_total, eta_s, and ``summary`` when the frame's analysis
    is already known (replays).
``analysis``
    a frame's analysis finished (``id`` None). ``data``: index, rail_mm,
    object_distance_mm, Q, Ls_px, Lr_px, La_mm (the focus curve La(u) point,
    None until both corners are measured), edge_width_px (blurred-step σ), edge_spread_px
    (RMS width of the frame's edge-spread function: what the defocus model fits), error.
``state``
    the job changed state (``id`` None). ``data``: state, from, reason, last_error.
``fault``
    a device fault the job recovered from (``id`` None). ``data``: what (where
    in the sweep), error (the device's message), action (retry, rehome,
    reconnect and why).
``phase``
    the job entered a phase of its run (``id`` None). ``data``: phase
    (``opening``, ``homing``, ``white``, ``aligning``, ``sweeping``,
    ``calibrating``), detail.

:class:`EventHub` fans events out to :class:`Subscription` objects (a bounded
queue each: a consumer that falls more than ``maxsize`` events behind gets
``overflowed`` set and should replay from the store) and to callbacks (called
in the publishing thread; they must not block -- for asyncio use
``loop.call_soon_threadsafe``).
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from calibration.pipeline import FrameSummary
from station.store import StepRecord


@dataclass(frozen=True)
class JobEvent:
    """One event of one job.

    Attributes:
        job_id: the job.
        type: ``"step"``, ``"analysis"``, ``"state"``, ``"fault"`` or ``"phase"``.
        id: the step index for ``step`` events (SSE event id), else None.
        data: JSON-ready payload (see the module docstring).
        at: Unix time (s) of the event.
    """

    job_id: int
    type: str
    id: int | None
    data: dict[str, Any]
    at: float = field(default_factory=time.time)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "job_id": self.job_id,
            "type": self.type,
            "id": self.id,
            "at": self.at,
            "data": self.data,
        }


def la_mm(summary: FrameSummary, reference_gap_mm: float) -> float | None:
    """La = Lp·Ls with Lp = Cr/(Lr − Ls) (mm; OPTICS.md §3), None when not measurable."""
    ls, lr = summary.Ls_px, summary.Lr_px
    if not (math.isfinite(ls) and math.isfinite(lr)) or lr - ls <= 0:
        return None
    return reference_gap_mm / (lr - ls) * ls


def _num(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def analysis_payload(summary: FrameSummary, reference_gap_mm: float) -> dict[str, Any]:
    """The ``analysis`` event data of a frame summary (JSON-ready)."""
    return {
        "index": summary.index,
        "rail_mm": _num(summary.rail_mm),
        "object_distance_mm": _num(summary.object_distance_mm),
        "Q": _num(summary.Q),
        "Ls_px": _num(summary.Ls_px),
        "Lr_px": _num(summary.Lr_px),
        "La_mm": la_mm(summary, reference_gap_mm),
        "edge_width_px": _num(summary.edge_width_px),
        "edge_spread_px": _num(summary.edge_spread_px),
        "error": summary.error or None,
    }


def step_data(step: StepRecord, frames_done: int, frames_total: int) -> dict[str, Any]:
    """The data of a ``step`` event: the recorded step (rail positions in mm, the frame's
    file and SHA-256) and the job's frame count so far."""
    return {
        "index": step.index,
        "commanded_mm": step.commanded_mm,
        "actual_mm": step.actual_mm,
        "file": step.file,
        "sha256": step.sha256,
        "frames_done": frames_done,
        "frames_total": frames_total,
    }


class Subscription:
    """Events of one job (or of all jobs) in publication order; see :meth:`EventHub.subscribe`."""

    def __init__(self, hub: EventHub, job_id: int | None, maxsize: int) -> None:
        self._hub = hub
        self.job_id = job_id
        self._queue: queue.Queue[JobEvent] = queue.Queue(maxsize)
        self.overflowed = False

    def _offer(self, event: JobEvent) -> None:
        if self.job_id is not None and event.job_id != self.job_id:
            return
        try:
            self._queue.put_nowait(event)
        except queue.Full:
            self.overflowed = True

    def get(self, timeout_s: float | None = None) -> JobEvent | None:
        """The next event, waiting up to ``timeout_s`` seconds (None: forever); None on timeout."""
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def drain(self) -> list[JobEvent]:
        """Every event already queued, without waiting."""
        out: list[JobEvent] = []
        while True:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        """Stop receiving events."""
        self._hub._remove(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventHub:
    """Publishes job events to subscriptions and callbacks (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subs: list[Subscription] = []
        self._callbacks: list[Callable[[JobEvent], None]] = []

    def subscribe(self, job_id: int | None = None, *, maxsize: int = 10000) -> Subscription:
        """A new subscription to the events of ``job_id`` (None: every job)."""
        sub = Subscription(self, job_id, maxsize)
        with self._lock:
            self._subs.append(sub)
        return sub

    def add_callback(self, callback: Callable[[JobEvent], None]) -> None:
        """Call ``callback(event)`` for every event (in the publishing thread)."""
        with self._lock:
            self._callbacks.append(callback)

    def remove_callback(self, callback: Callable[[JobEvent], None]) -> None:
        """Stop calling ``callback``."""
        with self._lock:
            if callback in self._callbacks:
                self._callbacks.remove(callback)

    def _remove(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def publish(self, event: JobEvent) -> None:
        """Deliver ``event`` to every subscriber; callback errors are ignored."""
        with self._lock:
            subs = list(self._subs)
            callbacks = list(self._callbacks)
        for sub in subs:
            sub._offer(event)
        for callback in callbacks:
            try:
                callback(event)
            except Exception:  # noqa: BLE001 - a listener must not break the sweep
                pass


# --------------------------------------------------------------------------- progress


@dataclass
class LiveProgress:
    """What the hardware worker is doing for the active job (guarded by the orchestrator).

    Attributes:
        job_id: the active job.
        phase: current phase (see the module docstring).
        frames_done: frames written and recorded.
        frames_total: frames of the sweep.
        frames_analysed: frames whose analysis finished.
        rail_mm: last read-back rail position (mm), None before the first.
        step_durations_s: wall time of the recent steps (s), for the ETA.
        pause_requested, cancel_requested: a request waiting for the next step boundary.
        last_error: the latest retried (recovered) fault, for the operator.
        started_at: Unix time (s) the run started.
    """

    job_id: int
    phase: str = "starting"
    frames_done: int = 0
    frames_total: int = 0
    frames_analysed: int = 0
    rail_mm: float | None = None
    step_durations_s: list[float] = field(default_factory=list)
    pause_requested: bool = False
    cancel_requested: bool = False
    last_error: str | None = None
    started_at: float = field(default_factory=time.time)

    def eta_s(self) -> float | None:
        """Seconds until the last frame (median of the recent steps), None if unknown."""
        left = self.frames_total - self.frames_done
        if left <= 0:
            return 0.0
        recent = sorted(self.step_durations_s[-20:])
        if not recent:
            return None
        return left * recent[len(recent) // 2]


__all__ = [
    "EventHub",
    "JobEvent",
    "LiveProgress",
    "Subscription",
    "analysis_payload",
    "la_mm",
]
