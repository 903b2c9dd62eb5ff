"""What a sweep run honours around every device action, on the hardware worker thread.

:class:`RunGuard` is the run's control and fault side (:class:`station.runner.SweepRun`
does the phases and asks it):

- **step boundaries** (:meth:`RunGuard.boundary`): shut-down, cancel, the archive
  writer's health, the station's ownership of its jobs, pause (the run waits in
  ``paused``, then checks the devices' references again);
- **the fault policy** (:meth:`RunGuard.with_policy`): a device action that raises a
  :class:`drivers.errors.DeviceError` is retried, re-homed or reconnected as
  :mod:`station.faults` says, at most :data:`MAX_RECOVERED_FAULTS` times a run, each
  recovery announced as a ``fault`` event; otherwise the run fails with
  :class:`~station.run_control.JobFailed` naming what it was doing;
- **winding down** (:meth:`RunGuard.wind_down`): after a stop or failure, write what
  was grabbed, cancel the analysis, stop the rail.

It holds the run's archive writer thread (:attr:`RunGuard.sink`) and streaming
analysis (:attr:`RunGuard.session`) once :class:`station.frame_pipeline.FramePipeline`
has started them, because these are what it checks, drains and stops.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from calibration.archive import DiskFull
from drivers.errors import ConnectionLost, DeviceError, PortUnavailable
from station.analysis import AnalysisSession
from station.events import JobEvent
from station.faults import Action, check_frame, rule_for
from station.run_control import JobFailed, RunContext, StopRequested
from station.store import JobState, StoreUnavailable
from station.writer import FrameWriter

T = TypeVar("T")

MAX_RECOVERED_FAULTS = 25
"""A job that needed more recoveries than this fails (something is persistently wrong)."""


class RunGuard:
    """Step boundaries, the fault policy and winding down of one run (see the module docstring).

    Args:
        job_id: the running job.
        devices: ``station.devices.StationDevices`` (camera, rail, xy).
        ctx: orchestrator services.
        job_dir: the job's archive directory (named in storage errors).

    Attributes:
        sink: the archive writer thread, None until the white phase starts it (and
            again once the run closed it at its end).
        session: the streaming analysis, None unless the job calibrates.
        recovered_faults: device faults recovered from in this run so far.
    """

    def __init__(self, job_id: int, devices: Any, ctx: RunContext, job_dir: Path) -> None:
        self.job_id = job_id
        self.dev = devices
        self.ctx = ctx
        self.cfg = ctx.config
        self.job_dir = job_dir
        self.sink: FrameWriter | None = None
        self.session: AnalysisSession | None = None
        self.recovered_faults = 0

    def announce_phase(self, phase: str, detail: str = "") -> None:
        """Set the live progress's phase and publish a ``phase`` event."""
        with self.ctx.progress_lock:
            self.ctx.progress.phase = phase
        self.ctx.publish(JobEvent(self.job_id, "phase", None, {"phase": phase, "detail": detail}))

    # ------------------------------------------------------------------ step boundaries

    def boundary(self) -> bool:
        """A step boundary: honour cancel / shut-down / pause, and the writer's health.

        Returns True if the job was paused (and resumed) here: the caller puts the
        XY stage back where its next action needs it.
        """
        control = self.ctx.control
        if control.shutdown:
            raise StopRequested(JobState.INTERRUPTED, "station shut down while the job was running")
        if control.cancel:
            raise StopRequested(JobState.CANCELLED, control.cancel_reason)
        if self.sink is not None:
            self.check_sink()
        lost = self.ctx.ownership_problem()
        if lost is not None:  # another process may now recover and resume this very job
            raise StopRequested(
                JobState.INTERRUPTED,
                f"{lost}; the sweep stopped so that two processes never write one job "
                "(resume it once the station has its lock back)",
                error=True,
            )
        if control.pause:
            self._pause()
            return True
        return False

    def check_sink(self) -> None:
        """Raise the writer thread's error (as :meth:`storage_failure`) if it stopped."""
        assert self.sink is not None
        error = self.sink.error
        if error is not None:
            raise self.storage_failure(error)

    def storage_failure(self, error: BaseException) -> JobFailed:
        """The failure for an error writing the archive or recording a step."""
        if isinstance(error, StoreUnavailable):
            return JobFailed(f"a written frame cannot be recorded in the job store: {error}")
        if isinstance(error, DiskFull):
            return JobFailed(f"disk full, nothing written past the last frame: {error}")
        return JobFailed(f"cannot write the archive {self.job_dir}: {error}")

    def _pause(self) -> None:
        control = self.ctx.control
        if self.sink is not None:
            self.sink.drain()
            self.check_sink()
        self.make_safe()
        with self.ctx.progress_lock:
            self.ctx.progress.pause_requested = False
            self.ctx.progress.phase = "paused"
        self.ctx.transition(self.job_id, JobState.PAUSED, control.pause_reason)
        answer = control.wait_paused()
        if answer == "shutdown":
            raise StopRequested(JobState.INTERRUPTED, "station shut down while the job was paused")
        if answer == "cancel":
            raise StopRequested(JobState.CANCELLED, control.cancel_reason)
        self.ctx.transition(self.job_id, JobState.RUNNING, control.resume_reason)
        # the devices may have been touched while paused: check the references again
        self.home_if_needed()

    def home_if_needed(self) -> None:
        """Home the rail and the XY stage if they have no reference."""
        rail, xy = self.dev.rail, self.dev.xy
        if not self.with_policy("reading the rail's reference", rail.is_homed):
            self.announce_phase("homing", "rail")
            self.with_policy("homing the rail", rail.home)
        if not self.with_policy("reading the XY stage's reference", xy.is_homed):
            self.announce_phase("homing", "xy stage")
            self.with_policy("homing the XY stage", xy.home)

    # ------------------------------------------------------------------ winding down

    def make_safe(self) -> None:
        """Stop the rail (decelerated); errors are ignored (best effort)."""
        try:
            self.dev.rail.stop()
        except (DeviceError, OSError):
            pass

    def wind_down(self) -> None:
        """After a stop or failure: write every frame already grabbed, stop the rail."""
        if self.sink is not None:
            try:
                self.sink.close()
            except Exception:  # noqa: BLE001 - already failing; the error is in the outcome
                pass
        if self.session is not None:
            self.session.cancel()
        self.make_safe()

    # ------------------------------------------------------------------ the fault policy

    def note_fault(self, what: str, exc: BaseException, action: str) -> None:
        """Count a recovered fault, show it (``last_error``, ``fault`` event); fail past the cap."""
        self.recovered_faults += 1
        text = f"{what}: {exc} -- {action}"
        with self.ctx.progress_lock:
            self.ctx.progress.last_error = text
        self.ctx.publish(
            JobEvent(
                self.job_id, "fault", None, {"what": what, "error": str(exc), "action": action}
            )
        )
        if self.recovered_faults > MAX_RECOVERED_FAULTS:
            raise JobFailed(
                f"{what}: more than {MAX_RECOVERED_FAULTS} device faults in this run, the last: "
                f"{exc}"
            )

    def with_policy(
        self,
        what: str,
        op: Callable[[], T],
        *,
        rehome: Callable[[], None] | None = None,
    ) -> T:
        """Run ``op``; on a device error follow :mod:`station.faults` (bounded).

        ``what`` says what the run was doing (it starts the failure message);
        ``rehome`` is the recovery for a rule that re-homes (without it such a fault
        fails the run).
        """
        used: dict[int, int] = {}
        while True:
            try:
                return op()
            except DeviceError as exc:
                rule = rule_for(exc)
                key = id(rule)
                n = used.get(key, 0)
                broken = isinstance(exc, PortUnavailable | ConnectionLost)
                if rule.action is Action.FAIL or n >= rule.extra_attempts:
                    tries = f" (after {n + 1} attempts)" if n else ""
                    raise JobFailed(f"{what}: {exc}{tries}", devices_broken=broken) from exc
                if rule.action is Action.REHOME and rehome is None:
                    raise JobFailed(f"{what}: {exc}") from exc
                used[key] = n + 1
                self.note_fault(what, exc, f"{rule.action.value} ({rule.why})")
                if rule.delay_s:
                    threading.Event().wait(rule.delay_s)
                try:
                    if rule.action is Action.REHOME:
                        assert rehome is not None
                        rehome()
                    elif rule.action is Action.RECONNECT:
                        self.dev.camera.reconnect(timeout_s=max(self.cfg.camera.timeout_s, 5.0))
                except DeviceError as again:
                    raise JobFailed(
                        f"{what}: {exc}; recovery ({rule.action.value}) failed: {again}",
                        # a camera that cannot be reopened: reopen everything for the next job
                        devices_broken=isinstance(again, PortUnavailable)
                        or rule.action is Action.RECONNECT,
                    ) from again

    def grab(self, what: str, timer: list[float] | None = None, *, where: str = "") -> Any:
        """Grab a frame under the fault policy; a blank or saturated frame is a fault too.

        ``what`` names the frame in :func:`station.faults.check_frame`'s message,
        ``where`` (default ``what``) starts the failure message; the camera's time
        (s) is added to ``timer[0]``.
        """
        timeout = self.cfg.camera.timeout_s

        def once() -> Any:
            t = time.perf_counter()
            frame = self.dev.camera.grab(timeout_s=timeout)
            if timer is not None:
                timer[0] += time.perf_counter() - t
            check_frame(frame.pixels, frame.bit_depth, what=what)
            return frame

        return self.with_policy(f"{where or what}: grabbing", once)


__all__ = ["MAX_RECOVERED_FAULTS", "RunGuard"]
