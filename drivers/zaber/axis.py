"""One Zaber axis as a :class:`drivers.axis.Axis` (positions in mm, times in s).

The device counts in microsteps; :class:`ZaberAxisConfig` gives the size of
one microstep in micrometres, and every public method converts.

:class:`ZaberAxis` is composed of three collaborators, one job each:

- :class:`~drivers.zaber.link.AxisLink`: requests addressed to the axis, its
  status poll and warning flags;
- :class:`~drivers.zaber.settings.AxisSettings`: travel limits and speeds read and
  set up at connect, read back, restored at close, and the motion timeouts they imply;
- :class:`~drivers.zaber.motion.MotionSupervisor`: starting, waiting for, checking
  and stopping motions, and whether the position is still trusted.

Safety rules:

- no move is sent to an axis without a reference position: the device's WR
  flag, or a fault after which the driver no longer trusts the position
  (stall FS, limit FE/WL, encoder FQ), makes ``move_abs_mm`` raise
  :class:`NotReferenced` until ``home()`` succeeded;
- targets are checked against the device's ``limit.min``/``limit.max`` (and
  optional tighter soft limits) before anything is sent;
- after every move the driver waits for IDLE, with a timeout derived from the
  distance, ``maxspeed`` and ``accel`` (x1.5, x ``timeout_scale``, plus
  ``timeout_margin_s``); past it the axis is sent ``stop`` and
  :class:`MotionTimeout` is raised;
- once idle, the device's warning flags are checked (full list via
  ``warnings``) and mapped to typed errors; fault flags are cleared on the
  device after being reported, so the error is raised once and the operator
  re-homes;
- the idle position is compared to the target: more than ``tolerance_um``
  off raises :class:`PositionMismatch` (carrying both positions);
- NI (command interrupted) is the firmware's record that a motion was cut short;
  it stays set until ``warnings clear``.  ``stop()`` clears it once the axis is
  idle (as Zaber's own library does), and a stale NI is cleared before each move
  or home, so an NI seen after a motion always belongs to that motion.

Firmware series (read with ``get version`` at connect, :attr:`ZaberAxis.firmware`):
firmware 6 names the identity setting ``deviceid``, firmware 7 ``device.id`` (the
driver asks with the name of the series and falls back to the other on
``BADCOMMAND``); ``system.serial`` is optional.

Stored settings are not changed behind the lab's back: with a configured
``speed_mm_s`` / ``accel_mm_s2`` the driver passes them with every move
(``move abs <pos> <speed> <accel>``, firmware 7.25 and later), so the device's
``maxspeed`` and ``accel`` stay as they are.  On older firmware, which has no
per-move arguments, it sets ``maxspeed``/``accel`` at connect and sets the values it
found back at :meth:`ZaberAxis.close` (``ZaberAxis.changed_settings`` lists them).
Homing always runs at the device's own homing speeds.  ``comm.checksum``, switched
on for reply checksums when it was off, is switched off again when the port closes.
"""

from __future__ import annotations

import math
import time

from drivers.axis import AxisIdentity, AxisLimits
from drivers.errors import DeviceError, TargetOutOfRange
from drivers.zaber import protocol
from drivers.zaber.config import ZaberAxisConfig
from drivers.zaber.link import AxisLink
from drivers.zaber.motion import MotionSupervisor, PendingMotion
from drivers.zaber.port import ZaberPort
from drivers.zaber.settings import MOVE_SPEED_ARGS_SINCE as MOVE_SPEED_ARGS_SINCE
from drivers.zaber.settings import AxisSettings

#: Identity settings by firmware series: (firmware 6 name, firmware 7 name).
DEVICE_ID_SETTINGS = ("deviceid", "device.id")
PERIPHERAL_ID_SETTINGS = ("peripheralid", "peripheral.id")


def parse_version(text: str) -> tuple[int, int]:
    """``"7.38"`` -> (7, 38); (0, 0) when the text is not a version."""
    major, _, minor = text.strip().partition(".")
    try:
        return int(major), int(minor.split(".")[0] or 0)
    except ValueError:
        return (0, 0)


class ZaberAxis:
    """A Zaber axis implementing :class:`drivers.axis.Axis`.

    Args:
        port: the chain's transport (may be shared by several axes).
        config: device/axis numbers, microstep size, tolerance, speeds.
        owns_port: close the port in :meth:`close`.

    Call :meth:`connect` once before use (``open_rail`` does it for you).
    """

    vendor = "Zaber"

    def __init__(
        self, port: ZaberPort, config: ZaberAxisConfig, *, owns_port: bool = False
    ) -> None:
        self._port = port
        self._cfg = config
        self._owns_port = owns_port
        self._connected = False
        self._identity: AxisIdentity | None = None
        self._version: tuple[int, int] = (0, 0)
        self._link = AxisLink(port, config)
        self._settings = AxisSettings(self._link, config)
        self._motion = MotionSupervisor(self._link, config, self._settings)

    # ------------------------------------------------------------------ basics

    @property
    def name(self) -> str:
        """Configured name."""
        return self._cfg.name

    @property
    def config(self) -> ZaberAxisConfig:
        """The configuration this axis was built with."""
        return self._cfg

    @property
    def port(self) -> ZaberPort:
        """The transport this axis talks through."""
        return self._port

    @property
    def label(self) -> str:
        """Name plus address, as used in error messages."""
        return self._link.label

    def mm_to_usteps(self, position_mm: float) -> int:
        """Millimetres to (rounded) microsteps."""
        return self._cfg.mm_to_usteps(position_mm)

    def usteps_to_mm(self, usteps: float) -> float:
        """Microsteps to millimetres."""
        return self._cfg.usteps_to_mm(usteps)

    # ------------------------------------------------------------------ lifecycle

    def connect(self) -> ZaberAxis:
        """Open the port if needed, read firmware, identity and limits, set up speeds.

        Lingering fault flags (FS, FE, FQ, WL) are cleared and the axis is then
        treated as not homed.  Raises DeviceError subclasses naming the axis.
        """
        cfg, link = self._cfg, self._link
        if not self._port.is_open:
            self._port.open()
        self._port.enable_checksums(cfg.device, label=self.label)
        version = link.request("get version", axis=0).data
        self._version = parse_version(version)
        device_id = link.get_named(DEVICE_ID_SETTINGS, axis=0, firmware=self._version) or "unknown"
        serial = link.get_optional("system.serial", axis=0) or "unknown"
        peripheral = link.get_named(PERIPHERAL_ID_SETTINGS, axis=cfg.axis, firmware=self._version)
        model = f"device id {device_id}" + (f", peripheral id {peripheral}" if peripheral else "")
        self._identity = AxisIdentity(
            vendor=self.vendor,
            model=model,
            serial=serial,
            firmware=version,
            address=f"{self._port.url} device {cfg.device} axis {cfg.axis}",
        )
        self._settings.load(self._version)
        flags = self.warnings()
        if flags & protocol.CLEARABLE_FLAGS:
            self.clear_warnings()
        if flags & protocol.POSITION_LOST_FLAGS:
            self._motion.needs_home = True
        self._connected = True
        return self

    @property
    def firmware(self) -> tuple[int, int]:
        """Firmware version (major, minor) read at connect ((0, 0) before)."""
        return self._version

    @property
    def changed_settings(self) -> dict[str, int]:
        """Settings this axis wrote at connect with the value found before (restored at close)."""
        return self._settings.changed

    @changed_settings.setter
    def changed_settings(self, value: dict[str, int]) -> None:
        self._settings.changed = value

    @property
    def speed_mode(self) -> str:
        """How configured speeds reach the device: ``"per-move"`` (``move abs`` arguments,
        firmware >= 7.25), ``"written"`` (set at connect, restored at close) or
        ``"stored"`` (none configured: the device's own settings)."""
        return self._settings.speed_mode

    def read_back(self) -> dict[str, str]:
        """The settings the station relies on, read from the device now (raw values):
        ``version``, ``limit.min``, ``limit.max``, ``maxspeed``, ``accel``,
        ``comm.checksum``, ``pos`` and the active ``warnings``."""
        self._require_connected()
        return self._settings.read_back()

    def restore_settings(self) -> None:
        """Write back the settings changed at connect (best effort; see the module notes)."""
        self._settings.restore()

    def close(self) -> None:
        """Restore changed settings, forget the connection; closes the port if owned."""
        if self._connected:
            self.restore_settings()
        self._connected = False
        if self._owns_port:
            self._port.close()

    def __enter__(self) -> ZaberAxis:
        return self if self._connected else self.connect()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ Axis interface

    def identity(self) -> AxisIdentity:
        """Vendor, device id, serial, firmware and address (read at connect)."""
        self._require_connected()
        assert self._identity is not None
        return self._identity

    def limits_mm(self) -> AxisLimits:
        """Allowed travel (mm): device limits, narrowed by the configured soft limits."""
        self._require_connected()
        low_usteps, high_usteps = self._settings.limits_usteps
        low = self.usteps_to_mm(low_usteps)
        high = self.usteps_to_mm(high_usteps)
        if self._cfg.soft_limits_mm is not None:
            low = max(low, self._cfg.soft_limits_mm[0])
            high = min(high, self._cfg.soft_limits_mm[1])
        return AxisLimits(low, high)

    def is_homed(self) -> bool:
        """True if the device has a reference (no WR) and the driver still trusts it."""
        return self._motion.is_homed()

    def is_busy(self) -> bool:
        """True while the axis is moving."""
        return self._link.status().busy

    def position_mm(self) -> float:
        """Current position (mm). Raises NotReferenced when the axis is not homed."""
        return self._motion.position_mm()

    def home(self, timeout_s: float | None = None) -> None:
        """Home the axis and wait (``timeout_s`` s; None = derived from the travel)."""
        self.finish(self.start_home(timeout_s))

    def move_abs_mm(self, target_mm: float, timeout_s: float | None = None) -> float:
        """Move to ``target_mm`` (mm), wait, verify; return the read-back position (mm)."""
        return self.finish(self.start_move_abs_mm(target_mm, timeout_s))

    def stop(self) -> None:
        """Decelerate to a stop and wait until idle (estop if it does not stop in time).

        The NI flag the stop leaves is then cleared (a motion being waited for in
        another thread still ends with MoveInterrupted).
        """
        self._motion.stop()

    def estop(self) -> None:
        """Emergency stop (``estop``): halts at once; does not wait."""
        self._link.request("estop")

    def wait_idle(self, timeout_s: float) -> None:
        """Wait until idle (``timeout_s`` s), raising typed errors for fault flags.

        Past the timeout the axis is sent ``stop`` and MotionTimeout is raised.
        """
        self._motion.wait(time.monotonic() + timeout_s, context="waiting for idle")

    # ------------------------------------------------------------------ split motion (XY)

    def start_home(self, timeout_s: float | None = None) -> PendingMotion:
        """Send ``home`` and return without waiting; pass the result to :meth:`finish`.

        Homing is the recovery from faults: stale fault flags are cleared first, so
        the flags seen after homing are homing's own.  Raises DeviceBusy if moving.
        """
        self._require_connected()
        return self._motion.start_home(timeout_s)

    def start_move_abs_mm(self, target_mm: float, timeout_s: float | None = None) -> PendingMotion:
        """Check and send ``move abs`` without waiting; pass the result to :meth:`finish`.

        Raises TargetOutOfRange, NotReferenced, DeviceBusy, CommandRejected, or the
        error for a fault flag still set on the device.
        """
        target = self.check_target_mm(target_mm)
        return self._motion.start_move(target, target_mm, timeout_s)

    def check_target_mm(self, target_mm: float) -> int:
        """Validate a target (mm) against the limits; return it in microsteps.

        Sends nothing.  Raises TargetOutOfRange.
        """
        self._require_connected()
        limits = self.limits_mm()
        if not math.isfinite(target_mm) or not (
            limits.min_mm - 1e-9 <= target_mm <= limits.max_mm + 1e-9
        ):
            raise TargetOutOfRange(
                f"target {target_mm} mm outside travel "
                f"[{limits.min_mm:.4f}, {limits.max_mm:.4f}] mm",
                device=self.label,
            )
        target = self.mm_to_usteps(target_mm)
        low, high = self._settings.limits_usteps
        return min(max(target, low), high)

    def finish(self, pending: PendingMotion) -> float:
        """Wait for a started motion, check flags and position; return position (mm)."""
        return self._motion.finish(pending)

    # ------------------------------------------------------------------ flags

    def warnings(self) -> frozenset[str]:
        """All warning flags active on the axis (``warnings``)."""
        return self._link.warnings()

    def clear_warnings(self) -> frozenset[str]:
        """Clear the clearable flags; returns the flags that were active."""
        return self._link.clear_warnings()

    # ------------------------------------------------------------------ internals

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceError("axis not connected", device=self.label, hint="call connect() first")


__all__ = ["PendingMotion", "ZaberAxis", "ZaberAxisConfig"]
