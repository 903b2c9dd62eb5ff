"""Describe the station's open devices, JSON-ready: identity and state of the camera,
the rail, the XY stage and (when anything is simulated) the simulated bench.

Every entry has a ``name``; a device that cannot be read has an ``error`` entry (its
message) instead of failing the whole description. Positions are mm (``None`` while an
axis is not homed), exposure µs, gain dB, sizes px, temperature °C.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from drivers.axis import Axis
from drivers.camera import Camera, CameraSettings, Roi
from drivers.errors import DeviceError
from drivers.zaber import XYStage
from station.config import StationConfig
from station.config_sections import XYStageConfig


def _error(name: str, exc: BaseException) -> dict[str, Any]:
    return {"name": name, "error": str(exc)}


def describe_camera(camera: Camera, settings: CameraSettings | None) -> dict[str, Any]:
    """Identity, sensor, ROI, pixel format, exposure and gain of an open camera."""
    try:
        info = camera.info()
    except DeviceError as exc:
        return _error("camera", exc)
    out: dict[str, Any] = {
        "name": "camera",
        "backend": info.backend,
        "vendor": info.vendor,
        "model": info.model,
        "serial": info.serial,
        "device": info.device,
        "sensor_px": [info.sensor_width, info.sensor_height],
    }
    if settings is not None:
        roi = settings.roi or Roi(info.sensor_width, info.sensor_height)
        out.update(
            roi=dataclasses.asdict(roi),
            pixel_format=settings.pixel_format,
            exposure_us=settings.exposure_us,
            gain=settings.gain,
        )
    if info.has_temperature:
        out["temperature_c"] = camera.temperature_c()
    return out


def _describe_axis(axis: Axis, name: str) -> dict[str, Any]:
    try:
        identity = dataclasses.asdict(axis.identity())
        limits = axis.limits_mm()
        homed = axis.is_homed()
        position = axis.position_mm() if homed else None
    except DeviceError as exc:
        return _error(name, exc)
    return {
        "name": name,
        "identity": identity,
        "homed": homed,
        "position_mm": position,
        "limits_mm": [limits.min_mm, limits.max_mm],
    }


def describe_rail(rail: Axis, config: StationConfig) -> dict[str, Any]:
    """Identity, homed state, position (mm) and object distance u (mm) of the rail."""
    out = _describe_axis(rail, "rail")
    if out.get("position_mm") is not None:
        out["object_distance_mm"] = config.rail.object_distance_mm(out["position_mm"])
    return out


def describe_xy(xy: XYStage, config: XYStageConfig) -> dict[str, Any]:
    """Both axes of the XY stage, the stage position and the board offset (mm)."""
    x = _describe_axis(xy.x, "xy stage x")
    y = _describe_axis(xy.y, "xy stage y")
    out: dict[str, Any] = {"name": "xy stage", "x": x, "y": y}
    errors = [e["error"] for e in (x, y) if "error" in e]
    if errors:
        out["error"] = "; ".join(errors)
        return out
    out["homed"] = bool(x["homed"] and y["homed"])
    if out["homed"]:
        pos = (x["position_mm"], y["position_mm"])
        out["position_mm"] = list(pos)
        out["board_offset_mm"] = [
            pos[0] - config.alignment.x_mm,
            pos[1] - config.alignment.y_mm,
        ]
    else:
        out["position_mm"] = None
    return out


def describe_bench(bench: Any) -> dict[str, Any]:
    """True (emulator-side) positions and the scene of the simulated bench."""
    out: dict[str, Any] = {"speedup": bench.speedup}
    try:
        out["emulator"] = bench.url
    except RuntimeError:
        pass
    for key, read in (
        ("rail_true_mm", bench.rail_mm),
        ("stage_true_mm", bench.stage_xy_mm),
        ("scene", bench.scene_state),
    ):
        try:
            value = read()
        except (RuntimeError, DeviceError) as exc:
            out[key] = {"error": str(exc)}
            continue
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = dataclasses.asdict(value)
        out[key] = value
    return out


__all__ = ["describe_bench", "describe_camera", "describe_rail", "describe_xy"]
