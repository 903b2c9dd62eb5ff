"""Generic, vendor-neutral interface of one linear motion axis.

The station talks to every motorized axis (the board rail, each axis of the XY
stage) through :class:`Axis`, so a Thorlabs APT or Newport SMC100 driver can be
dropped in later.  All positions are in **millimetres** in the axis's own
coordinate (0 at the home position), all times in **seconds**.

Contract every implementation follows:

- ``move_abs_mm`` refuses to move an axis that has no reference position
  (raises :class:`drivers.errors.NotReferenced`) and, once the axis is idle,
  reads the position back and raises :class:`drivers.errors.PositionMismatch`
  when it is off by more than the configured tolerance;
- ``position_mm`` never returns a position the axis cannot vouch for: it
  raises :class:`drivers.errors.NotReferenced` when the axis is not homed;
- every failure is a :class:`drivers.errors.DeviceError` subclass.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class AxisIdentity:
    """Who an axis is: enough to tell two stages apart in a log or a report.

    Attributes:
        vendor: manufacturer, e.g. ``"Zaber"``.
        model: model or device id as reported by the device.
        serial: serial number as reported by the device.
        firmware: firmware version string.
        address: where it is reached, e.g. ``"/dev/ttyUSB0 device 1 axis 1"``.
    """

    vendor: str
    model: str
    serial: str
    firmware: str
    address: str


@dataclass(frozen=True)
class AxisLimits:
    """Travel range of an axis, in millimetres (inclusive)."""

    min_mm: float
    max_mm: float

    def contains(self, position_mm: float) -> bool:
        """True if ``position_mm`` (mm) lies within the range."""
        return self.min_mm <= position_mm <= self.max_mm

    @property
    def span_mm(self) -> float:
        """Length of the travel (mm)."""
        return self.max_mm - self.min_mm


@runtime_checkable
class Axis(Protocol):
    """One linear axis. Units: mm and seconds."""

    @property
    def name(self) -> str:
        """Human-readable name used in logs and error messages."""
        ...

    def home(self, timeout_s: float | None = None) -> None:
        """Find the reference position; blocks until done (``timeout_s`` seconds, None = derived)."""
        ...

    def move_abs_mm(self, target_mm: float, timeout_s: float | None = None) -> float:
        """Move to ``target_mm`` (mm), wait, verify, and return the read-back position (mm)."""
        ...

    def position_mm(self) -> float:
        """Current position (mm); raises NotReferenced if the axis is not homed."""
        ...

    def is_homed(self) -> bool:
        """True if the axis has a trusted reference position."""
        ...

    def is_busy(self) -> bool:
        """True while the axis is moving."""
        ...

    def stop(self) -> None:
        """Decelerate to a stop and wait until idle."""
        ...

    def estop(self) -> None:
        """Emergency stop: halt as fast as possible; returns without waiting."""
        ...

    def wait_idle(self, timeout_s: float) -> None:
        """Block until the axis is idle, at most ``timeout_s`` seconds; raise on faults."""
        ...

    def identity(self) -> AxisIdentity:
        """Vendor, model, serial, firmware and address of the axis."""
        ...

    def limits_mm(self) -> AxisLimits:
        """Allowed travel (mm)."""
        ...
