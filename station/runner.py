"""One run of one sweep job on the hardware worker thread.

:class:`SweepRun` does, in order (each phase is announced as a ``phase`` event):

1. **prepare** -- check the request against the devices (rail travel, camera
   exposure range), configure the camera, open the job's ``lfcal-sweep/1``
   archive (new, or resumed after :func:`station.recovery.reconcile` verified
   what is on disk), home the rail and the XY stage if they have no reference;
2. **white** -- unless the archive already holds a verified white image: move
   the XY stage to the white position and grab the flat field (or copy the
   white image of an earlier job), then fit the MLA grid on it and start the
   streaming analysis;
3. **align** -- move the XY stage to the alignment position;
4. **sweep** -- for every rail position not yet recorded, in index order:
   move (the driver waits for IDLE and reads the position back), settle, grab,
   sanity-check, and hand the frame to the :class:`station.writer.FrameWriter`
   thread, which writes it atomically, records the step and submits it for
   analysis while the rail already moves on. Pause, cancel and shut-down
   requests are honoured here, between steps;
5. **calibrate** -- wait for the writer and the analysis, combine the frame
   summaries into the calibration result (in an analysis worker process).

Device errors go through :mod:`station.faults`: bounded retries where safe,
otherwise :class:`~station.run_control.JobFailed` with the device's own message plus where in the
sweep it happened. The run never changes the job's final state itself; it
returns an :class:`~station.run_control.Outcome` and the orchestrator stores it.

The phases are here; :class:`SweepRun` composes the pieces that do one job each:

- :class:`station.run_guard.RunGuard` -- step boundaries (pause, cancel, shut-down,
  the writer's health, ownership), the fault policy around every device action,
  homing, winding down after a stop or failure;
- :func:`station.run_archive.open_job_archive` -- the archive, resumed or new
  (with :func:`principal_point_px` and :func:`camera_settings`, importable from here);
- :class:`station.frame_pipeline.FramePipeline` -- the white image, the MLA grid
  fit, the streaming analysis and the writer thread, and their callbacks.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path
from typing import Any

from calibration.archive import SweepWriter, atomic_write_bytes
from calibration.pipeline import CalibrationError
from drivers.camera import CameraSettings, Roi, bit_depth
from drivers.errors import DeviceError
from station.frame_pipeline import FramePipeline
from station.recovery import VerifyReport
from station.run_archive import camera_settings, open_job_archive, principal_point_px
from station.run_control import JobFailed, Outcome, RunContext, StepTiming, StopRequested
from station.run_guard import MAX_RECOVERED_FAULTS, RunGuard
from station.store import JobRecord, JobState, StoreUnavailable
from station.sweep import RequestInvalid, SweepPlan, SweepRequest, plan_sweep
from station.writer import CapturedFrame

RESULT_NAME = "result.json"
"""The calibration result, written next to ``sweep.json`` in the job directory."""


class SweepRun:
    """Runs one job on already opened devices (see the module docstring).

    Args:
        job: the job (state ``running``).
        devices: ``station.devices.StationDevices`` (camera, rail, xy).
        ctx: orchestrator services.
    """

    def __init__(self, job: JobRecord, devices: Any, ctx: RunContext) -> None:
        self.job = job
        self.plan = SweepPlan.from_dict(job.request)
        self.dev = devices
        self.ctx = ctx
        self.cfg = ctx.config
        self.job_dir = Path(job.archive_dir)
        self.guard = RunGuard(job.id, devices, ctx, self.job_dir)
        self.frames = FramePipeline(job.id, self.job_dir, self.plan, devices, ctx, self.guard)
        self.writer: SweepWriter | None = None
        self.report: VerifyReport | None = None
        self.settings: CameraSettings | None = None

    # ------------------------------------------------------------------ entry

    def execute(self) -> Outcome:
        """Run the job to its end; never raises (programming errors become a failed job)."""
        try:
            self._prepare()
            self._white()
            self._align()
            self._sweep()
            return self._finish()
        except StopRequested as stop:
            self.guard.wind_down()
            reason = self._with_count(stop.reason)
            return Outcome(stop.state, reason, last_error=reason if stop.error else None)
        except JobFailed as exc:
            self.guard.wind_down()
            message = self._with_count(exc.message)
            return Outcome(
                JobState.FAILED,
                message,
                last_error=message,
                result=exc.result,
                devices_broken=exc.devices_broken,
            )
        except StoreUnavailable as exc:  # e.g. a pause the store could not record
            self.guard.wind_down()
            message = self._with_count(f"the job store cannot be written: {exc}")
            return Outcome(JobState.FAILED, message, last_error=message)
        except Exception as exc:  # noqa: BLE001 - the job must end in a truthful state
            self.guard.wind_down()
            message = self._with_count(f"internal error: {type(exc).__name__}: {exc}")
            return Outcome(JobState.FAILED, message, last_error=message)

    def _with_count(self, message: str) -> str:
        """``message`` plus how many of the sweep's frames the store holds (if it answers)."""
        try:
            kept = self.ctx.store.step_count(self.job.id)
        except Exception:  # noqa: BLE001
            return message
        return f"{message} ({kept} of {self.plan.frames} frames kept)"

    # ------------------------------------------------------------------ 1. prepare

    def _prepare(self) -> None:
        self.guard.announce_phase("preparing")
        if self.plan.calibrate and self.ctx.pool is not None:
            self.ctx.pool.start()  # the workers import the calibration core meanwhile
        try:
            rail_limits = self.dev.rail.limits_mm()
            exposure_limits = self.dev.camera.exposure_limits_us()
        except DeviceError as exc:
            raise JobFailed(f"cannot read the device limits: {exc}") from exc
        try:
            plan_sweep(
                SweepRequest(
                    start_mm=self.plan.start_mm,
                    stop_mm=self.plan.stop_mm,
                    step_mm=self.plan.step_mm,
                    exposure_us=self.plan.exposure_us,
                    settle_s=self.plan.settle_s,
                ),
                self.cfg,
                rail_limits_mm=(rail_limits.min_mm, rail_limits.max_mm),
                exposure_limits_us=exposure_limits,
            )
        except RequestInvalid as exc:
            raise JobFailed(f"the request does not fit the devices: {exc}") from exc
        wanted = camera_settings(self.cfg, self.plan.exposure_us)
        settings = self.guard.with_policy(
            "configuring the camera", lambda: self.dev.camera.configure(wanted)
        )
        info = self.guard.with_policy("reading the camera's identity", self.dev.camera.info)
        roi = settings.roi or Roi(info.sensor_width, info.sensor_height)
        depth = bit_depth(settings.pixel_format)
        self.settings = settings
        self.writer, self.report = open_job_archive(
            self.job, self.plan, self.dev, self.ctx, settings, roi, depth
        )
        self.guard.home_if_needed()

    # ------------------------------------------------------------------ 2. white

    def _white(self) -> None:
        self.guard.boundary()
        assert self.writer is not None and self.report is not None
        self.frames.start(self.writer, self.report)

    # ------------------------------------------------------------------ 3. align

    def _align(self) -> None:
        pos = self.cfg.xy_stage.alignment
        self.guard.announce_phase("aligning", f"XY stage to ({pos.x_mm:g}, {pos.y_mm:g}) mm")
        self.guard.with_policy(
            "moving the XY stage to the alignment position",
            lambda: self.dev.xy.move_xy_mm(pos.x_mm, pos.y_mm),
            rehome=self.dev.xy.home,
        )

    # ------------------------------------------------------------------ 4. sweep

    def _sweep(self) -> None:
        sink = self.guard.sink
        assert sink is not None
        positions = self.plan.positions_mm()
        done = {s.index for s in self.ctx.store.steps(self.job.id)}
        todo = [i for i in range(self.plan.frames) if i not in done]
        self.guard.announce_phase(
            "sweeping", f"{len(todo)} of {self.plan.frames} frames to capture"
        )
        for index in todo:
            t0 = time.perf_counter()
            if self.guard.boundary():
                self._align()
                self.guard.announce_phase("sweeping", "resumed")
                t0 = time.perf_counter()
            frame, move_s, settle_s, grab_s = self._capture(index, positions[index])
            try:
                sink.put(frame)
            except OSError as exc:
                raise self.guard.storage_failure(exc) from exc
            total = time.perf_counter() - t0
            timing = StepTiming(index, move_s, settle_s, grab_s, total)
            self.ctx.timings.append(timing)
            with self.ctx.progress_lock:
                self.ctx.progress.step_durations_s.append(total)

    def _capture(self, index: int, target: float) -> tuple[CapturedFrame, float, float, float]:
        """Move the rail to ``target`` (mm), settle, grab: the frame and the three times (s)."""
        where = f"step {index} (rail {target:.3f} mm)"
        started = time.time()
        t0 = time.perf_counter()
        actual = self.guard.with_policy(
            f"{where}: moving the rail",
            lambda: self.dev.rail.move_abs_mm(target),
            rehome=self._rehome_rail,
        )
        t1 = time.perf_counter()
        with self.ctx.progress_lock:
            self.ctx.progress.rail_mm = actual
        if self.plan.settle_s > 0:
            threading.Event().wait(self.plan.settle_s)
        t2 = time.perf_counter()
        grab_s = [0.0]
        frame = self.guard.grab(f"frame {index} at {actual:.3f} mm", grab_s, where=where)
        captured = CapturedFrame(
            index=index,
            commanded_mm=target,
            actual_mm=float(actual),
            pixels=frame.pixels,
            started_at=started,
            captured_at=frame.host_timestamp_ns / 1e9 if frame.host_timestamp_ns else time.time(),
            extra={
                "frame_id": int(frame.frame_id),
                # what the camera applied for this frame: exposure, gain (+ its feature),
                # black level, DeviceTemperature, trigger, flat-field state
                **{
                    k: v
                    for k, v in frame.metadata().items()
                    if k not in ("pixel_format", "bit_depth")
                },
            },
        )
        return captured, t1 - t0, t2 - t1, grab_s[0]

    def _rehome_rail(self) -> None:
        self.guard.announce_phase("homing", "rail lost its reference")
        self.dev.rail.home()
        self.guard.announce_phase("sweeping", "rail homed again")

    # ------------------------------------------------------------------ 5. finish

    def _finish(self) -> Outcome:
        sink = self.guard.sink
        assert sink is not None
        sink.close()
        self.guard.check_sink()
        self.guard.sink = None
        control = self.ctx.control
        if control.cancel:
            raise StopRequested(JobState.CANCELLED, control.cancel_reason)
        recorded = {s.index for s in self.ctx.store.steps(self.job.id)}
        missing = sorted(set(range(self.plan.frames)) - recorded)
        if missing:
            raise JobFailed(f"frames {missing[:10]} were not recorded")
        session = self.guard.session
        if not self.plan.calibrate or session is None:
            return Outcome(JobState.SUCCEEDED, "all frames captured (calibration not requested)")
        self.guard.announce_phase("calibrating", f"{self.plan.frames} frames")
        summaries = session.wait(timeout_s=600.0)
        assert self.frames.geometry is not None
        try:
            result = session.combine(
                [summaries[i] for i in sorted(summaries) if i in recorded], self.frames.geometry
            )
        except CalibrationError as exc:
            partial = exc.partial
            if partial is not None:
                partial = dict(partial, error=str(exc))
                self._save_result(partial)
            raise JobFailed(f"calibration failed: {exc}", result=partial) from exc
        result["station"] = {
            "job_id": self.job.id,
            "archive_dir": str(self.job_dir),
            "frames": self.plan.frames,
        }
        self._save_result(result)
        a, b = result.get("a_mm"), result.get("b_mm")
        focus = (result.get("focus") or {}).get("object_distance_mm")
        text = "calibrated"
        if all(isinstance(v, float) and math.isfinite(v) for v in (a, b, focus)):
            text = f"calibrated: a = {a:.4f} mm, b = {b:.4f} mm, focus plane u = {focus:.2f} mm"
        return Outcome(JobState.SUCCEEDED, text, result=result)

    def _save_result(self, result: dict[str, Any]) -> None:
        """Write ``result`` to :data:`RESULT_NAME` in the job directory (best effort)."""
        try:
            data = (json.dumps(result, indent=1, allow_nan=False) + "\n").encode("utf-8")
            atomic_write_bytes(self.job_dir / RESULT_NAME, data)
        except (OSError, ValueError):
            pass  # the result is in the job store anyway


__all__ = [
    "MAX_RECOVERED_FAULTS",
    "RESULT_NAME",
    "SweepRun",
    "camera_settings",
    "principal_point_px",
]
