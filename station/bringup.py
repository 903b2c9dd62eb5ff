"""``lfcal devices --check``: the bring-up report a lab runs once on new hardware.

Each line is ``PASS`` or ``FAIL``, a subject and what was measured::

    PASS rail identity: Zaber device id 50081, SN 100001, firmware 7.38
    PASS rail settings: limit.min 0, limit.max 2099738 (0.000..100.000 mm covers 0..100 mm) ...
    PASS rail move: +1.000 mm and back, read-back error 0.00 um (tolerance 5 um)
    PASS camera identity: Basler acA5472-17um SN 40012345 firmware 1.2.3 (aravis)
    PASS camera settings: PixelFormat Mono12p, ExposureTime 10000 us, Gain 0 dB ...
    FAIL camera transport: the GVSP socket buffer is capped at net.core.rmem_max ...
    PASS camera grab: 5120x5120 Mono12p (12 bit), counts 64..3890, temperature 41.3 C

What is checked:

* every axis: identity and firmware (series 6 or 7); the settings the station relies on
  read back (``limit.min``/``limit.max`` against the configured travel, ``maxspeed``,
  ``accel``, how the configured speed reaches the device, ``comm.checksum``); no
  warning flag other than the expected ones; one short move (1 mm, or less on a short
  travel) away and back with the read-back error against ``position_tolerance_um``.
  Axes without a reference are homed first (the check moves the stages);
* the camera: identity and firmware; every configured setting read back (pixel format,
  exposure, gain and the feature it went to, black level, trigger, flat field, ROI);
  start-up transport warnings (a socket buffer capped by ``net.core.rmem_max``); one
  test grab with pixel format, bit depth, min/max counts (blank or saturated is a FAIL)
  and ``DeviceTemperature``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.errors import DeviceError
from station.config import StationConfig


@dataclass(frozen=True)
class CheckLine:
    """One line of the report."""

    ok: bool
    subject: str
    detail: str

    def __str__(self) -> str:
        return f"{'PASS' if self.ok else 'FAIL'} {self.subject}: {self.detail}"


#: Warning flags a connected, idle axis may show without anything being wrong.
_HARMLESS_FLAGS = frozenset({"none", "WR", "NI"})


def _guard(subject: str, action: Callable[[], CheckLine]) -> CheckLine:
    try:
        return action()
    except DeviceError as exc:
        return CheckLine(False, subject, " ".join(str(exc).split()))


def _axis_lines(
    name: str, axis: Any, travel_mm: tuple[float, float], tol_um: float
) -> list[CheckLine]:
    lines: list[CheckLine] = []

    def identity() -> CheckLine:
        ident = axis.identity()
        major = str(ident.firmware).split(".")[0]
        ok = major in ("6", "7")
        note = "" if ok else " (not a firmware 6 or 7 ASCII device: untested)"
        return CheckLine(
            ok,
            f"{name} identity",
            f"{ident.vendor} {ident.model}, SN {ident.serial}, firmware {ident.firmware}{note}",
        )

    def settings() -> CheckLine:
        if not hasattr(axis, "read_back"):
            limits = axis.limits_mm()
            return CheckLine(
                True, f"{name} settings", f"travel {limits.min_mm}..{limits.max_mm} mm"
            )
        values = axis.read_back()
        limits = axis.limits_mm()
        low = axis.usteps_to_mm(int(values["limit.min"]))
        high = axis.usteps_to_mm(int(values["limit.max"]))
        slack = tol_um / 1000.0  # a travel one microstep short of nominal still covers
        covers = low <= travel_mm[0] + slack and travel_mm[1] <= high + slack
        flags = set(values["warnings"].split())
        flags_ok = flags <= _HARMLESS_FLAGS
        ok = covers and flags_ok
        detail = (
            f"limit.min {values['limit.min']}, limit.max {values['limit.max']} "
            f"({low:.3f}..{high:.3f} mm {'covers' if covers else 'does NOT cover'} the "
            f"configured {travel_mm[0]:g}..{travel_mm[1]:g} mm; usable "
            f"{limits.min_mm:g}..{limits.max_mm:g} mm), maxspeed {values['maxspeed']}, "
            f"accel {values['accel']}, configured speed: {axis.speed_mode}, "
            f"comm.checksum {values['comm.checksum']}, warnings {values['warnings']}"
        )
        return CheckLine(ok, f"{name} settings", detail)

    def move() -> CheckLine:
        if not axis.is_homed():
            axis.home()
        limits = axis.limits_mm()
        start = axis.position_mm()
        step = min(1.0, (limits.max_mm - limits.min_mm) / 4.0)
        target = start + step if start + step <= limits.max_mm else start - step
        reached = axis.move_abs_mm(target)
        back = axis.move_abs_mm(start)
        error_um = max(abs(reached - target), abs(back - start)) * 1000.0
        ok = math.isfinite(error_um) and error_um <= tol_um
        return CheckLine(
            ok,
            f"{name} move",
            f"{target - start:+.3f} mm and back from {start:.3f} mm, read-back error "
            f"{error_um:.2f} um (tolerance {tol_um:g} um)",
        )

    for subject, check in (("identity", identity), ("settings", settings), ("move", move)):
        lines.append(_guard(f"{name} {subject}", check))
    return lines


def _camera_lines(devices: Any, config: StationConfig, timeout_s: float) -> list[CheckLine]:
    cam = config.camera
    camera = devices.camera

    def read_settings() -> Any:
        read = getattr(camera, "settings", None)
        return read() if callable(read) else devices.camera_settings

    def identity() -> CheckLine:
        info = camera.info()
        return CheckLine(
            True,
            "camera identity",
            f"{info.vendor} {info.model} SN {info.serial} firmware {info.firmware or '-'} "
            f"({info.backend}, {info.device}), sensor {info.sensor_width}x{info.sensor_height}",
        )

    def settings() -> CheckLine:
        info = camera.info()
        applied = read_settings()
        problems = []
        if applied.pixel_format != cam.pixel_format:
            problems.append(f"PixelFormat {applied.pixel_format} (configured {cam.pixel_format})")
        if applied.exposure_us is None or not math.isclose(
            applied.exposure_us, cam.exposure_us, rel_tol=0.01, abs_tol=1.0
        ):
            problems.append(f"exposure {applied.exposure_us} us (configured {cam.exposure_us:g})")
        if applied.gain is None or not math.isclose(applied.gain, cam.gain, abs_tol=0.05):
            problems.append(f"gain {applied.gain} (configured {cam.gain:g})")
        if applied.trigger != cam.trigger:
            problems.append(f"trigger {applied.trigger} (configured {cam.trigger})")
        if cam.flat_field == "off" and applied.flat_field != "off":
            problems.append("on-camera flat-field correction is on")
        roi = applied.roi
        if (
            cam.roi is not None
            and roi is not None
            and (
                (roi.width, roi.height, roi.offset_x, roi.offset_y)
                != (cam.roi.width, cam.roi.height, cam.roi.offset_x, cam.roi.offset_y)
            )
        ):
            problems.append(f"ROI {roi} (configured {cam.roi})")
        unit = {"Gain": " dB", "GainRaw": " (raw units)"}.get(info.gain_feature or "", "")
        roi_text = f"{roi.width}x{roi.height}+{roi.offset_x}+{roi.offset_y}" if roi else "-"
        detail = (
            f"PixelFormat {applied.pixel_format}, exposure {applied.exposure_us:g} us, "
            f"{info.gain_feature or 'gain'} {applied.gain:g}{unit}, black level "
            f"{'-' if applied.black_level is None else f'{applied.black_level:g}'}, trigger "
            f"{applied.trigger}, flat field {applied.flat_field}, ROI {roi_text}"
            if applied.exposure_us is not None and applied.gain is not None
            else str(applied)
        )
        if problems:
            detail += "; differs: " + "; ".join(problems)
        return CheckLine(not problems, "camera settings", detail)

    def transport() -> CheckLine:
        notes = list(getattr(camera, "warnings", []))
        if notes:
            return CheckLine(False, "camera transport", "; ".join(notes))
        return CheckLine(True, "camera transport", "no warning")

    def grab() -> CheckLine:
        frame = camera.grab(timeout_s)
        pixels = frame.pixels
        low, high = int(pixels.min()), int(pixels.max())
        blank = low == high
        saturated = high >= frame.max_count
        temperature = (
            "not offered" if frame.temperature_c is None else f"{frame.temperature_c:.1f} C"
        )
        detail = (
            f"{frame.width}x{frame.height} {frame.pixel_format} ({frame.bit_depth} bit), "
            f"counts {low}..{high} of 0..{frame.max_count}, temperature {temperature}"
        )
        if blank:
            detail += "; blank frame (lens cap? light?)"
        elif saturated:
            detail += "; saturated (lower the exposure or gain)"
        return CheckLine(not (blank or saturated), "camera grab", detail)

    return [
        _guard("camera identity", identity),
        _guard("camera settings", settings),
        _guard("camera transport", transport),
        _guard("camera grab", grab),
    ]


def bring_up_report(devices: Any, config: StationConfig) -> list[CheckLine]:
    """Run every check on the open ``devices`` (``station.devices.StationDevices``)."""
    lines: list[CheckLine] = []
    rail = config.rail
    lines += _axis_lines(
        "rail", devices.rail, (rail.min_mm, rail.max_mm), rail.position_tolerance_um
    )
    xy = config.xy_stage
    for name, axis, travel in (
        ("xy stage x", devices.xy.x, (xy.x.min_mm, xy.x.max_mm)),
        ("xy stage y", devices.xy.y, (xy.y.min_mm, xy.y.max_mm)),
    ):
        lines += _axis_lines(name, axis, travel, xy.position_tolerance_um)
    lines += _camera_lines(devices, config, config.camera.timeout_s)
    return lines


__all__ = ["CheckLine", "bring_up_report"]
