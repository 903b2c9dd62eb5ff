"""The simulated backend built from the station configuration: the plenoptic scene of the
simulated camera (``[camera]`` preset and size) and the bench (emulated stages and the
simulated camera) for the emulated ``[rail]`` and ``[xy_stage]``.

The backend's modules are not imported here: :mod:`station.devices` loads them by name
from its backend table, only when the configuration asks for them, and hands them in.
Units: mm, mm/s, mm/s², µs.
"""

from __future__ import annotations

from typing import Any

from drivers.errors import DeviceError
from station.config import StationConfig
from station.config_sections import RailConfig, XYStageConfig

SIM_REFERENCE_EXPOSURE_US = 10000.0
"""Exposure (µs) at which the simulated scene has the preset's white level."""


def make_scene(scene_module: Any, config: StationConfig) -> Any:
    """The plenoptic scene of the simulated camera (``[camera]`` preset and size), built
    with ``scene_module`` (the backend's scene module)."""
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


def _bench_axis(
    bench_module: Any, link: RailConfig | XYStageConfig, device: int, axis: int, max_mm: float
) -> Any:
    """An emulated axis of the bench: Zaber ``device``/``axis`` on the chain of ``link``,
    travel ``max_mm`` (at least 1 mm), starting at 10 mm (or its end when shorter)."""
    return bench_module.BenchAxis(
        device=device,
        axis=axis,
        microstep_um=link.microstep_um,
        travel_mm=max(max_mm, 1.0),
        speed_mm_s=link.max_speed_mm_s,
        accel_mm_s2=link.accel_mm_s2,
        start_mm=min(10.0, max(max_mm, 1.0)),
    )


def make_bench(bench_module: Any, config: StationConfig, scene: Any | None, speedup: float) -> Any:
    """The simulated bench (started) for the emulated stages of ``config`` and ``scene``,
    built with ``bench_module`` (the backend's bench module).

    The bench has one emulated chain: the rail and the XY stage when both are emulated,
    otherwise only the emulated one (the other is real and feeds the scene through
    ``use_rail_position`` / ``use_stage_position``).
    """
    rail = xy_x = xy_y = None
    if config.rail.driver == "emulated":
        r = config.rail
        rail = _bench_axis(bench_module, r, r.device, r.axis, r.max_mm)
    xy = config.xy_stage
    if xy.driver == "emulated":
        xy_x, xy_y = (
            _bench_axis(bench_module, xy, a.device, a.axis, a.max_mm) for a in (xy.x, xy.y)
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


__all__ = ["SIM_REFERENCE_EXPOSURE_US", "make_bench", "make_scene"]
