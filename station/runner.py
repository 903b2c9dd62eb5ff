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
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from calibration.archive import (
    ArchiveError,
    DiskFull,
    SweepArchive,
    SweepWriter,
    atomic_write_bytes,
)
from calibration.pipeline import (
    CalibrationError,
    SweepGeometry,
)
from drivers.camera import CameraSettings, Roi, bit_depth
from drivers.errors import ConnectionLost, DeviceError, PortUnavailable
from station.analysis import AnalysisSession, summary_from_dict
from station.config import StationConfig
from station.events import JobEvent, analysis_payload, step_data
from station.faults import Action, check_frame, rule_for
from station.recovery import VerifyReport, reconcile
from station.run_control import JobFailed, Outcome, RunContext, StepTiming, StopRequested
from station.store import JobRecord, JobState, StepRecord, StoreUnavailable
from station.sweep import RequestInvalid, SweepPlan, SweepRequest, plan_sweep
from station.writer import CapturedFrame, FrameWriter

T = TypeVar("T")

MAX_RECOVERED_FAULTS = 25
"""A job that needed more recoveries than this fails (something is persistently wrong)."""

RESULT_NAME = "result.json"
"""The calibration result, written next to ``sweep.json`` in the job directory."""


# --------------------------------------------------------------------------- geometry


def principal_point_px(
    config: StationConfig, roi: Roi | None, camera_pp: tuple[float, float] | None = None
) -> tuple[float, float]:
    """Principal point (px) in the coordinates of the delivered frames.

    From ``camera.principal_point_px`` if configured, else the camera's own
    (``camera_pp``: :attr:`drivers.camera.CameraInfo.principal_point_px`, known to a
    simulated camera), else the sensor centre; minus the ROI offset.
    """
    cam = config.camera
    pp = cam.principal_point_px if cam.principal_point_px is not None else camera_pp
    if pp is None:
        w, h = cam.sensor_size_px
        pp = ((w - 1) / 2.0, (h - 1) / 2.0)
    ox, oy = (roi.offset_x, roi.offset_y) if roi is not None else (0, 0)
    return (float(pp[0]) - ox, float(pp[1]) - oy)


def camera_settings(config: StationConfig, exposure_us: float) -> CameraSettings:
    """The camera settings of a sweep: the configured format, gain and ROI, this exposure."""
    cam = config.camera
    roi = None
    if cam.roi is not None:
        roi = Roi(cam.roi.width, cam.roi.height, cam.roi.offset_x, cam.roi.offset_y)
    return CameraSettings(
        pixel_format=cam.pixel_format, exposure_us=exposure_us, gain=cam.gain, roi=roi
    )


# --------------------------------------------------------------------------- the run


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
        self.writer: SweepWriter | None = None
        self.sink: FrameWriter | None = None
        self.session: AnalysisSession | None = None
        self.geometry: SweepGeometry | None = None
        self.recovered_faults = 0
        self.report: VerifyReport | None = None

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
            self._wind_down()
            reason = self._with_count(stop.reason)
            return Outcome(stop.state, reason, last_error=reason if stop.error else None)
        except JobFailed as exc:
            self._wind_down()
            message = self._with_count(exc.message)
            return Outcome(
                JobState.FAILED,
                message,
                last_error=message,
                result=exc.result,
                devices_broken=exc.devices_broken,
            )
        except StoreUnavailable as exc:  # e.g. a pause the store could not record
            self._wind_down()
            message = self._with_count(f"the job store cannot be written: {exc}")
            return Outcome(JobState.FAILED, message, last_error=message)
        except Exception as exc:  # noqa: BLE001 - the job must end in a truthful state
            self._wind_down()
            message = self._with_count(f"internal error: {type(exc).__name__}: {exc}")
            return Outcome(JobState.FAILED, message, last_error=message)

    def _with_count(self, message: str) -> str:
        try:
            kept = self.ctx.store.step_count(self.job.id)
        except Exception:  # noqa: BLE001
            return message
        return f"{message} ({kept} of {self.plan.frames} frames kept)"

    # ------------------------------------------------------------------ helpers

    def _phase(self, phase: str, detail: str = "") -> None:
        with self.ctx.progress_lock:
            self.ctx.progress.phase = phase
        self.ctx.publish(JobEvent(self.job.id, "phase", None, {"phase": phase, "detail": detail}))

    def _boundary(self) -> bool:
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
            self._check_sink()
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

    def _check_sink(self) -> None:
        assert self.sink is not None
        error = self.sink.error
        if error is not None:
            raise self._storage_failure(error)

    def _storage_failure(self, error: BaseException) -> JobFailed:
        if isinstance(error, StoreUnavailable):
            return JobFailed(f"a written frame cannot be recorded in the job store: {error}")
        if isinstance(error, DiskFull):
            return JobFailed(f"disk full, nothing written past the last frame: {error}")
        return JobFailed(f"cannot write the archive {self.job_dir}: {error}")

    def _pause(self) -> None:
        control = self.ctx.control
        if self.sink is not None:
            self.sink.drain()
            self._check_sink()
        self._make_safe()
        with self.ctx.progress_lock:
            self.ctx.progress.pause_requested = False
            self.ctx.progress.phase = "paused"
        self.ctx.transition(self.job.id, JobState.PAUSED, control.pause_reason)
        answer = control.wait_paused()
        if answer == "shutdown":
            raise StopRequested(JobState.INTERRUPTED, "station shut down while the job was paused")
        if answer == "cancel":
            raise StopRequested(JobState.CANCELLED, control.cancel_reason)
        self.ctx.transition(self.job.id, JobState.RUNNING, control.resume_reason)
        # the devices may have been touched while paused: check the references again
        self._home_if_needed()

    def _make_safe(self) -> None:
        """Stop the rail (decelerated); errors are ignored (best effort)."""
        try:
            self.dev.rail.stop()
        except (DeviceError, OSError):
            pass

    def _wind_down(self) -> None:
        """After a stop or failure: write every frame already grabbed, stop the rail."""
        if self.sink is not None:
            try:
                self.sink.close()
            except Exception:  # noqa: BLE001 - already failing; the error is in the outcome
                pass
        if self.session is not None:
            self.session.cancel()
        self._make_safe()

    def _note_fault(self, what: str, exc: BaseException, action: str) -> None:
        self.recovered_faults += 1
        text = f"{what}: {exc} -- {action}"
        with self.ctx.progress_lock:
            self.ctx.progress.last_error = text
        self.ctx.publish(
            JobEvent(
                self.job.id, "fault", None, {"what": what, "error": str(exc), "action": action}
            )
        )
        if self.recovered_faults > MAX_RECOVERED_FAULTS:
            raise JobFailed(
                f"{what}: more than {MAX_RECOVERED_FAULTS} device faults in this run, the last: "
                f"{exc}"
            )

    def _with_policy(
        self,
        what: str,
        op: Callable[[], T],
        *,
        rehome: Callable[[], None] | None = None,
    ) -> T:
        """Run ``op``; on a device error follow :mod:`station.faults` (bounded)."""
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
                self._note_fault(what, exc, f"{rule.action.value} ({rule.why})")
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

    # ------------------------------------------------------------------ 1. prepare

    def _prepare(self) -> None:
        self._phase("preparing")
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
        settings = self._with_policy(
            "configuring the camera", lambda: self.dev.camera.configure(wanted)
        )
        info = self._with_policy("reading the camera's identity", self.dev.camera.info)
        roi = settings.roi or Roi(info.sensor_width, info.sensor_height)
        depth = bit_depth(settings.pixel_format)
        self.settings = settings
        self._open_archive(roi, depth, settings)
        self._home_if_needed()

    def _open_archive(self, roi: Roi, depth: int, settings: CameraSettings) -> None:
        store = self.ctx.store
        if (self.job_dir / "sweep.json").is_file():
            try:
                try:
                    self.report = reconcile(store, self.job.id, self.job_dir)
                finally:
                    self.ctx.row_changed(self.job.id)
                self.writer = SweepWriter.resume(self.job_dir)
            except (ArchiveError, OSError) as exc:
                raise JobFailed(
                    f"the job's archive {self.job_dir} cannot be resumed: {exc}"
                ) from exc
            cam = self.writer.manifest.camera
            if (cam.width, cam.height, cam.bit_depth) != (roi.width, roi.height, depth):
                raise JobFailed(
                    f"the camera delivers {roi.width}x{roi.height} px at {depth} bits, but the "
                    f"job's archive holds {cam.width}x{cam.height} px at {cam.bit_depth} bits: "
                    "restore the camera settings of the job (ROI, pixel format) to resume it"
                )
            return
        key = f"{roi.width}x{roi.height}+{roi.offset_x}+{roi.offset_y}"
        pp = self.ctx.principal_point_cache.get(key)
        if pp is None:
            pp = principal_point_px(self.cfg, roi, self.dev.camera.info().principal_point_px)
            self.ctx.principal_point_cache[key] = pp
        header = self.cfg.manifest_header(
            width=roi.width, height=roi.height, bit_depth=depth, principal_point_px=pp
        )
        header["station"] = {
            "job_id": self.job.id,
            "created_at": self.job.created_at,
            "sweep": self.plan.to_dict(),
            "camera": {
                "pixel_format": settings.pixel_format,
                "exposure_us": settings.exposure_us,
                "gain": settings.gain,
                "roi": [roi.width, roi.height, roi.offset_x, roi.offset_y],
                "black_level": settings.black_level,
                "trigger": settings.trigger,
                "flat_field": settings.flat_field,
            },
        }
        if self.dev.bench is not None:
            header["simulated"] = {"preset": self.cfg.camera.preset}
        try:
            self.writer = SweepWriter.in_place(self.job_dir, header)
        except (ArchiveError, OSError) as exc:
            raise JobFailed(f"cannot create the job's archive {self.job_dir}: {exc}") from exc
        self.report = VerifyReport(archive_exists=True)

    def _home_if_needed(self) -> None:
        rail, xy = self.dev.rail, self.dev.xy
        if not self._with_policy("reading the rail's reference", rail.is_homed):
            self._phase("homing", "rail")
            self._with_policy("homing the rail", rail.home)
        if not self._with_policy("reading the XY stage's reference", xy.is_homed):
            self._phase("homing", "xy stage")
            self._with_policy("homing the XY stage", xy.home)

    # ------------------------------------------------------------------ 2. white

    def _white(self) -> None:
        self._boundary()
        assert self.writer is not None and self.report is not None
        white: np.ndarray | None = None
        if self.report.white_ok:
            try:
                white = SweepArchive.open(self.job_dir).white()
            except ArchiveError:
                white = None
        if white is None:
            white = self._new_white()
            try:
                self.writer.write_white(white)
            except OSError as exc:
                raise self._storage_failure(exc) from exc
        self.geometry = SweepGeometry.from_manifest(self.writer.manifest)
        self._start_pipeline(white)

    def _new_white(self) -> np.ndarray:
        source = self.plan.white_from_job
        if source is not None:
            self._phase("white", f"reusing the white image of job {source}")
            return self._white_of_job(source)
        pos = self.cfg.xy_stage.white
        self._phase("white", f"XY stage to the white position ({pos.x_mm:g}, {pos.y_mm:g}) mm")
        self._with_policy(
            "moving the XY stage to the white position",
            lambda: self.dev.xy.move_xy_mm(pos.x_mm, pos.y_mm),
            rehome=self.dev.xy.home,
        )
        return self._grab("the white image").pixels

    def _white_of_job(self, source: int) -> np.ndarray:
        try:
            other = self.ctx.store.get_job(source)
            archive = SweepArchive.open(other.archive_dir)
            check = archive.check(decode=False)
            if check.white:
                raise ArchiveError("; ".join(check.white))
            image = archive.white()
        except (ArchiveError, KeyError, OSError) as exc:
            raise JobFailed(f"cannot reuse the white image of job {source}: {exc}") from exc
        assert self.writer is not None
        cam = self.writer.manifest.camera
        if image.shape != cam.shape:
            raise JobFailed(
                f"the white image of job {source} is {image.shape[1]}x{image.shape[0]} px, this "
                f"job's frames are {cam.width}x{cam.height} px"
            )
        return image

    def _start_pipeline(self, white: np.ndarray) -> None:
        """Start the writer thread and (when calibrating) the streaming analysis."""
        assert self.writer is not None and self.geometry is not None
        store, job_id = self.ctx.store, self.job.id
        if self.plan.calibrate and self.ctx.pool is not None:
            self._phase("white", "fitting the MLA grid")
            try:
                analyzer = self.ctx.pool.fit_analyzer(self.geometry, white)
            except ValueError as exc:
                raise JobFailed(
                    f"the white image is unusable, the MLA grid fit failed: {exc} -- check that "
                    "the XY stage's white position shows the board's plain light area"
                ) from exc
            cam = self.writer.manifest.camera
            self.session = self.ctx.pool.session(
                f"{job_id}-{time.time_ns()}",
                analyzer,
                shape=cam.shape,
                bit_depth=cam.bit_depth,
                on_summary=self._on_summary,
            )
            for step in store.steps(job_id):
                if step.summary is not None:
                    self.session.add_known(summary_from_dict(step.summary))
                else:
                    self.session.submit(step.index, step.actual_mm, self.job_dir / step.file)
        with self.ctx.progress_lock:
            self.ctx.progress.frames_done = store.step_count(job_id)
            self.ctx.progress.frames_analysed = (
                self.session.done_count() if self.session is not None else 0
            )
        self.sink = FrameWriter(self.writer, store, job_id, on_written=self._on_written)

    def _on_written(self, step: StepRecord) -> None:
        """Writer thread: a frame is on disk and recorded."""
        self.ctx.row_changed(self.job.id)  # before the step is announced
        if self.session is not None:
            self.session.submit(step.index, step.actual_mm, self.job_dir / step.file)
        progress = self.ctx.progress
        with self.ctx.progress_lock:
            progress.frames_done += 1
            done, total, eta = progress.frames_done, progress.frames_total, progress.eta_s()
        self.ctx.publish(
            JobEvent(
                self.job.id,
                "step",
                step.index,
                {**step_data(step, done, total), "eta_s": eta},
            )
        )

    def _on_summary(self, summary: Any) -> None:
        """Analysis callback: store the summary with the step and publish it."""
        try:
            self.ctx.store.set_step_summary(self.job.id, summary.index, summary.to_dict())
        except Exception:  # noqa: BLE001 - the summary is recomputed on resume if lost
            pass
        with self.ctx.progress_lock:
            self.ctx.progress.frames_analysed += 1
        self.ctx.publish(
            JobEvent(
                self.job.id,
                "analysis",
                None,
                analysis_payload(summary, self.cfg.board.reference_gap_mm),
            )
        )

    # ------------------------------------------------------------------ 3. align

    def _align(self) -> None:
        pos = self.cfg.xy_stage.alignment
        self._phase("aligning", f"XY stage to ({pos.x_mm:g}, {pos.y_mm:g}) mm")
        self._with_policy(
            "moving the XY stage to the alignment position",
            lambda: self.dev.xy.move_xy_mm(pos.x_mm, pos.y_mm),
            rehome=self.dev.xy.home,
        )

    # ------------------------------------------------------------------ 4. sweep

    def _sweep(self) -> None:
        assert self.sink is not None
        positions = self.plan.positions_mm()
        done = {s.index for s in self.ctx.store.steps(self.job.id)}
        todo = [i for i in range(self.plan.frames) if i not in done]
        self._phase("sweeping", f"{len(todo)} of {self.plan.frames} frames to capture")
        for index in todo:
            t0 = time.perf_counter()
            if self._boundary():
                self._align()
                self._phase("sweeping", "resumed")
                t0 = time.perf_counter()
            frame, move_s, settle_s, grab_s = self._capture(index, positions[index])
            try:
                self.sink.put(frame)
            except OSError as exc:
                raise self._storage_failure(exc) from exc
            total = time.perf_counter() - t0
            timing = StepTiming(index, move_s, settle_s, grab_s, total)
            self.ctx.timings.append(timing)
            with self.ctx.progress_lock:
                self.ctx.progress.step_durations_s.append(total)

    def _capture(self, index: int, target: float) -> tuple[CapturedFrame, float, float, float]:
        where = f"step {index} (rail {target:.3f} mm)"
        started = time.time()
        t0 = time.perf_counter()
        actual = self._with_policy(
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
        frame = self._grab(f"frame {index} at {actual:.3f} mm", grab_s, where=where)
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
        self._phase("homing", "rail lost its reference")
        self.dev.rail.home()
        self._phase("sweeping", "rail homed again")

    def _grab(self, what: str, timer: list[float] | None = None, *, where: str = "") -> Any:
        timeout = self.cfg.camera.timeout_s

        def once() -> Any:
            t = time.perf_counter()
            frame = self.dev.camera.grab(timeout_s=timeout)
            if timer is not None:
                timer[0] += time.perf_counter() - t
            check_frame(frame.pixels, frame.bit_depth, what=what)
            return frame

        return self._with_policy(f"{where or what}: grabbing", once)

    # ------------------------------------------------------------------ 5. finish

    def _finish(self) -> Outcome:
        assert self.sink is not None
        self.sink.close()
        self._check_sink()
        self.sink = None
        control = self.ctx.control
        if control.cancel:
            raise StopRequested(JobState.CANCELLED, control.cancel_reason)
        recorded = {s.index for s in self.ctx.store.steps(self.job.id)}
        missing = sorted(set(range(self.plan.frames)) - recorded)
        if missing:
            raise JobFailed(f"frames {missing[:10]} were not recorded")
        if not self.plan.calibrate or self.session is None:
            return Outcome(JobState.SUCCEEDED, "all frames captured (calibration not requested)")
        self._phase("calibrating", f"{self.plan.frames} frames")
        summaries = self.session.wait(timeout_s=600.0)
        assert self.geometry is not None
        try:
            result = self.session.combine(
                [summaries[i] for i in sorted(summaries) if i in recorded], self.geometry
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
        import json

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
