"""Request and response models of the HTTP API (they make the OpenAPI document).

The sweep request model is built per configuration (:func:`sweep_body_model`)
so that the rail's travel appears in the schema as the allowed range of
``start_mm`` and ``stop_mm``. Validation is strict: ``"12"`` is not a number and
``1`` is not a boolean. Cross-field rules (stop ≥ start, at most
``sweep.max_frames`` frames, the camera's exposure range) are the station's and
come back as 422 with the same field-level shape.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Path
from pydantic import BaseModel, ConfigDict, Field, create_model

from station.config import StationConfig
from station.store import JobState
from station.sweep import HARD_MAX_FRAMES

MIN_STEP_MM = 0.001
"""Smallest rail step accepted (1 µm; a Zaber microstep is about 0.05 µm)."""

MAX_ID = 2**53
"""Largest job id accepted in a path (larger ones cannot exist)."""

JobId = Annotated[int, Path(ge=1, le=MAX_ID, description="job id", examples=[1])]
"""A job id in a path."""

SWEEP_FIELDS = (
    "start_mm",
    "stop_mm",
    "step_mm",
    "exposure_us",
    "settle_s",
    "calibrate",
    "white_from_job",
    "note",
)


class _SweepBodyBase(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


def sweep_body_model(config: StationConfig) -> type[BaseModel]:
    """The ``POST /jobs`` body model for this station (ranges from the configuration)."""
    lo, hi = config.rail.min_mm, config.rail.max_mm
    sw = config.sweep
    max_frames = min(sw.max_frames, HARD_MAX_FRAMES)
    exposure = sw.exposure_us or config.camera.exposure_us
    settle = sw.settle_s if sw.settle_s is not None else config.rail.settle_s
    fields: dict[str, Any] = {
        "start_mm": (
            float | None,
            Field(
                default=None,
                ge=lo,
                le=hi,
                description=f"first rail position (mm); default {sw.start_mm:g}",
                examples=[sw.start_mm],
            ),
        ),
        "stop_mm": (
            float | None,
            Field(
                default=None,
                ge=lo,
                le=hi,
                description=f"last rail position (mm), inclusive, ≥ start_mm; default {sw.stop_mm:g}",
                examples=[sw.stop_mm],
            ),
        ),
        "step_mm": (
            float | None,
            Field(
                default=None,
                ge=MIN_STEP_MM,
                le=hi - lo,
                description=f"rail step between frames (mm), at least {MIN_STEP_MM:g} mm; "
                f"default {sw.step_mm:g}; at most "
                f"{max_frames} frames",
                examples=[sw.step_mm],
                json_schema_extra={"x-max-frames": max_frames},
            ),
        ),
        "exposure_us": (
            float | None,
            Field(
                default=None,
                gt=0,
                le=60e6,
                description="camera exposure (µs); default: the configured one",
                examples=[exposure],
            ),
        ),
        "settle_s": (
            float | None,
            Field(
                default=None,
                ge=0,
                le=60,
                description="wait after each rail move (s)",
                examples=[settle],
            ),
        ),
        "calibrate": (bool, Field(default=True, description="calibrate at the end of the sweep")),
        "white_from_job": (
            int | None,
            Field(
                default=None,
                ge=1,
                le=MAX_ID,
                description="reuse the white image of this earlier job (same frame size)",
            ),
        ),
        "note": (
            str | None,
            Field(default=None, max_length=500, description="free text stored with the job"),
        ),
    }
    model = create_model("SweepRequest", __base__=_SweepBodyBase, **fields)
    model.__doc__ = (
        "A sweep along the rail; every field is optional (defaults from the station's "
        "[sweep] and [camera] configuration)."
    )
    return model


class JobLinks(BaseModel):
    """Where to find more about a job."""

    self: str
    events: str
    result: str
    archive: str
    focus_plot: str
    disparity_plot: str
    render_calibrated: str
    render_designed: str


class JobOut(BaseModel):
    """A job: its state and progress."""

    id: int = Field(description="job id")
    state: JobState = Field(description="queued, running, paused, succeeded, failed, ...")
    created_at: float = Field(description="Unix time (s)")
    updated_at: float = Field(description="Unix time (s)")
    request: dict[str, Any] = Field(description="the validated sweep (concrete values)")
    archive_dir: str = Field(description="the job's lfcal-sweep/1 archive directory")
    frames_done: int = Field(description="frames written and recorded")
    frames_total: int = Field(description="frames of the sweep")
    frames_analysed: int | None = Field(default=None, description="frames analysed (active job)")
    phase: str | None = Field(default=None, description="what the active job is doing")
    rail_mm: float | None = Field(default=None, description="current rail position (mm)")
    eta_s: float | None = Field(default=None, description="seconds until the last frame")
    last_error: str | None = Field(default=None, description="why the job failed / stopped")
    has_result: bool = Field(description="a calibration result is stored")
    pause_requested: bool = False
    cancel_requested: bool = False
    recent_fault: str | None = Field(default=None, description="last recovered fault")
    station_id: str = Field(default="", description="the station that owns and runs the job")
    station_alive: bool | None = Field(
        default=None,
        description="in the job list: whether the owning station's process is running "
        "(holds its lock on the shared database); false: that station is down, and a job "
        "it left running has no worker until the station restarts and marks it "
        "interrupted; null where not reported",
    )
    camera_serial: str | None = Field(
        default=None, description="serial number of the camera that took the frames"
    )
    archive_url: str | None = Field(
        default=None, description="where the archive is uploaded (s3://...), if anywhere"
    )
    links: JobLinks


class JobList(BaseModel):
    """Jobs, oldest first."""

    jobs: list[JobOut]


class ResultVersionOut(BaseModel):
    """One version of a job's result (0: the station's own; then each recalibration)."""

    job_id: int
    version: int = Field(description="0 for the station's result, then 1, 2, ...")
    software_version: str = Field(description="lfcal-station version that computed it")
    created_at: float = Field(description="Unix time (s) it was stored")
    source: str = Field(description="station or recalibrate")
    result: dict[str, Any] | None = Field(default=None, description="the result JSON")


class ResultVersionList(BaseModel):
    """Every version of a job's result, oldest first."""

    versions: list[ResultVersionOut]


class CalibrationResult(BaseModel):
    """The calibration (``lfcal-result/1``): every key of ``lfcal calibrate``'s JSON."""

    model_config = ConfigDict(extra="allow")

    a_mm: float | None = Field(default=None, description="focus distance a in front of the MLA")
    b_mm: float | None = Field(default=None, description="MLA-to-sensor distance b (mm)")
    Q: float | None = Field(default=None, description="Q = b/a at the focus plane")
    patch_size_px: float | None = Field(default=None, description="ESIF patch size p (px)")
    uncertainty: dict[str, Any] | None = None
    focus: dict[str, Any] | None = None
    frames: list[dict[str, Any]] = Field(default_factory=list)


class Health(BaseModel):
    """Health of the station: what is down and why."""

    status: str = Field(description='"ok", or "degraded" while a component is down')
    version: str
    devices: str = Field(description="connected, busy, opening or down")
    read_only_requires_key: bool
    jobs_active: int | None = Field(
        description="jobs queued, running or paused (null if the store cannot be read)"
    )
    can_run_jobs: bool = Field(
        default=True, description="false (and HTTP 503) when the station cannot run jobs"
    )
    problems: list[str] = Field(default_factory=list, description="one sentence per problem")
    components: dict[str, Any] = Field(
        default_factory=dict,
        description="worker, store, storage, analysis, devices: each with its state",
    )


class DevicesOut(BaseModel):
    """The station's devices: connection, identity, position, homed, camera settings."""

    model_config = ConfigDict(extra="allow")

    connected: bool
    busy: bool = Field(description="a job owns the devices (positions are the last known)")
    camera: dict[str, Any] | None = None
    rail: dict[str, Any] | None = None
    xy_stage: dict[str, Any] | None = None


__all__ = [
    "MAX_ID",
    "JobId",
    "SWEEP_FIELDS",
    "CalibrationResult",
    "DevicesOut",
    "Health",
    "JobLinks",
    "JobList",
    "JobOut",
    "sweep_body_model",
]
