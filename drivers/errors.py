"""Typed errors for every device driver of the station.

Every error carries the name of the device it concerns and a short "what to
check" hint for the operator, so a message reads like::

    rail (zaber device 1 axis 1 on /dev/ttyUSB0): stalled while moving to 42.000 mm
    -- check: obstruction in the travel, load too heavy, speed/accel too high

:class:`DeviceError` is deliberately generic (no serial or motion notion in it):
camera and other drivers subclass it directly.  Motion-specific errors below
are used by every motion driver (Zaber today; Thorlabs APT or Newport SMC100
later), not only by the Zaber one.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


class DeviceError(Exception):
    """Base class: something went wrong with a piece of hardware.

    Attributes:
        device: human-readable name of the device (and where it is connected).
        message: what happened.
        hint: what the operator should check.
    """

    default_hint = "check the device's power, cabling and configuration"

    def __init__(self, message: str, *, device: str = "", hint: str | None = None) -> None:
        self.device = device
        self.message = message
        self.hint = hint if hint is not None else self.default_hint
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = f"{self.device}: " if self.device else ""
        tail = f" -- check: {self.hint}" if self.hint else ""
        return f"{where}{self.message}{tail}"

    def __reduce__(self) -> tuple[Any, ...]:
        # keep every attribute (reason, flags, positions...) across pickling,
        # e.g. when an error is sent back from a worker process
        return (_restore, (type(self), self.args, self.__dict__.copy()))


def _restore(cls: type[DeviceError], args: tuple[Any, ...], state: dict[str, Any]) -> DeviceError:
    error = cls.__new__(cls)
    Exception.__init__(error, *args)
    error.__dict__.update(state)
    return error


# --------------------------------------------------------------------------- transport


class PortUnavailable(DeviceError):
    """The serial port / socket cannot be opened (missing, busy, refused)."""

    default_hint = (
        "the port path or URL (ls /dev/serial/by-id), that the USB adapter is plugged in, "
        "that no other program holds the port, and for socket:// that the server is running"
    )


class ConnectionLost(PortUnavailable):
    """The port went away while in use (USB unplugged, server closed the socket)."""

    default_hint = "the USB cable/adapter or the network link; reconnect and re-home the stage"


class DeviceTimeout(DeviceError):
    """Something did not happen within the allowed time."""

    default_hint = "that the device is powered and not blocked"


class NoReply(DeviceTimeout):
    """The device did not answer a command at all."""

    default_hint = (
        "the device is powered, the cable is connected, the device number and baud rate "
        "are right and the device speaks the expected protocol"
    )


class MotionTimeout(DeviceTimeout):
    """The axis stayed busy much longer than the move should take (stuck BUSY)."""

    default_hint = (
        "mechanical blockage, a far too low speed setting, or a device fault; "
        "the driver sent a stop"
    )


class GarbledReply(DeviceError):
    """A reply could not be parsed (wrong framing, unexpected bytes)."""

    default_hint = (
        "baud rate and protocol settings, cable shielding/length, and that no other program "
        "writes to the same port"
    )


class ChecksumError(GarbledReply):
    """A reply's checksum did not match its contents (bytes corrupted on the wire)."""


class CommandRejected(DeviceError):
    """The device understood the message but refused the command.

    Attributes:
        reason: the device's reason code (e.g. ``BADDATA``, ``BADCOMMAND``,
            ``BADAXIS``, ``DEVICEONLY``, ``PARKED``...).
        command: the command text that was rejected.
    """

    default_hint = "the command, its argument and the device/axis numbers in the configuration"

    def __init__(
        self,
        message: str,
        *,
        reason: str,
        command: str = "",
        device: str = "",
        hint: str | None = None,
    ) -> None:
        self.reason = reason
        self.command = command
        super().__init__(message, device=device, hint=hint)


# --------------------------------------------------------------------------- motion


class MotionError(DeviceError):
    """Base for motion failures reported by (or detected on) an axis.

    Attributes:
        flags: device warning/fault codes active when the error was raised
            (vendor-specific strings, e.g. Zaber ``FS``/``WL``); may be empty.
    """

    def __init__(
        self,
        message: str,
        *,
        device: str = "",
        hint: str | None = None,
        flags: Iterable[str] = (),
    ) -> None:
        self.flags = frozenset(flags)
        super().__init__(message, device=device, hint=hint)


class StageStalled(MotionError):
    """The motor stalled and the axis stopped itself (Zaber FS). Position is not trusted."""

    default_hint = (
        "obstruction in the travel, too heavy or unbalanced load, speed/acceleration too "
        "high; home the axis again before the next move"
    )


class LimitHit(MotionError):
    """A limit sensor stopped the move unexpectedly or is faulty (Zaber WL / FE)."""

    default_hint = (
        "the limit settings against the real travel, the limit sensor and its cable, "
        "slippage; home the axis again before the next move"
    )


class NotReferenced(MotionError):
    """The axis has no reference position (never homed, or power was lost: Zaber WR)."""

    default_hint = "home the axis; if it was homed before, check the device's power supply"


class MoveInterrupted(MotionError):
    """The move was interrupted by a stop or another move before it ended (Zaber NI)."""

    default_hint = "whether a stop was requested, another program or the manual knob moved the axis"


class DeviceFault(MotionError):
    """Any other device fault that stopped or endangers motion (driver, encoder...)."""

    default_hint = (
        "the device's fault list (warnings), temperature and supply; clear faults and home"
    )


class DeviceBusy(MotionError):
    """The axis was already moving when a new motion was requested."""

    default_hint = "whether another program or the manual knob is moving the axis"


class PositionMismatch(MotionError):
    """The axis is idle but not where it was commanded to be.

    Attributes:
        target_mm: commanded position (mm).
        actual_mm: read-back position (mm).
        tolerance_mm: allowed difference (mm).
    """

    default_hint = (
        "slippage, load, encoder or a misconfigured microstep size; the read-back "
        "position is what the device reports"
    )

    def __init__(
        self,
        message: str,
        *,
        target_mm: float,
        actual_mm: float,
        tolerance_mm: float,
        device: str = "",
        hint: str | None = None,
    ) -> None:
        self.target_mm = target_mm
        self.actual_mm = actual_mm
        self.tolerance_mm = tolerance_mm
        super().__init__(message, device=device, hint=hint)


class TargetOutOfRange(MotionError, ValueError):
    """A move target lies outside the axis's travel limits (checked before sending)."""

    default_hint = "the requested position against the axis limits in the configuration"


__all__ = [
    "ChecksumError",
    "CommandRejected",
    "ConnectionLost",
    "DeviceBusy",
    "DeviceError",
    "DeviceFault",
    "DeviceTimeout",
    "GarbledReply",
    "LimitHit",
    "MotionError",
    "MotionTimeout",
    "MoveInterrupted",
    "NoReply",
    "NotReferenced",
    "PortUnavailable",
    "PositionMismatch",
    "StageStalled",
    "TargetOutOfRange",
]
