"""What a client reads of a job: its status, result, archive, frames and recorded events.

Functions of the job store that take no lock and write nothing to it (and, for the archive's
files, :class:`station.archive_source.ArchiveReader`); :class:`station.orchestrator.Orchestrator`
adds the active job's live progress and serves them. Errors the web layer maps: :class:`station.store.JobNotFound` (404),
:class:`FrameNotFound` (404), :class:`ResultNotReady` (409).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calibration.archive import frame_file_name, read_image, read_manifest
from station.analysis import summary_from_dict
from station.archive_source import ArchiveReader
from station.events import JobEvent, analysis_payload, step_data
from station.store import JobRecord, JobState, JobStore


class ResultNotReady(RuntimeError):
    """The job has no calibration result (yet): the web layer answers 409.

    Attributes:
        job_id: the job.
        state: its state.
    """

    def __init__(self, job_id: int, state: JobState, why: str) -> None:
        self.job_id = job_id
        self.state = state
        super().__init__(f"job {job_id} is {state.value}: {why}")


class FrameNotFound(KeyError):
    """The job has no recorded frame with this index (the web layer answers 404)."""

    def __init__(self, job_id: int, index: int) -> None:
        self.job_id = job_id
        self.index = index
        super().__init__(f"job {job_id} has no recorded frame {index}")

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class JobStatus:
    """What a client sees of a job (JSON-ready through :meth:`to_dict`).

    Attributes:
        id, state, created_at, updated_at, archive_dir, last_error: from the store.
        request: the validated sweep (:class:`station.sweep.SweepPlan` as a dict).
        frames_done: frames written and recorded.
        frames_total: frames of the sweep.
        frames_analysed: frames analysed (active job only; else None).
        phase: what the active job is doing (``preparing``, ``homing``, ``white``,
            ``aligning``, ``sweeping``, ``paused``, ``calibrating``), else None.
        rail_mm: last read-back rail position of the active job (mm), else None.
        eta_s: seconds until the last frame (active job), else None.
        pause_requested, cancel_requested: a request waiting for the next step boundary.
        has_result: a calibration result (or a failed calibration's partial result) is stored.
        recent_fault: the last fault the active job recovered from, else None.
        station_id, camera_serial, archive_url: from the store (see
            :class:`station.store.JobRecord`).
    """

    id: int
    state: JobState
    created_at: float
    updated_at: float
    request: dict[str, Any]
    archive_dir: str
    frames_done: int
    frames_total: int
    last_error: str | None
    has_result: bool
    frames_analysed: int | None = None
    phase: str | None = None
    rail_mm: float | None = None
    eta_s: float | None = None
    pause_requested: bool = False
    cancel_requested: bool = False
    recent_fault: str | None = None
    station_id: str = ""
    camera_serial: str | None = None
    archive_url: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (``state`` as its string)."""
        out = dict(self.__dict__)
        out["state"] = self.state.value
        return out


def status_of(job: JobRecord, frames_done: int, **live: Any) -> JobStatus:
    """The client's view of ``job`` with ``frames_done`` and the active job's ``live`` fields."""
    return JobStatus(
        id=job.id,
        state=job.state,
        created_at=job.created_at,
        updated_at=job.updated_at,
        request=job.request,
        archive_dir=str(job.archive_dir),
        frames_done=frames_done,
        frames_total=job.frames_total,
        last_error=job.last_error,
        has_result=job.has_result,
        station_id=job.station_id,
        camera_serial=job.camera_serial,
        archive_url=job.archive_url,
        **live,
    )


def result_of(job: JobRecord, store: JobStore) -> dict[str, Any]:
    """The calibration result (JSON object) of a succeeded job (``job`` read with its result).

    Raises :class:`ResultNotReady` (409) while the job runs, or when it ended
    without a result (its ``last_error`` says why; a failed calibration's
    partial result is in the record).
    """
    if job.state is JobState.SUCCEEDED and job.result is not None:
        return job.result
    if job.state is JobState.SUCCEEDED:
        raise ResultNotReady(job.id, job.state, "the job only acquired frames (calibrate false)")
    if job.state in (JobState.QUEUED, JobState.RUNNING, JobState.PAUSED):
        raise ResultNotReady(job.id, job.state, "the calibration is not finished")
    why = job.last_error
    if why is None:
        changes = store.transitions(job.id)
        why = changes[-1].reason if changes else "no result"
    raise ResultNotReady(job.id, job.state, why)


def archive_dir_of(store: JobStore, archives: ArchiveReader, job_id: int) -> Path:
    """The job's ``lfcal-sweep/1`` directory (it may not exist before the job starts):
    the local one, else a copy fetched from object storage (:mod:`station.archive_source`)."""
    job = store.get_job(job_id)
    return archives.local_dir(job.archive_dir, job.archive_url)


def _frame_file(store: JobStore, job_id: int, index: int) -> str:
    """The recorded frame's file name in its archive (:class:`FrameNotFound` otherwise)."""
    step = store.step(job_id, index)
    if step is None:
        store.get_job(job_id)  # JobNotFound first
        raise FrameNotFound(job_id, index)
    return step.file or frame_file_name(index)


def frame_path_of(store: JobStore, archives: ArchiveReader, job_id: int, index: int) -> Path:
    """The file of a recorded frame (:class:`FrameNotFound` otherwise)."""
    name = _frame_file(store, job_id, index)
    return archive_dir_of(store, archives, job_id) / name


def read_frame_of(store: JobStore, archives: ArchiveReader, job_id: int, index: int) -> Any:
    """A recorded frame as counts (``uint16``, ``(height, width)``), e.g. for a preview.

    Raises :class:`FrameNotFound`, or a :class:`calibration.archive.ImageError`
    if the file is damaged.
    """
    name = _frame_file(store, job_id, index)
    directory = archive_dir_of(store, archives, job_id)
    manifest = read_manifest(directory)
    return read_image(
        directory / name, expected_shape=manifest.camera.shape, bit_depth=manifest.camera.bit_depth
    )


def replay_events(
    store: JobStore, job: JobRecord, after: int | None, *, reference_gap_mm: float
) -> list[JobEvent]:
    """``step`` events of the job's recorded steps with index > ``after`` (from the store,
    so they survive restarts), each with the frame's analysis ``summary`` when
    known, then one ``state`` event with the job's current state.

    SSE recipe: subscribe first, then replay from Last-Event-ID, then forward
    live events, skipping ``step`` events whose id was already replayed.
    """
    events = []
    total = job.frames_total
    done = 0
    for step in store.steps(job.id):
        done += 1
        if after is not None and step.index <= after:
            continue
        data = {**step_data(step, done, total), "replayed": True}
        if step.summary is not None:
            data["summary"] = analysis_payload(summary_from_dict(step.summary), reference_gap_mm)
        events.append(JobEvent(job.id, "step", step.index, data, at=step.written_at))
    events.append(
        JobEvent(
            job.id,
            "state",
            None,
            {
                "state": job.state.value,
                "from": None,
                "reason": "current state",
                "last_error": job.last_error,
            },
            at=job.updated_at,
        )
    )
    return events
