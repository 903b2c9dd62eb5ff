"""Sweep requests: what a client may ask for, and its validation against the station.

A :class:`SweepRequest` is what arrives over HTTP or from ``lfcal sweep``; every
field is optional and defaults to the ``[sweep]`` / ``[camera]`` configuration.
:func:`plan_sweep` checks it against the configuration (and, when known, the
rail's travel and the camera's exposure range read from the devices) and turns
it into a :class:`SweepPlan` with concrete values, or raises
:class:`RequestInvalid` listing **every** problem as ``(field, message)`` pairs
(the web layer answers 422 with them).

Units: mm, s, µs as the names say.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from station.config import StationConfig

HARD_MAX_FRAMES = 2000
"""No sweep has more frames than this, whatever ``sweep.max_frames`` says."""

_EPS = 1e-9


class RequestInvalid(ValueError):
    """A sweep request that cannot run.

    Attributes:
        problems: ``(field, message)`` pairs, one per problem; ``field`` is the
            request field (``start_mm`` ...) or ``"request"`` for the whole body.
    """

    def __init__(self, problems: list[tuple[str, str]]) -> None:
        self.problems = list(problems)
        super().__init__("; ".join(f"{field}: {msg}" for field, msg in self.problems))


class SweepRequest(BaseModel):
    """A sweep as a client asks for it (all optional; defaults from the configuration).

    Attributes:
        start_mm: first rail position (mm).
        stop_mm: last rail position (mm), inclusive (reached when on the step grid).
        step_mm: rail step between frames (mm), > 0.
        exposure_us: camera exposure during the sweep and the white image (µs).
        settle_s: wait after each rail move before the frame (s).
        calibrate: run the calibration at the end (False: acquisition only).
        white_from_job: reuse the white image of this earlier job instead of
            capturing one (it must have the same frame size).
        note: free text stored with the job.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    start_mm: float | None = Field(default=None, description="first rail position (mm)")
    stop_mm: float | None = Field(default=None, description="last rail position (mm), inclusive")
    step_mm: float | None = Field(default=None, description="rail step between frames (mm)")
    exposure_us: float | None = Field(default=None, description="camera exposure (µs)")
    settle_s: float | None = Field(default=None, description="wait after each move (s)")
    calibrate: bool = Field(default=True, description="calibrate at the end of the sweep")
    white_from_job: int | None = Field(
        default=None, ge=1, description="reuse the white image of this earlier job"
    )
    note: str | None = Field(default=None, max_length=500, description="free text")


@dataclass(frozen=True)
class SweepPlan:
    """A validated sweep with concrete values (stored as the job's request).

    Attributes:
        start_mm, stop_mm, step_mm: the rail range and step (mm).
        frames: number of rail positions.
        exposure_us: exposure (µs).
        settle_s: wait after each move (s).
        calibrate: calibrate at the end.
        white_from_job: job whose white image is reused, or None (capture).
        note: free text.
    """

    start_mm: float
    stop_mm: float
    step_mm: float
    frames: int
    exposure_us: float
    settle_s: float
    calibrate: bool = True
    white_from_job: int | None = None
    note: str | None = None

    def positions_mm(self) -> list[float]:
        """Commanded rail position (mm) of every frame, rounded to 1 nm."""
        return [round(self.start_mm + k * self.step_mm, 6) for k in range(self.frames)]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (what the job store keeps as the request)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SweepPlan:
        """Inverse of :meth:`to_dict` (unknown keys ignored)."""
        known = {k: data[k] for k in cls.__dataclass_fields__ if k in data}
        return cls(**known)


def frame_count(start_mm: float, stop_mm: float, step_mm: float) -> int:
    """Rail positions from ``start_mm`` to ``stop_mm`` (inclusive) in ``step_mm`` steps (mm)."""
    if stop_mm < start_mm or not step_mm > 0:
        return 0
    count = (stop_mm - start_mm) / step_mm + _EPS
    if not math.isfinite(count) or count > 1e9:
        return 1_000_000_000  # absurdly many: the frame limit rejects it with a clear message
    return int(math.floor(count)) + 1


def parse_request(data: SweepRequest | dict[str, Any] | None) -> SweepRequest:
    """A :class:`SweepRequest` from a dict (JSON body); :class:`RequestInvalid` on bad fields."""
    if isinstance(data, SweepRequest):
        return data
    if data is None:
        return SweepRequest()
    if not isinstance(data, dict):
        raise RequestInvalid([("request", f"must be a JSON object, got {type(data).__name__}")])
    try:
        return SweepRequest.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            field = ".".join(str(p) for p in err["loc"]) or "request"
            msg = err["msg"]
            if err["type"] == "extra_forbidden":
                allowed = ", ".join(SweepRequest.model_fields)
                msg = f"unknown field (allowed: {allowed})"
            problems.append((field, msg))
        raise RequestInvalid(problems) from None


def plan_sweep(
    request: SweepRequest | dict[str, Any] | None,
    config: StationConfig,
    *,
    rail_limits_mm: tuple[float, float] | None = None,
    exposure_limits_us: tuple[float, float] | None = None,
) -> SweepPlan:
    """Validate ``request`` against the configuration and the devices; return the plan.

    Args:
        request: the client's request (None: the configured default sweep).
        config: the station configuration (defaults and limits).
        rail_limits_mm: the rail's travel (mm) as the device reports it; the
            configured ``rail.min_mm``/``max_mm`` are used as well.
        exposure_limits_us: the camera's (min, max) exposure (µs), when known.

    Raises:
        RequestInvalid: with every problem found.
    """
    req = parse_request(request)
    sw, cam = config.sweep, config.camera
    start = sw.start_mm if req.start_mm is None else req.start_mm
    stop = sw.stop_mm if req.stop_mm is None else req.stop_mm
    step = sw.step_mm if req.step_mm is None else req.step_mm
    exposure = (
        req.exposure_us if req.exposure_us is not None else (sw.exposure_us or cam.exposure_us)
    )
    settle = (
        req.settle_s
        if req.settle_s is not None
        else (sw.settle_s if sw.settle_s is not None else config.rail.settle_s)
    )
    problems: list[tuple[str, str]] = []

    lo, hi = config.rail.min_mm, config.rail.max_mm
    if rail_limits_mm is not None:
        lo, hi = max(lo, rail_limits_mm[0]), min(hi, rail_limits_mm[1])
    for name, value in (("start_mm", start), ("stop_mm", stop)):
        if not lo - _EPS <= value <= hi + _EPS:
            problems.append(
                (name, f"{value:g} mm is outside the rail's travel [{lo:g}, {hi:g}] mm")
            )
    step_ok = step > 0
    if not step_ok:
        problems.append(("step_mm", f"must be greater than 0 mm, got {step:g} mm"))
    if stop < start:
        problems.append(("stop_mm", f"must not be below start_mm ({start:g} mm), got {stop:g} mm"))
    frames = frame_count(start, stop, step) if step_ok else 0
    limit = min(sw.max_frames, HARD_MAX_FRAMES)
    if step_ok and stop >= start and frames > limit:
        smallest = (stop - start) / (limit - 1) if limit > 1 else float("inf")
        problems.append(
            (
                "step_mm",
                f"{step:g} mm steps from {start:g} to {stop:g} mm make {frames} frames; at most "
                f"{limit} are allowed (sweep.max_frames): use a step of at least "
                f"{math.ceil(smallest * 1e6) / 1e6:g} mm or a shorter range",
            )
        )
    if not exposure > 0:
        problems.append(("exposure_us", f"must be greater than 0 µs, got {exposure:g} µs"))
    elif exposure_limits_us is not None:
        elo, ehi = exposure_limits_us
        if not elo <= exposure <= ehi:
            problems.append(
                (
                    "exposure_us",
                    f"{exposure:g} µs is outside the camera's exposure range [{elo:g}, {ehi:g}] µs",
                )
            )
    if not 0 <= settle <= 60:
        problems.append(("settle_s", f"must be between 0 and 60 s, got {settle:g} s"))
    if problems:
        raise RequestInvalid(problems)
    return SweepPlan(
        start_mm=float(start),
        stop_mm=float(stop),
        step_mm=float(step),
        frames=frames,
        exposure_us=float(exposure),
        settle_s=float(settle),
        calibrate=req.calibrate,
        white_from_job=req.white_from_job,
        note=req.note,
    )


__all__ = [
    "HARD_MAX_FRAMES",
    "RequestInvalid",
    "SweepPlan",
    "SweepRequest",
    "frame_count",
    "parse_request",
    "plan_sweep",
]
