"""Zaber axis configurations for tests against the emulator."""

from __future__ import annotations

from drivers.zaber import ZaberAxisConfig


def axis_config(
    name: str = "rail", device: int = 1, axis: int = 1, *, speedup: float, **extra: object
) -> ZaberAxisConfig:
    """Axis config whose motion timeouts match an emulator running ``speedup`` times
    faster than real time (0.1 µm microsteps, 0.5 µm tolerance, 2 ms polling)."""
    values: dict[str, object] = {
        "name": name,
        "device": device,
        "axis": axis,
        "microstep_um": 0.1,
        "tolerance_um": 0.5,
        "timeout_scale": 1.0 / speedup,
        "timeout_margin_s": 0.5,
        "poll_interval_s": 0.002,
    }
    values.update(extra)
    return ZaberAxisConfig(**values)  # type: ignore[arg-type]
