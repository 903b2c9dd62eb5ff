"""One Zaber axis as a :class:`drivers.axis.Axis` (positions in mm, times in s).

The device counts in microsteps; :class:`ZaberAxisConfig` gives the size of
one microstep in micrometres, and every public method converts.

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
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal

from drivers.axis import AxisIdentity, AxisLimits
from drivers.errors import (
    CommandRejected,
    DeviceBusy,
    DeviceError,
    MotionTimeout,
    MoveInterrupted,
    NotReferenced,
    PositionMismatch,
    TargetOutOfRange,
)
from drivers.zaber import protocol
from drivers.zaber.port import ZaberPort
from drivers.zaber.protocol import Reply

#: Flags of lower precedence than WR: when a reply shows one of them, WR is not set.
_BELOW_WR = frozenset(protocol.WARNING_PRIORITY[protocol.WARNING_PRIORITY.index("WR") + 1 :])

#: ``move abs <pos> <speed> <accel>`` exists from this firmware version on.
MOVE_SPEED_ARGS_SINCE = (7, 25)

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


@dataclass(frozen=True)
class PendingMotion:
    """A motion that was started and not yet waited for (see ``finish``).

    Attributes:
        kind: ``"move"`` or ``"home"``.
        target_usteps: move target in microsteps (None for home).
        deadline: ``time.monotonic()`` by which the axis must be idle.
        resent: the command had to be re-sent, so NI (interrupted) is expected.
        stops: the axis's count of ``stop()`` calls when the motion started (a stop
            from another thread clears the NI flag; this tells ``finish`` it happened).
    """

    kind: Literal["move", "home"]
    target_usteps: int | None
    deadline: float
    resent: bool
    stops: int = 0


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
        self._needs_home = False
        self._limits_usteps = (0, 0)
        self._speed = 1.0  # microsteps/s, of moves
        self._accel = 1.0  # microsteps/s^2, of moves
        self._home_speed = 1.0  # microsteps/s: the device's stored maxspeed
        self._home_accel = 1.0
        self._move_args = ""  # " <speed> <accel>" appended to move abs (firmware >= 7.25)
        self._identity: AxisIdentity | None = None
        self._version: tuple[int, int] = (0, 0)
        self._stops = 0  # stop() calls so far (see PendingMotion.stops)
        #: Settings this axis wrote at connect with the value found before (restored at close).
        self.changed_settings: dict[str, int] = {}

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
        return f"{self._cfg.name} (zaber device {self._cfg.device} axis {self._cfg.axis} on {self._port.url})"

    def mm_to_usteps(self, position_mm: float) -> int:
        """Millimetres to (rounded) microsteps."""
        return round(position_mm * 1000.0 / self._cfg.microstep_um)

    def usteps_to_mm(self, usteps: float) -> float:
        """Microsteps to millimetres."""
        return usteps * self._cfg.microstep_um / 1000.0

    # ------------------------------------------------------------------ lifecycle

    def connect(self) -> ZaberAxis:
        """Open the port if needed, read firmware, identity and limits, set up speeds.

        Lingering fault flags (FS, FE, FQ, WL) are cleared and the axis is then
        treated as not homed.  Raises DeviceError subclasses naming the axis.
        """
        cfg = self._cfg
        if not self._port.is_open:
            self._port.open()
        self._port.enable_checksums(cfg.device, label=self.label)
        version = self._request("get version", axis=0).data
        self._version = parse_version(version)
        device_id = self._get_named(DEVICE_ID_SETTINGS, axis=0) or "unknown"
        serial = self._get_optional("system.serial", axis=0) or "unknown"
        peripheral = self._get_named(PERIPHERAL_ID_SETTINGS, axis=cfg.axis)
        model = f"device id {device_id}" + (f", peripheral id {peripheral}" if peripheral else "")
        self._identity = AxisIdentity(
            vendor=self.vendor,
            model=model,
            serial=serial,
            firmware=version,
            address=f"{self._port.url} device {cfg.device} axis {cfg.axis}",
        )
        low = self._get_int("limit.min")
        high = self._get_int("limit.max")
        if not low < high:
            raise DeviceError(
                f"device reports an empty travel: limit.min {low} >= limit.max {high}",
                device=self.label,
                hint="the device's limit settings (Zaber Launcher)",
            )
        self._limits_usteps = (low, high)
        self._setup_speeds()
        flags = self.warnings()
        if flags & protocol.CLEARABLE_FLAGS:
            self.clear_warnings()
        if flags & protocol.POSITION_LOST_FLAGS:
            self._needs_home = True
        self._connected = True
        return self

    @property
    def firmware(self) -> tuple[int, int]:
        """Firmware version (major, minor) read at connect ((0, 0) before)."""
        return self._version

    def _setup_speeds(self) -> None:
        """Per-move speed arguments (firmware >= 7.25) or settings written and restored."""
        cfg = self._cfg
        stored_speed = self._get_int("maxspeed")
        stored_accel = self._get_int("accel")
        self._home_speed = protocol.data_to_speed(stored_speed)
        self._home_accel = protocol.data_to_accel(stored_accel)
        speed_data = (
            protocol.speed_to_data(cfg.speed_mm_s * 1000.0 / cfg.microstep_um)
            if cfg.speed_mm_s is not None
            else None
        )
        accel_data = (
            protocol.accel_to_data(cfg.accel_mm_s2 * 1000.0 / cfg.microstep_um)
            if cfg.accel_mm_s2 is not None
            else None
        )
        self._move_args = ""
        if speed_data is None and accel_data is None:
            pass
        elif self._version >= MOVE_SPEED_ARGS_SINCE:
            # both arguments go together; the one not configured is the stored setting
            self._move_args = f" {speed_data or stored_speed} {accel_data or stored_accel}"
        else:
            for name, data, stored in (
                ("maxspeed", speed_data, stored_speed),
                ("accel", accel_data, stored_accel),
            ):
                if data is not None and data != stored:
                    self.changed_settings.setdefault(name, stored)
                    self._request(f"set {name} {data}")
        self._speed = protocol.data_to_speed(speed_data or stored_speed)
        self._accel = protocol.data_to_accel(accel_data or stored_accel)

    @property
    def speed_mode(self) -> str:
        """How configured speeds reach the device: ``"per-move"`` (``move abs`` arguments,
        firmware >= 7.25), ``"written"`` (set at connect, restored at close) or
        ``"stored"`` (none configured: the device's own settings)."""
        if self._move_args:
            return "per-move"
        return "written" if self.changed_settings else "stored"

    def read_back(self) -> dict[str, str]:
        """The settings the station relies on, read from the device now (raw values):
        ``version``, ``limit.min``, ``limit.max``, ``maxspeed``, ``accel``,
        ``comm.checksum``, ``pos`` and the active ``warnings``."""
        self._require_connected()
        out = {"version": self._request("get version", axis=0).data}
        for name in ("limit.min", "limit.max", "maxspeed", "accel"):
            out[name] = self._request(f"get {name}").data
        out["comm.checksum"] = self._get_optional("comm.checksum", axis=0) or "unknown"
        out["pos"] = self._status().data
        out["warnings"] = " ".join(sorted(self.warnings())) or "none"
        return out

    def restore_settings(self) -> None:
        """Write back the settings changed at connect (best effort; see the module notes)."""
        changed, self.changed_settings = self.changed_settings, {}
        if not self._port.is_open:
            return
        for name, value in changed.items():
            try:
                self._request(f"set {name} {value}")
            except DeviceError:
                pass

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
        low = self.usteps_to_mm(self._limits_usteps[0])
        high = self.usteps_to_mm(self._limits_usteps[1])
        if self._cfg.soft_limits_mm is not None:
            low = max(low, self._cfg.soft_limits_mm[0])
            high = min(high, self._cfg.soft_limits_mm[1])
        return AxisLimits(low, high)

    def is_homed(self) -> bool:
        """True if the device has a reference (no WR) and the driver still trusts it."""
        return self._has_reference(self._status()) and not self._needs_home

    def is_busy(self) -> bool:
        """True while the axis is moving."""
        return self._status().busy

    def position_mm(self) -> float:
        """Current position (mm). Raises NotReferenced when the axis is not homed."""
        status = self._status()
        if self._needs_home or not self._has_reference(status):
            raise NotReferenced("position unknown: axis not homed", device=self.label)
        return self.usteps_to_mm(status.data_int())

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
        self._stops += 1
        self._request("stop")
        timeout = (
            self._speed / self._accel
        ) * self._cfg.timeout_scale * 2.0 + self._cfg.timeout_margin_s
        deadline = time.monotonic() + timeout
        while (status := self._status()).busy:
            if time.monotonic() >= deadline:
                self._request("estop")
                raise MotionTimeout(
                    f"still moving {timeout:.2f} s after stop; estop sent", device=self.label
                )
            time.sleep(self._cfg.poll_interval_s)
        self._clear_interrupted(status)

    def _clear_interrupted(self, status: Reply) -> None:
        """Clear the NI a stop leaves behind, unless a fault flag is also set (that one
        is left for the next motion's check to report)."""
        if status.warning == protocol.NO_WARNING:
            return
        flags = self.warnings()
        if "NI" in flags and not flags & (protocol.FAULT_FLAGS | protocol.POSITION_LOST_FLAGS):
            self.clear_warnings()

    def estop(self) -> None:
        """Emergency stop (``estop``): halts at once; does not wait."""
        self._request("estop")

    def wait_idle(self, timeout_s: float) -> None:
        """Wait until idle (``timeout_s`` s), raising typed errors for fault flags.

        Past the timeout the axis is sent ``stop`` and MotionTimeout is raised.
        """
        self._wait(time.monotonic() + timeout_s, context="waiting for idle")

    # ------------------------------------------------------------------ split motion (XY)

    def start_home(self, timeout_s: float | None = None) -> PendingMotion:
        """Send ``home`` and return without waiting; pass the result to :meth:`finish`.

        Homing is the recovery from faults: stale fault flags are cleared first, so
        the flags seen after homing are homing's own.  Raises DeviceBusy if moving.
        """
        self._require_connected()
        status = self._status()
        if status.busy:
            raise DeviceBusy("cannot home: axis already moving", device=self.label)
        # the shown flag may hide others (WR outranks NI): read the full list
        if status.warning != protocol.NO_WARNING and self.warnings() & protocol.CLEARABLE_FLAGS:
            self.clear_warnings()
        reply = self._request("home")
        if timeout_s is None:
            low, high = self._limits_usteps
            kinematic = 2.0 * protocol.move_duration_s(
                high - low, self._home_speed, self._home_accel
            )
            timeout_s = kinematic * self._cfg.timeout_scale * 1.5 + self._cfg.timeout_margin_s
        return PendingMotion(
            "home", None, time.monotonic() + timeout_s, reply.attempts > 1, self._stops
        )

    def start_move_abs_mm(self, target_mm: float, timeout_s: float | None = None) -> PendingMotion:
        """Check and send ``move abs`` without waiting; pass the result to :meth:`finish`.

        Raises TargetOutOfRange, NotReferenced, DeviceBusy, CommandRejected, or the
        error for a fault flag still set on the device.
        """
        target = self.check_target_mm(target_mm)
        status = self._status()
        if status.warning == "WR" or self._needs_home:
            self._needs_home = self._needs_home or status.warning == "WR"
            raise NotReferenced(
                f"refusing to move to {target_mm} mm: axis not homed", device=self.label
            )
        if status.busy:
            raise DeviceBusy(
                f"cannot move to {target_mm} mm: axis already moving", device=self.label
            )
        if status.warning != "--":
            flags = self.warnings()
            self._raise_for_flags(flags, f"before moving to {target_mm} mm", ignore={"NI"})
            if "NI" in flags:  # a stale interruption (an earlier stop): not this move's
                self.clear_warnings()
        start = status.data_int()
        reply = self._request(f"move abs {target}{self._move_args}")
        if reply.warning == "WR":  # power lost between the check and the move
            self._quiet_stop()
            self._needs_home = True
            raise NotReferenced("device lost its reference (power cycle?)", device=self.label)
        if timeout_s is None:
            kinematic = protocol.move_duration_s(target - start, self._speed, self._accel)
            timeout_s = kinematic * self._cfg.timeout_scale * 1.5 + self._cfg.timeout_margin_s
        return PendingMotion(
            "move", target, time.monotonic() + timeout_s, reply.attempts > 1, self._stops
        )

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
        return min(max(target, self._limits_usteps[0]), self._limits_usteps[1])

    def finish(self, pending: PendingMotion) -> float:
        """Wait for a started motion, check flags and position; return position (mm)."""
        ignore = {"NI"} if pending.resent else set()
        if pending.kind == "home":
            self._wait(pending.deadline, context="homing", ignore=ignore)
            self._check_not_stopped(pending, "homing")
            self._needs_home = False
            return self.position_mm()
        assert pending.target_usteps is not None
        target_mm = self.usteps_to_mm(pending.target_usteps)
        context = f"moving to {target_mm:.4f} mm"
        self._wait(pending.deadline, context=context, ignore=ignore)
        self._check_not_stopped(pending, context)
        # read back with a fresh query once idle (not the data of the poll that saw IDLE)
        final = self._status()
        if final.busy:
            raise DeviceBusy("axis moving again right after the move ended", device=self.label)
        actual = final.data_int()
        actual_mm = self.usteps_to_mm(actual)
        tolerance_mm = self._cfg.tolerance_um / 1000.0
        if abs(actual_mm - target_mm) > tolerance_mm + 1e-12:
            raise PositionMismatch(
                f"idle at {actual_mm:.4f} mm, commanded {target_mm:.4f} mm "
                f"(off by {(actual_mm - target_mm) * 1000:.2f} um, tolerance {self._cfg.tolerance_um} um)",
                target_mm=target_mm,
                actual_mm=actual_mm,
                tolerance_mm=tolerance_mm,
                device=self.label,
            )
        return actual_mm

    def _check_not_stopped(self, pending: PendingMotion, context: str) -> None:
        """MoveInterrupted if ``stop()`` ran during the motion (it cleared the NI flag)."""
        if self._stops != pending.stops:
            raise MoveInterrupted(
                f"{context}: stopped by a stop command", device=self.label, flags={"NI"}
            )

    # ------------------------------------------------------------------ flags

    def warnings(self) -> frozenset[str]:
        """All warning flags active on the axis (``warnings``)."""
        return protocol.parse_warnings_data(self._request("warnings").data)

    def clear_warnings(self) -> frozenset[str]:
        """Clear the clearable flags; returns the flags that were active."""
        reply = self._request("warnings clear", retry=False)
        return protocol.parse_warnings_data(reply.data)

    # ------------------------------------------------------------------ internals

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceError("axis not connected", device=self.label, hint="call connect() first")

    def _request(self, text: str, *, axis: int | None = None, retry: bool | None = None) -> Reply:
        cfg = self._cfg
        reply = self._port.request(
            cfg.device, cfg.axis if axis is None else axis, text, label=self.label, retry=retry
        )
        if reply.rejected:
            error = protocol.rejection_error(reply, command=text, device=self.label)
            if error.reason in ("BADAXIS", "DEVICEONLY"):
                error.hint = (
                    f"the device ({cfg.device}) and axis ({cfg.axis}) numbers in the configuration"
                )
            raise error
        return reply

    def _get_int(self, setting: str) -> int:
        return self._request(f"get {setting}").data_int()

    def _get_optional(self, setting: str, *, axis: int | None = None) -> str | None:
        """A setting's value, or None when the device rejects it (unknown to this firmware,
        or not available on this axis: identity extras must not stop a connect)."""
        try:
            return self._request(f"get {setting}", axis=axis).data
        except CommandRejected:
            return None

    def _get_named(self, names: tuple[str, str], *, axis: int) -> str | None:
        """A setting firmware 7 renamed: the series' own name first, then the other."""
        ordered = names if self._version < (7, 0) else (names[1], names[0])
        for name in ordered:
            value = self._get_optional(name, axis=axis)
            if value is not None:
                return value
        return None

    def _status(self) -> Reply:
        return self._request("get pos")

    def _has_reference(self, status: Reply) -> bool:
        """False if WR is set.  A reply shows only the highest-precedence flag, so when
        the shown flag outranks WR (e.g. WT, WV) the full list is read."""
        shown = status.warning
        if shown == "WR":
            return False
        if shown == protocol.NO_WARNING or shown in _BELOW_WR:
            return True
        return "WR" not in self.warnings()

    def _quiet_stop(self) -> None:
        try:
            self._request("stop")
        except DeviceError:
            pass

    def _raise_for_flags(self, flags: frozenset[str], context: str, *, ignore: set[str]) -> None:
        """Raise the typed error for ``flags`` (after clearing them on the device)."""
        error = protocol.error_for_flags(flags, device=self.label, context=context, ignore=ignore)
        if error is None:
            return
        if flags & protocol.POSITION_LOST_FLAGS:
            self._needs_home = True
        if flags & protocol.CLEARABLE_FLAGS - ignore:
            try:
                self.clear_warnings()
            except DeviceError:
                pass
        raise error

    def _wait(self, deadline: float, *, context: str, ignore: set[str] | None = None) -> Reply:
        """Poll until idle; then map the flags to errors. Returns the final status reply."""
        ignore = ignore or set()
        while True:
            status = self._status()
            if not status.busy:
                if status.warning != "--":
                    self._raise_for_flags(self.warnings(), context, ignore=ignore)
                return status
            if time.monotonic() >= deadline:
                self._quiet_stop()
                raise MotionTimeout(
                    f"still BUSY at the deadline while {context} "
                    f"(position {self.usteps_to_mm(status.data_int()):.4f} mm); stop sent",
                    device=self.label,
                )
            time.sleep(self._cfg.poll_interval_s)


__all__ = ["PendingMotion", "ZaberAxis", "ZaberAxisConfig"]
