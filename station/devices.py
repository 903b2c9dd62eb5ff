"""Open the station's devices -- camera, rail, XY stage -- from its configuration.

:func:`open_devices` builds the real drivers or the simulated bench, as the
configuration says, and returns them as :class:`StationDevices`::

    with open_devices(load_config("config/simulated.toml")) as devices:
        devices.rail.move_abs_mm(50.0)                          # u = 300 mm
        frame = devices.camera.grab(config.camera.timeout_s)

* rail: a Zaber axis on ``rail.port`` (``driver = "zaber"``) or on the emulator's pty
  (``"emulated"``); the XY stage shares the rail's port when it is on the rail's chain
  (no ``xy_stage.port``), otherwise it gets its own port;
* camera: Aravis by ``camera.address`` (unicast; never GigE discovery), harvesters by
  ``camera.cti`` + ``camera.serial``, or the simulated camera of the bench; it is
  opened and configured with ``[camera]`` (pixel format, exposure, gain, ROI);
* simulated/emulated parts are a backend like any other: :data:`SIMULATION_BACKEND` names
  its modules (``drivers.sim.bench``, ``drivers.sim.plenoptic_scene``), loaded **by name**
  only when the configuration asks for them (``camera.backend = "simulated"``,
  ``driver = "emulated"``); production code never imports ``drivers.sim``, and caching
  rendered frames (``camera.frame_cache``) is the simulated camera's own business;
* homing: each stage is homed at open when its ``home_on_connect`` is true (override
  with ``home=``); rail and XY stage home at the same time.

Every device is tried even when another fails; then, if any failed, everything that
did open is closed again and :class:`DevicesError` lists one typed
:class:`drivers.errors.DeviceError` per failing device (its message names the device
and what to check: port path, chain, camera address, .cti file ...).

Units: mm, µs, dB, px.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from drivers.axis import Axis
from drivers.camera import Camera, CameraSettings, Roi, TransportSettings, create_camera
from drivers.errors import DeviceError, PortUnavailable
from drivers.zaber import XYStage, ZaberAxis, ZaberAxisConfig, ZaberPort, open_rail, open_xy_stage
from station.config import StationConfig
from station.config_sections import RailConfig, XYStageConfig

SIMULATION_BACKEND: dict[str, str] = {
    "bench": "drivers.sim.bench",
    "scene": "drivers.sim.plenoptic_scene",
}
"""Modules of the simulated backend, imported by name when the config asks for them:
the bench (emulated stages and the simulated camera) and the plenoptic scene it shows."""

BENCH_MODULE = SIMULATION_BACKEND["bench"]

SIM_REFERENCE_EXPOSURE_US = 10000.0
"""Exposure (µs) at which the simulated scene has the preset's white level."""

ROLES = ("camera", "rail", "xy_stage")
"""Device roles, in the order they are reported."""

ROLE_NAMES = {"camera": "camera", "rail": "rail", "xy_stage": "xy stage"}
"""Human-readable device names."""


class DevicesError(DeviceError):
    """One or more station devices could not be opened (the others were closed again).

    Attributes:
        failures: role (``"camera"``, ``"rail"``, ``"xy_stage"``) -> the typed error.
        opened: :meth:`StationDevices.describe`-style entries of the devices that did
            open, taken before they were closed.
    """

    default_hint = "the configuration and the devices named above"

    def __init__(
        self, failures: dict[str, DeviceError], *, opened: dict[str, Any] | None = None
    ) -> None:
        self.failures = dict(failures)
        self.opened = dict(opened or {})
        lines = "; ".join(f"{ROLE_NAMES.get(k, k)}: {e}" for k, e in self.failures.items())
        count = len(self.failures)
        super().__init__(
            f"{count} device{'s' if count != 1 else ''} could not be opened: {lines}",
            device="station",
            hint="",
        )


# --------------------------------------------------------------------------- devices


@dataclass
class StationDevices:
    """The opened devices of the station.  Close with :meth:`close` or ``with``.

    Attributes:
        camera: the opened, configured camera.
        rail: the board rail (homed if ``rail.home_on_connect``).
        xy: the XY stage (homed if ``xy_stage.home_on_connect``).
        config: the configuration the devices were opened with.
        camera_settings: the camera settings in force after opening (read back).
        bench: the ``drivers.sim.bench.SimulatedBench`` when anything is simulated
            (true positions, fault injection), else None.
    """

    camera: Camera
    rail: Axis
    xy: XYStage
    config: StationConfig
    camera_settings: CameraSettings
    bench: Any | None = None
    _ports: list[ZaberPort] = field(default_factory=list, repr=False)

    def close(self) -> None:
        """Close the camera, the stages, the ports and the simulated bench (idempotent)."""
        _close_all(self.camera, self.xy, self.rail, self._ports, self.bench)

    def __enter__(self) -> StationDevices:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def describe(self) -> dict[str, Any]:
        """Identity and state of every device, JSON-ready.

        Keys ``camera``, ``rail``, ``xy_stage`` (and ``simulation`` with the bench's true
        positions when simulated).  A device that cannot be read has an ``error`` entry
        (its message) instead of failing the whole description.
        """
        settings = self.camera_settings
        read_back = getattr(self.camera, "settings", None)
        if callable(read_back):
            try:
                settings = read_back()
            except DeviceError:
                pass
        out: dict[str, Any] = {
            "camera": describe_camera(self.camera, settings),
            "rail": describe_rail(self.rail, self.config),
            "xy_stage": describe_xy(self.xy, self.config.xy_stage),
        }
        if self.bench is not None:
            out["simulation"] = describe_bench(self.bench)
        return out

    def object_distance_mm(self) -> float:
        """Object distance u (mm) at the rail's read-back position."""
        return self.config.rail.object_distance_mm(self.rail.position_mm())


def _close_all(*things: Any) -> None:
    """Close each thing (lists too), ignoring device errors: closing is best effort."""
    for thing in things:
        if thing is None:
            continue
        if isinstance(thing, list):
            _close_all(*thing)
            continue
        try:
            thing.close()
        except (DeviceError, OSError):
            pass


# --------------------------------------------------------------------------- describe


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


# --------------------------------------------------------------------------- open


def _axis_config(
    link: RailConfig | XYStageConfig,
    name: str,
    device: int,
    axis: int,
    limits: tuple[float, float],
    scale: float,
) -> ZaberAxisConfig:
    return ZaberAxisConfig(
        name=name,
        device=device,
        axis=axis,
        microstep_um=link.microstep_um,
        tolerance_um=link.position_tolerance_um,
        speed_mm_s=link.max_speed_mm_s,
        accel_mm_s2=link.accel_mm_s2,
        soft_limits_mm=limits,
        timeout_scale=scale,
    )


def _camera_settings(config: StationConfig) -> CameraSettings:
    cam = config.camera
    roi = None
    if cam.roi is not None:
        roi = Roi(cam.roi.width, cam.roi.height, cam.roi.offset_x, cam.roi.offset_y)
    return CameraSettings(
        pixel_format=cam.pixel_format,
        exposure_us=cam.exposure_us,
        gain=cam.gain,
        roi=roi,
        black_level=cam.black_level,
        trigger=cam.trigger,
        trigger_activation=cam.trigger_activation,
        flat_field=cam.flat_field,
    )


def transport_settings(config: StationConfig) -> TransportSettings:
    """``[camera.transport]`` as the drivers take it."""
    t = config.camera.transport
    return TransportSettings(
        packet_size=t.packet_size,
        packet_delay_ns=t.packet_delay_ns,
        throughput_limit_bps=t.throughput_limit_bps,
        buffer_count=t.buffer_count,
        socket_buffer_bytes=t.socket_buffer_bytes,
        frame_retention_ms=t.frame_retention_ms,
        packet_resend=t.packet_resend,
        packet_socket=t.packet_socket,
    )


def _make_scene(config: StationConfig) -> Any:
    """The plenoptic scene of the simulated camera (``[camera]`` preset and size)."""
    scene_module = importlib.import_module(SIMULATION_BACKEND["scene"])
    cam = config.camera
    try:
        return scene_module.scene_from_preset(
            cam.preset,
            width=cam.width,
            height=cam.height,
            principal_point_px=cam.principal_point_px,
        )
    except ValueError as exc:
        raise DeviceError(
            f"cannot build the simulated camera: {exc}",
            device="camera (simulated)",
            hint="camera.preset, camera.width/height and camera.principal_point_px",
        ) from None


def _make_bench(config: StationConfig, scene: Any | None, speedup: float) -> Any:
    """The simulated bench (started) for the emulated stages of ``config`` and ``scene``.

    The bench has one emulated chain: the rail and the XY stage when both are emulated,
    otherwise only the emulated one (the other is real and feeds the scene through
    ``use_rail_position`` / ``use_stage_position``).
    """
    bench_module = importlib.import_module(SIMULATION_BACKEND["bench"])
    BenchAxis = bench_module.BenchAxis
    rail = xy_x = xy_y = None
    if config.rail.driver == "emulated":
        r = config.rail
        rail = BenchAxis(
            device=r.device,
            axis=r.axis,
            microstep_um=r.microstep_um,
            travel_mm=max(r.max_mm, 1.0),
            speed_mm_s=r.max_speed_mm_s,
            accel_mm_s2=r.accel_mm_s2,
            start_mm=min(10.0, max(r.max_mm, 1.0)),
        )
    xy = config.xy_stage
    if xy.driver == "emulated":
        xy_x, xy_y = (
            BenchAxis(
                device=a.device,
                axis=a.axis,
                microstep_um=xy.microstep_um,
                travel_mm=max(a.max_mm, 1.0),
                speed_mm_s=xy.max_speed_mm_s,
                accel_mm_s2=xy.accel_mm_s2,
                start_mm=min(10.0, max(a.max_mm, 1.0)),
            )
            for a in (xy.x, xy.y)
        )
    try:
        bench = bench_module.SimulatedBench(
            scene,
            zero_object_distance_mm=config.rail.zero_object_distance_mm,
            direction=config.rail.direction,
            rail=rail,
            stage_x=xy_x,
            stage_y=xy_y,
            alignment_mm=(xy.alignment.x_mm, xy.alignment.y_mm),
            speedup=speedup,
            camera_seed=config.camera.seed,
            reference_exposure_us=SIM_REFERENCE_EXPOSURE_US,
            frame_cache=config.camera.frame_cache if scene is not None else None,
        )
        return bench.start()
    except (OSError, ValueError) as exc:
        raise DeviceError(
            f"cannot start the simulated bench: {exc}",
            device="simulated bench",
            hint="that pseudo-terminals are available (/dev/ptmx) and the emulated "
            "device/axis numbers in [rail] and [xy_stage] do not collide",
        ) from None


def _as_device_error(exc: Exception, name: str) -> DeviceError:
    if isinstance(exc, DeviceError):
        return exc
    return DeviceError(f"{type(exc).__name__}: {exc}", device=name)


def open_devices(
    config: StationConfig, *, home: bool | None = None, emulator_speedup: float = 1.0
) -> StationDevices:
    """Open (and configure, and home) the camera, the rail and the XY stage.

    Args:
        config: the station configuration.
        home: home the stages now; None: as ``rail.home_on_connect`` and
            ``xy_stage.home_on_connect`` say.
        emulator_speedup: emulated motion runs this many times faster than real time.

    Raises:
        DevicesError: one or more devices failed (``failures`` has one typed
            :class:`DeviceError` per failing device); nothing is left open.
    """
    if not emulator_speedup > 0:
        raise ValueError("emulator_speedup must be positive")
    failures: dict[str, DeviceError] = {}
    bench: Any | None = None
    ports: list[ZaberPort] = []
    rail: ZaberAxis | None = None
    xy: XYStage | None = None
    camera: Camera | None = None
    settings: CameraSettings | None = None
    try:
        simulated = {
            "camera": config.camera.backend == "simulated",
            "rail": config.rail.driver == "emulated",
            "xy_stage": config.xy_stage.driver == "emulated",
        }
        scene = None
        if simulated["camera"]:
            try:
                scene = _make_scene(config)
            except DeviceError as exc:
                failures["camera"] = exc
        if scene is not None or simulated["rail"] or simulated["xy_stage"]:
            try:
                bench = _make_bench(config, scene, emulator_speedup)
            except DeviceError as exc:
                for role, is_simulated in simulated.items():
                    if is_simulated:
                        failures.setdefault(role, exc)
        rail, xy = _open_stages(config, bench, emulator_speedup, ports, failures)
        if bench is not None and bench.rail is None and rail is not None:
            bench.use_rail_position(rail.position_mm)
        if bench is not None and bench.stage_x is None and xy is not None:
            bench.use_stage_position(xy.position_xy_mm)
        _home(config, home, rail, xy, failures)
        if "camera" not in failures:
            camera, settings = _open_camera(config, bench, failures)
        if failures:
            opened: dict[str, Any] = {}
            if camera is not None:
                opened["camera"] = describe_camera(camera, settings)
            if rail is not None and "rail" not in failures:
                opened["rail"] = describe_rail(rail, config)
            if xy is not None and "xy_stage" not in failures:
                opened["xy_stage"] = describe_xy(xy, config.xy_stage)
            raise DevicesError(
                {role: failures[role] for role in ROLES if role in failures}, opened=opened
            )
    except BaseException:
        _close_all(camera, xy, rail, ports, bench)
        raise
    assert camera is not None and rail is not None and xy is not None and settings is not None
    return StationDevices(
        camera=camera,
        rail=rail,
        xy=xy,
        config=config,
        camera_settings=settings,
        bench=bench,
        _ports=ports,
    )


def _open_stages(
    config: StationConfig,
    bench: Any | None,
    speedup: float,
    ports: list[ZaberPort],
    failures: dict[str, DeviceError],
) -> tuple[ZaberAxis | None, XYStage | None]:
    """Connect the rail and the XY stage (sharing one port when on one chain)."""
    rc, xc = config.rail, config.xy_stage
    rail_scale = 1.0 / speedup if rc.driver == "emulated" else 1.0
    xy_scale = 1.0 / speedup if xc.driver == "emulated" else 1.0
    rail_cfg = _axis_config(rc, "rail", rc.device, rc.axis, (rc.min_mm, rc.max_mm), rail_scale)
    x_cfg = _axis_config(
        xc, "xy stage x", xc.x.device, xc.x.axis, (xc.x.min_mm, xc.x.max_mm), xy_scale
    )
    y_cfg = _axis_config(
        xc, "xy stage y", xc.y.device, xc.y.axis, (xc.y.min_mm, xc.y.max_mm), xy_scale
    )

    def url_of(link: RailConfig | XYStageConfig, own_port: str | None) -> str | None:
        if link.driver == "emulated":
            return bench.url if bench is not None else None
        return own_port

    rail_url = url_of(rc, rc.port)
    xy_url = url_of(xc, xc.port if xc.port is not None else rc.port)
    rail: ZaberAxis | None = None
    xy: XYStage | None = None
    shared: ZaberPort | None = None
    if config.xy_shares_rail_chain and rail_url is not None:
        shared = ZaberPort(rail_url, name="rail", baudrate=rc.baud_rate)
        try:
            shared.open()
            ports.append(shared)
        except PortUnavailable as exc:
            failures["rail"] = exc
            failures["xy_stage"] = PortUnavailable(
                f"not opened: it is on the rail's chain ({rail_url}), whose port failed",
                device="xy stage",
                hint="the rail's port (see the rail's error)",
            )
            return None, None
    if rail_url is not None and "rail" not in failures:
        try:
            rail = open_rail(shared or rail_url, rail_cfg, baudrate=rc.baud_rate)
        except (DeviceError, OSError, ValueError) as exc:
            failures["rail"] = _as_device_error(exc, "rail")
    if xy_url is not None and "xy_stage" not in failures:
        try:
            xy = open_xy_stage(shared or xy_url, x_cfg, y_cfg, baudrate=xc.baud_rate)
        except (DeviceError, OSError, ValueError) as exc:
            failures["xy_stage"] = _as_device_error(exc, "xy stage")
    return rail, xy


def _home(
    config: StationConfig,
    home: bool | None,
    rail: ZaberAxis | None,
    xy: XYStage | None,
    failures: dict[str, DeviceError],
) -> None:
    """Home the rail and the XY stage at the same time (as configured or forced)."""
    home_rail = rail is not None and (config.rail.home_on_connect if home is None else home)
    home_xy = xy is not None and (config.xy_stage.home_on_connect if home is None else home)
    pending = None
    if home_rail:
        assert rail is not None
        try:
            pending = rail.start_home()
        except DeviceError as exc:
            failures["rail"] = exc
    if home_xy:
        assert xy is not None
        try:
            xy.home()
        except DeviceError as exc:
            failures["xy_stage"] = exc
    if pending is not None:
        assert rail is not None
        try:
            rail.finish(pending)
        except DeviceError as exc:
            failures["rail"] = exc


def _open_camera(
    config: StationConfig, bench: Any | None, failures: dict[str, DeviceError]
) -> tuple[Camera | None, CameraSettings | None]:
    """Build, open and configure the camera; record a failure instead of raising."""
    cam_cfg = config.camera
    camera: Camera | None = None
    try:
        if cam_cfg.backend == "simulated":
            assert bench is not None
            camera = bench.camera
        else:
            camera = create_camera(
                cam_cfg.backend,
                address=cam_cfg.address,
                serial=cam_cfg.serial,
                cti=cam_cfg.cti,
                allow_discovery=False,
                interface=cam_cfg.interface,
                transport=transport_settings(config),
            )
        assert camera is not None
        camera.open()
        settings = camera.configure(_camera_settings(config))
        return camera, settings
    except (DeviceError, OSError, ValueError) as exc:
        failures["camera"] = _as_device_error(exc, f"camera ({cam_cfg.backend})")
        if camera is not None:
            _close_all(camera)
        return None, None


def position_text(value_mm: float | None) -> str:
    """A position (mm) for tables: ``"42.000 mm"`` or ``"unknown"`` (not homed)."""
    if value_mm is None or not math.isfinite(value_mm):
        return "unknown"
    return f"{value_mm:.3f} mm"


__all__ = [
    "BENCH_MODULE",
    "ROLES",
    "SIMULATION_BACKEND",
    "ROLE_NAMES",
    "DevicesError",
    "StationDevices",
    "describe_bench",
    "describe_camera",
    "describe_rail",
    "describe_xy",
    "open_devices",
    "position_text",
]
