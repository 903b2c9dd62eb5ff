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

The parts (their public names importable from here too): connecting the stages and
the camera, and homing, in :mod:`station.device_connect`; the ``describe_*`` functions
in :mod:`station.device_descriptions`; building the simulated backend's scene and bench
from the configuration in :mod:`station.simulated_backend` (its modules are loaded here).

Units: mm, µs, dB, px.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from drivers.axis import Axis
from drivers.camera import Camera, CameraSettings
from drivers.errors import DeviceError
from drivers.zaber import XYStage, ZaberAxis, ZaberPort
from station.config import StationConfig
from station.device_connect import (
    close_all,
    home_stages,
    open_camera,
    open_stages,
    transport_settings,
)
from station.device_descriptions import (
    describe_bench,
    describe_camera,
    describe_rail,
    describe_xy,
)
from station.simulated_backend import SIM_REFERENCE_EXPOSURE_US, make_bench, make_scene

SIMULATION_BACKEND: dict[str, str] = {
    "bench": "drivers.sim.bench",
    "scene": "drivers.sim.plenoptic_scene",
}
"""Modules of the simulated backend, imported by name when the config asks for them:
the bench (emulated stages and the simulated camera) and the plenoptic scene it shows."""

BENCH_MODULE = SIMULATION_BACKEND["bench"]

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
        close_all(self.camera, self.xy, self.rail, self._ports, self.bench)

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


# --------------------------------------------------------------------------- open


def _simulation_module(part: str) -> Any:
    """The simulated backend's ``part`` (``"bench"`` or ``"scene"``), imported by name
    from :data:`SIMULATION_BACKEND`: only ever called when the configuration asks for it."""
    return importlib.import_module(SIMULATION_BACKEND[part])


def _start_simulation(
    config: StationConfig, speedup: float, failures: dict[str, DeviceError]
) -> Any | None:
    """The started simulated bench when the configuration asks for any simulated device
    (None otherwise, or when it failed: its error is recorded for every simulated role)."""
    simulated = {
        "camera": config.camera.backend == "simulated",
        "rail": config.rail.driver == "emulated",
        "xy_stage": config.xy_stage.driver == "emulated",
    }
    scene = None
    if simulated["camera"]:
        try:
            scene = make_scene(_simulation_module("scene"), config)
        except DeviceError as exc:
            failures["camera"] = exc
    if scene is not None or simulated["rail"] or simulated["xy_stage"]:
        try:
            return make_bench(_simulation_module("bench"), config, scene, speedup)
        except DeviceError as exc:
            for role, is_simulated in simulated.items():
                if is_simulated:
                    failures.setdefault(role, exc)
    return None


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
        bench = _start_simulation(config, emulator_speedup, failures)
        rail, xy = open_stages(config, bench, emulator_speedup, ports, failures)
        if bench is not None and bench.rail is None and rail is not None:
            bench.use_rail_position(rail.position_mm)
        if bench is not None and bench.stage_x is None and xy is not None:
            bench.use_stage_position(xy.position_xy_mm)
        home_stages(config, home, rail, xy, failures)
        if "camera" not in failures:
            camera, settings = open_camera(config, bench, failures)
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
        close_all(camera, xy, rail, ports, bench)
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


def position_text(value_mm: float | None) -> str:
    """A position (mm) for tables: ``"42.000 mm"`` or ``"unknown"`` (not homed)."""
    if value_mm is None or not math.isfinite(value_mm):
        return "unknown"
    return f"{value_mm:.3f} mm"


__all__ = [
    "BENCH_MODULE",
    "ROLES",
    "SIMULATION_BACKEND",
    "SIM_REFERENCE_EXPOSURE_US",
    "ROLE_NAMES",
    "DevicesError",
    "StationDevices",
    "describe_bench",
    "describe_camera",
    "describe_rail",
    "describe_xy",
    "open_devices",
    "position_text",
    "transport_settings",
]
