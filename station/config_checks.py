"""Cross-field checks of the station configuration: problems that involve several keys.

:func:`cross_field_problems` returns ``(dotted key, reason)`` pairs; keys whose
own values were invalid (and replaced by defaults to check the rest) are passed
as ``invalid`` so that no problem is reported about a default.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Mapping
from typing import Any

from .config_sections import (
    ENV_API_KEYS,
    MIN_API_KEY_LENGTH,
    BoardConfig,
    CameraConfig,
    OpticsConfig,
    RailConfig,
    ServerConfig,
    StagePosition,
    StorageConfig,
    SweepConfig,
    XYStageConfig,
    ZaberLinkConfig,
)


def shares_chain(rail: RailConfig, xy: XYStageConfig) -> bool:
    if xy.port is None:
        return rail.driver == xy.driver
    return xy.driver == rail.driver == "zaber" and xy.port == rail.port


def api_key_problems(keys: list[str], key_name: str) -> list[tuple[str, str]]:
    """Problems of a list of API keys, as ``(key, reason)`` with ``key_name[i]`` keys."""
    out: list[tuple[str, str]] = []
    seen: set[str] = set()
    for i, k in enumerate(keys):
        where = f"{key_name}[{i}]"
        if len(k) < MIN_API_KEY_LENGTH:
            out.append(
                (where, f"API key too short ({len(k)} characters, need ≥ {MIN_API_KEY_LENGTH})")
            )
        elif re.search(r"\s", k):
            out.append((where, "API key must not contain whitespace"))
        elif k in seen:
            out.append((where, "duplicate API key"))
        seen.add(k)
    return out


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Problems:
    """Collects cross-field problems, dropping those that depend on keys known to be invalid.

    ``invalid`` holds dotted keys whose values failed validation and were replaced
    by defaults to check the rest; a problem whose ``deps`` (or key) is at or
    below one of them would be about the default, not the file, and is dropped.
    """

    def __init__(self, invalid: frozenset[str] = frozenset()) -> None:
        self.invalid = invalid
        self.items: list[tuple[str, str]] = []

    def _tainted(self, key: str) -> bool:
        return any(key == k or key.startswith((k + ".", k + "[")) for k in self.invalid)

    def add(self, key: str, reason: str, *deps: str) -> None:
        if not any(self._tainted(k) for k in (key, *deps)):
            self.items.append((key, reason))


def cross_field_problems(
    sections: Mapping[str, Any], invalid: frozenset[str] = frozenset()
) -> list[tuple[str, str]]:
    """Problems that involve several keys, as ``(key, reason)``.

    ``sections`` maps section names to validated section models; a missing or
    None section (it could not be validated) skips the checks that need it.
    ``invalid``: dotted keys that failed validation (their defaults were used).
    """
    out = _Problems(invalid)
    cam: CameraConfig | None = sections.get("camera")
    rail: RailConfig | None = sections.get("rail")
    xy: XYStageConfig | None = sections.get("xy_stage")
    optics: OpticsConfig | None = sections.get("optics")
    board: BoardConfig | None = sections.get("board")
    sweep: SweepConfig | None = sections.get("sweep")
    storage: StorageConfig | None = sections.get("storage")
    server: ServerConfig | None = sections.get("server")
    if cam is not None:
        _camera_problems(out, cam)
    if rail is not None:
        _link_problems(out, "rail", rail)
        if rail.min_mm >= rail.max_mm:
            out.add(
                "rail.max_mm",
                f"must exceed rail.min_mm ({rail.min_mm:g}), got {rail.max_mm:g}",
                "rail.min_mm",
            )
    if xy is not None:
        _xy_problems(out, xy, rail)
    if optics is not None:
        _optics_problems(out, optics)
    if board is not None and board.reference_gap_mm >= board.square_mm:
        out.add(
            "board.reference_gap_mm",
            f"must be smaller than board.square_mm ({board.square_mm:g}), "
            f"got {board.reference_gap_mm:g}",
            "board.square_mm",
        )
    if sweep is not None:
        _sweep_problems(out, sweep, rail, optics)
    if storage is not None:
        if storage.data_dir.exists() and not storage.data_dir.is_dir():
            out.add("storage.data_dir", f"{storage.data_dir} exists and is not a directory")
        path = storage.database_path
        if path is not None and path.is_dir():
            out.add("storage.database", f"{path} is a directory, not a file")
    if server is not None:
        _server_problems(out, server)
    return out.items


def _camera_problems(out: _Problems, cam: CameraConfig) -> None:
    given = cam.model_fields_set
    if cam.backend == "simulated":
        from calibration.presets import preset_names

        if cam.preset not in preset_names():
            out.add(
                "camera.preset",
                f"unknown preset {cam.preset!r}: choose one of {', '.join(preset_names())}",
            )
        for key in ("address", "serial", "cti"):
            if key in given:
                out.add(
                    f"camera.{key}",
                    'not used with backend = "simulated" (set backend = "aravis" or "harvesters")',
                    "camera.backend",
                )
        if cam.trigger != "software":
            out.add("camera.trigger", 'the simulated camera has only "software"')
    else:
        for key in ("preset", "seed", "principal_point_px", "frame_cache"):
            if key in given:
                out.add(f"camera.{key}", 'only used with backend = "simulated"', "camera.backend")
        if cam.interface == "usb3" and cam.backend != "aravis":
            out.add("camera.interface", 'only used with backend = "aravis"', "camera.backend")
        if cam.interface == "usb3" and cam.serial is None:
            out.add(
                "camera.serial",
                'field required (interface = "usb3" opens the camera by serial)',
                "camera.interface",
            )
        if cam.backend == "aravis" and cam.address is None and cam.serial is None:
            out.add(
                "camera.address",
                'field required (backend = "aravis" needs address or serial)',
                "camera.backend",
                "camera.serial",
            )
        if cam.backend == "harvesters":
            if cam.cti is None:
                out.add(
                    "camera.cti",
                    'field required (backend = "harvesters" needs the GenTL .cti file)',
                    "camera.backend",
                )
            elif not cam.cti.is_file():
                out.add("camera.cti", f"file not found: {cam.cti}")
    size_deps = ("camera.width", "camera.height", "camera.backend", "camera.preset")
    width, height = cam.sensor_size_px
    if cam.roi is not None:
        r = cam.roi
        if r.offset_x + r.width > width:
            out.add(
                "camera.roi.width",
                f"ROI columns {r.offset_x}..{r.offset_x + r.width - 1} "
                f"leave the {width} px wide sensor",
                *size_deps,
            )
        if r.offset_y + r.height > height:
            out.add(
                "camera.roi.height",
                f"ROI rows {r.offset_y}..{r.offset_y + r.height - 1} "
                f"leave the {height} px high sensor",
                *size_deps,
            )
    if cam.principal_point_px is not None:
        x, y = cam.principal_point_px
        if not (0 <= x <= width - 1 and 0 <= y <= height - 1):
            out.add(
                "camera.principal_point_px",
                f"({x:g}, {y:g}) is outside the {width}×{height} px sensor",
                *size_deps,
            )


def _link_problems(out: _Problems, name: str, link: ZaberLinkConfig) -> None:
    if link.driver == "zaber" and link.port is None and name == "rail":
        out.add(
            f"{name}.port",
            'field required (driver = "zaber" needs a port such as /dev/ttyUSB0 or '
            "socket://host:port)",
            f"{name}.driver",
        )
    if link.driver == "emulated" and link.port is not None:
        out.add(
            f"{name}.port",
            'not used with driver = "emulated" (the station starts the emulator on a pty); '
            'remove it or set driver = "zaber"',
            f"{name}.driver",
        )


def _xy_problems(out: _Problems, xy: XYStageConfig, rail: RailConfig | None) -> None:
    _link_problems(out, "xy_stage", xy)
    if xy.driver == "zaber" and xy.port is None and rail is not None and rail.driver != "zaber":
        out.add(
            "xy_stage.port",
            "field required (the rail is emulated, so the XY stage cannot share its chain)",
            "xy_stage.driver",
            "rail.driver",
        )
    for name, ax in (("x", xy.x), ("y", xy.y)):
        if ax.min_mm >= ax.max_mm:
            out.add(
                f"xy_stage.{name}.max_mm",
                f"must exceed xy_stage.{name}.min_mm ({ax.min_mm:g}), got {ax.max_mm:g}",
            )
    if (xy.x.device, xy.x.axis) == (xy.y.device, xy.y.axis):
        out.add(
            "xy_stage.y",
            f"same device {xy.y.device} axis {xy.y.axis} as xy_stage.x",
            "xy_stage.x",
        )
    if rail is not None and shares_chain(rail, xy):
        chain_deps = ("rail.device", "rail.axis", "rail.port", "rail.driver", "xy_stage.port")
        for name, ax in (("x", xy.x), ("y", xy.y)):
            if (ax.device, ax.axis) == (rail.device, rail.axis):
                out.add(
                    f"xy_stage.{name}",
                    f"device {ax.device} axis {ax.axis} is the rail's (same chain)",
                    *chain_deps,
                )
    for pos_name in ("alignment", "white"):
        pos: StagePosition = getattr(xy, pos_name)
        for name, ax, value in (("x", xy.x, pos.x_mm), ("y", xy.y, pos.y_mm)):
            if not ax.min_mm <= value <= ax.max_mm:
                out.add(
                    f"xy_stage.{pos_name}.{name}_mm",
                    f"{value:g} is outside the {name} travel {ax.min_mm:g}..{ax.max_mm:g} mm",
                    f"xy_stage.{name}",
                )


def _optics_problems(out: _Problems, optics: OpticsConfig) -> None:
    if optics.mla_pitch_mm <= optics.pixel_pitch_mm:
        out.add(
            "optics.mla_pitch_mm",
            f"must exceed optics.pixel_pitch_mm ({optics.pixel_pitch_mm:g}), "
            f"got {optics.mla_pitch_mm:g}",
            "optics.pixel_pitch_mm",
        )
    if optics.designed_b_mm is not None and optics.designed_b_mm <= optics.mla_focal_mm:
        out.add(
            "optics.designed_b_mm",
            f"must exceed optics.mla_focal_mm ({optics.mla_focal_mm:g}) in Keplerian mode, "
            f"got {optics.designed_b_mm:g}",
            "optics.mla_focal_mm",
        )


def _sweep_problems(
    out: _Problems, sweep: SweepConfig, rail: RailConfig | None, optics: OpticsConfig | None
) -> None:
    if sweep.stop_mm < sweep.start_mm:
        out.add(
            "sweep.stop_mm",
            f"must not be below sweep.start_mm ({sweep.start_mm:g}), got {sweep.stop_mm:g}",
            "sweep.start_mm",
        )
        return
    if sweep.frame_count > sweep.max_frames:
        out.add(
            "sweep.step_mm",
            f"gives {sweep.frame_count} frames, more than sweep.max_frames = {sweep.max_frames}",
            "sweep.start_mm",
            "sweep.stop_mm",
            "sweep.max_frames",
        )
    if rail is None or rail.min_mm >= rail.max_mm:
        return
    for key in ("start_mm", "stop_mm"):
        value = getattr(sweep, key)
        if not rail.min_mm <= value <= rail.max_mm:
            out.add(
                f"sweep.{key}",
                f"{value:g} is outside the rail limits {rail.min_mm:g}..{rail.max_mm:g} mm",
                "rail.min_mm",
                "rail.max_mm",
            )
    if optics is not None:
        u = min(rail.object_distance_mm(sweep.start_mm), rail.object_distance_mm(sweep.stop_mm))
        if u <= optics.main_focal_mm:
            out.add(
                "rail.zero_object_distance_mm",
                f"the sweep reaches object distance {u:g} mm, not beyond the main focal "
                f"length {optics.main_focal_mm:g} mm (check rail.direction)",
                "rail.direction",
                "sweep.start_mm",
                "sweep.stop_mm",
                "optics.main_focal_mm",
            )


def _server_problems(out: _Problems, server: ServerConfig) -> None:
    for key, reason in api_key_problems(server.api_keys, "server.api_keys"):
        out.add(key, reason)
    for i, origin in enumerate(server.cors_origins):
        if origin != "*" and not re.match(r"^https?://[^/\s?#]+$", origin):
            out.add(
                f"server.cors_origins[{i}]",
                f"must be an origin like http://host:port (no path) or *, got {origin!r}",
            )
    if not is_loopback(server.host) and not server.api_keys:
        out.add(
            "server.api_keys",
            f"required when server.host ({server.host}) is not a loopback address "
            f"(or set ${ENV_API_KEYS})",
            "server.host",
        )
