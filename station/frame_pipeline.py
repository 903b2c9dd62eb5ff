"""The white phase of a sweep run and the pipeline every frame goes through after it.

:meth:`FramePipeline.start` (on the hardware worker thread) gets the flat field --
the archive's verified white image, else a new one grabbed at the XY stage's white
position, else (``white_from_job``) a copy of an earlier job's -- writes it to the
archive, and on it starts:

- the streaming analysis (when the job calibrates): the MLA grid is fitted on the
  white image in an analysis worker, then every frame already recorded is handed
  over (its stored summary, or its file to analyse again);
- the archive writer thread (:class:`station.writer.FrameWriter`).

From then on :meth:`FramePipeline.on_written` runs on the writer thread for every
recorded step (analysis submission, progress, ``step`` event) and
:meth:`FramePipeline.on_summary` on the analysis side for every frame summary
(stored with its step, ``analysis`` event). The writer and the analysis are kept
by the run's :class:`station.run_guard.RunGuard`, which checks and stops them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.archive import ArchiveError, SweepArchive, SweepWriter
from calibration.clipping import OverexposedWhiteError
from calibration.pipeline import SweepGeometry
from station.analysis import summary_from_dict
from station.events import JobEvent, analysis_payload, step_data
from station.recovery import VerifyReport
from station.run_control import JobFailed, RunContext
from station.run_guard import RunGuard
from station.store import StepRecord
from station.sweep import SweepPlan
from station.writer import FrameWriter


class FramePipeline:
    """The white image and the writer / analysis pipeline of one run (see the module docstring).

    Args:
        job_id: the running job.
        job_dir: its archive directory.
        plan: its sweep.
        devices: ``station.devices.StationDevices`` (camera, rail, xy).
        ctx: orchestrator services.
        guard: the run's fault policy; it is handed the writer and the analysis.

    Attributes:
        geometry: the sweep's geometry (from the archive's manifest), set by :meth:`start`.
    """

    def __init__(
        self,
        job_id: int,
        job_dir: Path,
        plan: SweepPlan,
        devices: Any,
        ctx: RunContext,
        guard: RunGuard,
    ) -> None:
        self.job_id = job_id
        self.job_dir = job_dir
        self.plan = plan
        self.dev = devices
        self.ctx = ctx
        self.guard = guard
        self.geometry: SweepGeometry | None = None

    def start(self, writer: SweepWriter, report: VerifyReport) -> None:
        """The white phase: the white image in the archive, then the writer and the analysis."""
        white: np.ndarray | None = None
        if report.white_ok:
            try:
                white = SweepArchive.open(self.job_dir).white()
            except ArchiveError:
                white = None
        if white is None:
            white = self._new_white(writer)
            try:
                writer.write_white(white)
            except OSError as exc:
                raise self.guard.storage_failure(exc) from exc
        self.geometry = SweepGeometry.from_manifest(writer.manifest)
        self._start_pipeline(writer, white)

    def _new_white(self, writer: SweepWriter) -> np.ndarray:
        source = self.plan.white_from_job
        if source is not None:
            self.guard.announce_phase("white", f"reusing the white image of job {source}")
            return self._white_of_job(source, writer)
        pos = self.ctx.config.xy_stage.white
        self.guard.announce_phase(
            "white", f"XY stage to the white position ({pos.x_mm:g}, {pos.y_mm:g}) mm"
        )
        self.guard.with_policy(
            "moving the XY stage to the white position",
            lambda: self.dev.xy.move_xy_mm(pos.x_mm, pos.y_mm),
            rehome=self.dev.xy.home,
        )
        return self.guard.grab("the white image").pixels

    def _white_of_job(self, source: int, writer: SweepWriter) -> np.ndarray:
        try:
            other = self.ctx.store.get_job(source)
            archive = SweepArchive.open(other.archive_dir)
            check = archive.check(decode=False)
            if check.white:
                raise ArchiveError("; ".join(check.white))
            image = archive.white()
        except (ArchiveError, KeyError, OSError) as exc:
            raise JobFailed(f"cannot reuse the white image of job {source}: {exc}") from exc
        cam = writer.manifest.camera
        if image.shape != cam.shape:
            raise JobFailed(
                f"the white image of job {source} is {image.shape[1]}x{image.shape[0]} px, this "
                f"job's frames are {cam.width}x{cam.height} px"
            )
        return image

    def _start_pipeline(self, writer: SweepWriter, white: np.ndarray) -> None:
        """Start the writer thread and (when calibrating) the streaming analysis."""
        assert self.geometry is not None
        guard, store, job_id = self.guard, self.ctx.store, self.job_id
        if self.plan.calibrate and self.ctx.pool is not None:
            guard.announce_phase("white", "fitting the MLA grid")
            try:
                analyzer = self.ctx.pool.fit_analyzer(self.geometry, white)
            except OverexposedWhiteError as exc:
                raise JobFailed(f"the white image is unusable: {exc}") from exc
            except ValueError as exc:
                raise JobFailed(
                    f"the white image is unusable, the MLA grid fit failed: {exc} -- check that "
                    "the XY stage's white position shows the board's plain light area"
                ) from exc
            cam = writer.manifest.camera
            session = self.ctx.pool.session(
                f"{job_id}-{time.time_ns()}",
                analyzer,
                shape=cam.shape,
                bit_depth=cam.bit_depth,
                on_summary=self.on_summary,
            )
            guard.session = session  # from here on, a wind-down cancels it
            for step in store.steps(job_id):
                if step.summary is not None:
                    session.add_known(summary_from_dict(step.summary))
                else:
                    session.submit(step.index, step.actual_mm, self.job_dir / step.file)
        with self.ctx.progress_lock:
            self.ctx.progress.frames_done = store.step_count(job_id)
            self.ctx.progress.frames_analysed = (
                guard.session.done_count() if guard.session is not None else 0
            )
        guard.sink = FrameWriter(writer, store, job_id, on_written=self.on_written)

    def on_written(self, step: StepRecord) -> None:
        """Writer thread: a frame is on disk and recorded."""
        self.ctx.row_changed(self.job_id)  # before the step is announced
        session = self.guard.session
        if session is not None:
            session.submit(step.index, step.actual_mm, self.job_dir / step.file)
        progress = self.ctx.progress
        with self.ctx.progress_lock:
            progress.frames_done += 1
            done, total, eta = progress.frames_done, progress.frames_total, progress.eta_s()
        self.ctx.publish(
            JobEvent(
                self.job_id,
                "step",
                step.index,
                {**step_data(step, done, total), "eta_s": eta},
            )
        )

    def on_summary(self, summary: Any) -> None:
        """Analysis callback: store the summary with the step and publish it."""
        try:
            self.ctx.store.set_step_summary(self.job_id, summary.index, summary.to_dict())
        except Exception:  # noqa: BLE001 - the summary is recomputed on resume if lost
            pass
        with self.ctx.progress_lock:
            self.ctx.progress.frames_analysed += 1
        self.ctx.publish(
            JobEvent(
                self.job_id,
                "analysis",
                None,
                analysis_payload(summary, self.ctx.config.board.reference_gap_mm),
            )
        )


__all__ = ["FramePipeline"]
