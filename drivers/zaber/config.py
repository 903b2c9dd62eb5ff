"""Configuration of one Zaber axis (:class:`ZaberAxisConfig`) and its unit conversions.

The device counts in microsteps; ``microstep_um`` gives the size of one microstep in
micrometres, and the driver's public methods work in millimetres and seconds.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from drivers.zaber import protocol


@dataclass(frozen=True)
class ZaberAxisConfig:
    """Configuration of one Zaber axis.

    Attributes:
        name: name in logs and errors (``"rail"``, ``"stage x"``).
        device: device number on the chain (1-99).
        axis: axis number on the device (1-9).
        microstep_um: size of one microstep (um), from the stage's datasheet.
        tolerance_um: allowed |read-back - target| after a move (um).
        speed_mm_s: if set, the speed of every move (mm/s): a per-move argument on
            firmware >= 7.25, else written to ``maxspeed`` at connect and restored at close.
        accel_mm_s2: if set, the acceleration of every move (mm/s^2), like ``speed_mm_s``.
        soft_limits_mm: optional (min, max) travel tighter than the device's (mm).
        timeout_margin_s: added to every derived motion timeout (s).
        timeout_scale: multiplies the kinematic part of motion timeouts
            (set to 1/speedup against a sped-up emulator).
        poll_interval_s: pause between status polls while waiting for IDLE (s).
    """

    name: str = "zaber axis"
    device: int = 1
    axis: int = 1
    microstep_um: float = 0.1
    tolerance_um: float = 1.0
    speed_mm_s: float | None = None
    accel_mm_s2: float | None = None
    soft_limits_mm: tuple[float, float] | None = None
    timeout_margin_s: float = 1.0
    timeout_scale: float = 1.0
    poll_interval_s: float = 0.005

    def __post_init__(self) -> None:
        if not 1 <= self.device <= protocol.MAX_DEVICE:
            raise ValueError(
                f"{self.name}: device must be 1-{protocol.MAX_DEVICE}, got {self.device}"
            )
        if not 1 <= self.axis <= protocol.MAX_AXIS:
            raise ValueError(f"{self.name}: axis must be 1-{protocol.MAX_AXIS}, got {self.axis}")
        for key in ("microstep_um", "tolerance_um", "timeout_scale"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{self.name}: {key} must be positive")
        for key in ("speed_mm_s", "accel_mm_s2"):
            value = getattr(self, key)
            if value is not None and not value > 0:
                raise ValueError(f"{self.name}: {key} must be positive")
        if self.timeout_margin_s < 0 or self.poll_interval_s < 0:
            raise ValueError(f"{self.name}: timeouts must not be negative")
        if self.soft_limits_mm is not None:
            low, high = self.soft_limits_mm
            if not low < high:
                raise ValueError(f"{self.name}: soft_limits_mm must be (min, max) with min < max")

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> ZaberAxisConfig:
        """Build from a config-file table; unknown keys raise ValueError."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown Zaber axis settings: {sorted(unknown)}")
        values = dict(data)
        if values.get("soft_limits_mm") is not None:
            low, high = values["soft_limits_mm"]
            values["soft_limits_mm"] = (float(low), float(high))
        return cls(**values)

    def mm_to_usteps(self, position_mm: float) -> int:
        """Millimetres to (rounded) microsteps."""
        return round(position_mm * 1000.0 / self.microstep_um)

    def usteps_to_mm(self, usteps: float) -> float:
        """Microsteps to millimetres."""
        return usteps * self.microstep_um / 1000.0


__all__ = ["ZaberAxisConfig"]
