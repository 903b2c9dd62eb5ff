"""Connect the station's stages and camera as the configuration says: the Zaber rail and
XY stage on their ports (one shared port when the stage is on the rail's chain; an
emulated one on the simulated bench's pty), homing, and the camera by its backend
(Aravis by address, never GigE discovery; harvesters by .cti; or the bench's simulated
camera), opened and configured with ``[camera]``.

The ``open_*`` functions and :func:`home_stages` record a failing device in
``failures`` (role -> typed :class:`drivers.errors.DeviceError`) instead of raising, so
that :func:`station.devices.open_devices` can try every device. Units: mm, µm, mm/s,
mm/s², µs, dB, px.
"""

from __future__ import annotations

from typing import Any

from drivers.camera import Camera, CameraSettings, Roi, TransportSettings, create_camera
from drivers.errors import DeviceError, PortUnavailable
from drivers.zaber import XYStage, ZaberAxis, ZaberAxisConfig, ZaberPort, open_rail, open_xy_stage
from station.config import StationConfig
from station.config_sections import RailConfig, XYStageConfig


def close_all(*things: Any) -> None:
    """Close each thing (lists too), ignoring device errors: closing is best effort."""
    for thing in things:
        if thing is None:
            continue
        if isinstance(thing, list):
            close_all(*thing)
            continue
        try:
            thing.close()
        except (DeviceError, OSError):
            pass


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


def camera_settings(config: StationConfig) -> CameraSettings:
    """``[camera]`` as the drivers take it: pixel format, exposure (µs), gain (dB), ROI
    (px), black level, trigger and flat field."""
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


def _as_device_error(exc: Exception, name: str) -> DeviceError:
    if isinstance(exc, DeviceError):
        return exc
    return DeviceError(f"{type(exc).__name__}: {exc}", device=name)


def open_stages(
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


def home_stages(
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


def open_camera(
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
        settings = camera.configure(camera_settings(config))
        return camera, settings
    except (DeviceError, OSError, ValueError) as exc:
        failures["camera"] = _as_device_error(exc, f"camera ({cam_cfg.backend})")
        if camera is not None:
            close_all(camera)
        return None, None


__all__ = [
    "camera_settings",
    "close_all",
    "home_stages",
    "open_camera",
    "open_stages",
    "transport_settings",
]
