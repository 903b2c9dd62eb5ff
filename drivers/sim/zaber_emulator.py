"""Emulator of a chain of Zaber ASCII-protocol devices, for tests and demos.

It answers like a device: replies ``@DD A [ID] OK|RJ IDLE|BUSY WW data[:CC]``
with the RJ reasons BADCOMMAND / BADDATA / BADAXIS / DEVICEONLY /
BADMESSAGEID, warning flags with device precedence, ``comm.checksum`` and
``comm.alert`` settings, message ids, and device 0 / axis 0 addressing.
Motion has kinematics: trapezoidal profiles from ``maxspeed`` and ``accel``
(Zaber units), so BUSY lasts as long as the move would (divided by
``speedup``), decelerated ``stop``, immediate ``estop``, travel limits, and a
reference that is lost at power-up (WR) until ``home`` or ``set pos``.

Reachable over a pseudo-terminal in raw mode (``transport="pty"``: the driver
opens :attr:`ZaberEmulator.url`, a ``/dev/pts/N`` path) or over TCP bound to
127.0.0.1 only (``transport="tcp"``: ``socket://127.0.0.1:PORT``).  It runs
in a background thread: ``start()``/``stop()`` or ``with ZaberEmulator(...) as emu:``.

Fault injection (each test drives one kind)::

    emu.drop_replies(n)               command executed, reply lost
    emu.garble_replies(n)             one byte of the reply corrupted (checksum fails)
    emu.delay_replies(s, n)           reply arrives ``s`` seconds late
    emu.set_dead(device)              device answers nothing (and executes nothing)
    emu.stick_next_move(d, a)         next move never finishes: BUSY until stop/estop
    emu.stall_next_move(d, a, f)      next move stops at fraction f with FS
    emu.limit_on_next_move(d, a, f)   next move stops at fraction f with WL (or FE)
    emu.drift_next_move(d, a, n)      next move ends n microsteps off target, no flag
    emu.disconnect_on_next_move(d, a, f) / emu.disconnect()   link drops
    emu.power_cycle_on_next_move(d, a, f) / emu.power_cycle(d)   position lost, WR set
    emu.set_flags(d, a, "WT", ...)    raise any warning flag (temperature, voltage...)

Firmware series (``firmware=6`` or ``7``, per device or for the whole chain): firmware
6 names the identity settings ``deviceid`` / ``peripheralid``, firmware 7
``device.id`` / ``peripheral.id`` (each rejects the other's names with
``RJ BADCOMMAND``); ``get version`` answers ``6.32`` / ``7.38``; ``move abs|rel`` take
the optional ``speed accel`` arguments only from firmware 7.25 on (``RJ BADDATA``
before).  As on the firmware, the NI flag (command interrupted) set by ``stop`` or by
a command that interrupts a motion stays set -- through later, successful moves --
until ``warnings clear``.

Modelling choices (documented where a real device may differ): a command with
a wrong checksum is discarded without reply; moves are accepted while WR is
set (the driver is the one that refuses them); a move that interrupts another
starts from rest at the current position.
"""

from __future__ import annotations

import dataclasses
import errno
import heapq
import itertools
import math
import os
import select
import socket
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Literal

from drivers.errors import ChecksumError
from drivers.zaber import protocol

Transport = Literal["pty", "tcp"]

# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class AxisSpec:
    """One emulated axis.

    Attributes:
        microstep_um: size of one microstep (um); sets limit.max from the travel.
        travel_mm: travel from the home position (mm).
        speed_mm_s: initial maxspeed (mm/s).
        accel_mm_s2: initial accel (mm/s^2).
        start_mm: physical position at power-up (mm from home); reported as 0 with WR.
    """

    microstep_um: float = 0.1
    travel_mm: float = 100.0
    speed_mm_s: float = 20.0
    accel_mm_s2: float = 200.0
    start_mm: float = 10.0

    @property
    def limit_max(self) -> int:
        """Travel in microsteps."""
        return round(self.travel_mm * 1000.0 / self.microstep_um)

    @property
    def maxspeed_data(self) -> int:
        """Initial maxspeed setting (Zaber data units)."""
        return protocol.speed_to_data(self.speed_mm_s * 1000.0 / self.microstep_um)

    @property
    def accel_data(self) -> int:
        """Initial accel setting (Zaber data units)."""
        return protocol.accel_to_data(self.accel_mm_s2 * 1000.0 / self.microstep_um)


@dataclass(frozen=True)
class DeviceSpec:
    """One emulated device on the chain.

    Attributes:
        address: device number (1-99).
        axes: the device's axes.
        device_id: product id (``deviceid`` / ``device.id``).
        serial: ``system.serial``.
        firmware: 6 or 7: the setting names and commands of that firmware series
            (see :data:`FIRMWARE_SETTING_NAMES`).
        version: ``get version`` answer; default ``"6.32"`` or ``"7.38"`` by firmware.
        peripheral_id: per-axis ``peripheralid`` / ``peripheral.id``.
    """

    address: int = 1
    axes: tuple[AxisSpec, ...] = (AxisSpec(),)
    device_id: int = 50081
    serial: int = 100001
    firmware: int = 7
    version: str | None = None
    peripheral_id: int = 70245

    def __post_init__(self) -> None:
        if self.firmware not in (6, 7):
            raise ValueError(f"firmware must be 6 or 7, got {self.firmware}")

    @property
    def version_text(self) -> str:
        """What ``get version`` answers."""
        return self.version or ("6.32" if self.firmware == 6 else "7.38")

    @property
    def version_number(self) -> tuple[int, int]:
        """(major, minor) of :attr:`version_text`."""
        major, _, minor = self.version_text.partition(".")
        return int(major), int(minor or 0)


# --------------------------------------------------------------------------- kinematics


class _Profile(ABC):
    """1-D motion: position/velocity as functions of (scaled) time."""

    t0: float
    end_time: float
    end_pos: float

    @abstractmethod
    def position(self, t: float) -> float:
        """Position (microsteps) at time ``t``."""

    @abstractmethod
    def velocity(self, t: float) -> float:
        """Velocity (microsteps per second) at time ``t``."""


class _Trapezoid(_Profile):
    """Rest-to-rest move with maximum speed ``v`` and acceleration ``a`` (units/s, units/s^2)."""

    def __init__(self, t0: float, p0: float, p1: float, v: float, a: float) -> None:
        self.t0, self.p0, self.end_pos = t0, p0, p1
        distance = abs(p1 - p0)
        self.sign = 1.0 if p1 >= p0 else -1.0
        self.a = a
        if distance == 0:
            self.ta, self.tc, self.vp = 0.0, 0.0, 0.0
        elif distance >= v * v / a:
            self.ta, self.tc, self.vp = v / a, (distance - v * v / a) / v, v
        else:
            self.ta = math.sqrt(distance / a)
            self.tc, self.vp = 0.0, a * self.ta
        self.end_time = t0 + 2 * self.ta + self.tc

    def position(self, t: float) -> float:
        tau = min(max(t - self.t0, 0.0), self.end_time - self.t0)
        ta, tc, vp, a = self.ta, self.tc, self.vp, self.a
        if tau <= ta:
            s = 0.5 * a * tau * tau
        elif tau <= ta + tc:
            s = 0.5 * a * ta * ta + vp * (tau - ta)
        else:
            rem = 2 * ta + tc - tau
            total = a * ta * ta + vp * tc
            s = total - 0.5 * a * rem * rem
        return self.p0 + self.sign * s

    def velocity(self, t: float) -> float:
        tau = t - self.t0
        if tau <= 0 or t >= self.end_time:
            return 0.0
        if tau <= self.ta:
            speed = self.a * tau
        elif tau <= self.ta + self.tc:
            speed = self.vp
        else:
            speed = self.a * (2 * self.ta + self.tc - tau)
        return self.sign * speed


class _Decel(_Profile):
    """Deceleration from velocity ``v0`` to rest at ``a`` (a stop)."""

    def __init__(self, t0: float, p0: float, v0: float, a: float) -> None:
        self.t0, self.p0, self.v0, self.a = t0, p0, v0, a
        self.duration = abs(v0) / a if a > 0 else 0.0
        self.end_time = t0 + self.duration
        self.end_pos = self.position(self.end_time)

    def position(self, t: float) -> float:
        tau = min(max(t - self.t0, 0.0), self.duration)
        sign = 1.0 if self.v0 >= 0 else -1.0
        return self.p0 + self.v0 * tau - sign * 0.5 * self.a * tau * tau

    def velocity(self, t: float) -> float:
        tau = t - self.t0
        if tau <= 0 or tau >= self.duration:
            return 0.0
        sign = 1.0 if self.v0 >= 0 else -1.0
        return self.v0 - sign * self.a * tau


@dataclass
class _MoveFault:
    kind: Literal["stall", "limit", "stuck", "drift", "disconnect", "power"]
    fraction: float = 0.5
    flag: str = ""
    drift: int = 0
    off_s: float = 0.0


@dataclass
class _Motion:
    profile: _Profile
    kind: Literal["move", "home", "stop"]
    end_flags: tuple[str, ...] = ()
    stuck_after: bool = False


class _Axis:
    """State of one emulated axis.  Positions in microsteps, times in scaled seconds."""

    def __init__(self, number: int, spec: AxisSpec) -> None:
        self.number = number
        self.spec = spec
        # true position; the home sensor is at 0.  Reported position = phys - offset.
        self.phys = float(round(spec.start_mm * 1000.0 / spec.microstep_um))
        self.offset = self.phys
        self.limit_min = 0
        self.limit_max = spec.limit_max
        self.maxspeed = spec.maxspeed_data
        self.accel = spec.accel_data
        self.flags: set[str] = {"WR"}
        self.motion: _Motion | None = None
        self.stuck = False
        self.pending_fault: _MoveFault | None = None

    @property
    def speed(self) -> float:
        return protocol.data_to_speed(self.maxspeed)

    @property
    def acceleration(self) -> float:
        return protocol.data_to_accel(self.accel)

    def phys_at(self, t: float) -> float:
        return self.motion.profile.position(t) if self.motion else self.phys

    def reported(self, t: float) -> int:
        return round(self.phys_at(t) - self.offset)

    def busy(self, t: float) -> bool:
        return self.stuck or (self.motion is not None and t < self.motion.profile.end_time)

    def settle(self, t: float) -> bool:
        """Finish a motion whose time is over; True if one just finished."""
        motion = self.motion
        if motion is None or t < motion.profile.end_time:
            return False
        self.phys = motion.profile.end_pos
        self.motion = None
        self.flags.update(motion.end_flags)
        if motion.kind == "home":
            self.phys, self.offset = 0.0, 0.0
            self.flags.discard("WR")
        if motion.stuck_after:
            self.stuck = True
        return True

    def halt(self, t: float) -> None:
        """Freeze at the current position (no motion)."""
        self.phys = self.phys_at(t)
        self.motion = None
        self.stuck = False

    def power_loss(self, t: float) -> None:
        self.halt(t)
        self.offset = self.phys
        self.flags = {"WR"}
        self.pending_fault = None


@dataclass
class _Device:
    spec: DeviceSpec
    axes: list[_Axis]
    checksum: bool
    alert: bool
    dead: bool = False
    off_until: float = 0.0  # real time until which the device is powered off

    @property
    def address(self) -> int:
        return self.spec.address


@dataclass
class _ReplyFault:
    kind: Literal["drop", "garble", "delay"]
    remaining: int | None  # None = forever
    device: int | None
    delay_s: float = 0.0
    command: str | None = None  # only replies to commands starting with this


# --------------------------------------------------------------------------- links


class _PtyLink:
    """Master side of a raw pseudo-terminal; the driver opens :attr:`path`."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation, 8-bit clean
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.alive = True

    @property
    def url(self) -> str:
        return self.path

    def read_fds(self) -> list[int]:
        return [self.master] if self.alive else []

    def on_ready(self, ready: list[int]) -> bytes:
        if not self.alive or self.master not in ready:
            return b""
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: nobody has the slave open (cannot happen: we hold it)
            if exc.errno != errno.EIO:
                raise
            return b""

    def write(self, data: bytes) -> None:
        if not self.alive:
            return
        try:
            os.write(self.master, data)
        except (BlockingIOError, OSError):
            pass  # nobody reading: bytes are lost, as on a real line

    def disconnect(self) -> None:
        """Drop the line: the driver's next read/write fails (like an unplugged adapter)."""
        if self.alive:
            self.alive = False
            for fd in (self.master, self.slave):
                try:
                    os.close(fd)
                except OSError:
                    pass

    def close(self) -> None:
        self.disconnect()


class _TcpLink:
    """TCP server on 127.0.0.1 with one client at a time (like a serial line)."""

    def __init__(self, port: int) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", port))  # loopback only, never any other address
        self.listener.listen(1)
        self.listener.setblocking(False)
        self.port = self.listener.getsockname()[1]
        self.client: socket.socket | None = None

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def read_fds(self) -> list[int]:
        fds = [self.listener.fileno()]
        if self.client is not None:
            fds.append(self.client.fileno())
        return fds

    def on_ready(self, ready: list[int]) -> bytes:
        data = b""
        if self.client is not None and self.client.fileno() in ready:
            try:
                data = self.client.recv(4096)
            except OSError:
                data = b""
            if not data:
                self._drop_client()
        if self.listener.fileno() in ready:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                conn = None
            if conn is not None:
                if self.client is None:
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    conn.settimeout(1.0)
                    self.client = conn
                else:
                    conn.close()  # the line is taken
        return data

    def write(self, data: bytes) -> None:
        if self.client is None:
            return
        try:
            self.client.sendall(data)
        except OSError:
            self._drop_client()

    def _drop_client(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            except OSError:
                pass
            self.client = None

    def disconnect(self) -> None:
        """Close the current client connection; new connections are still accepted."""
        self._drop_client()

    def close(self) -> None:
        self._drop_client()
        self.listener.close()


# --------------------------------------------------------------------------- emulator

#: Settings whose name differs between the firmware series: (firmware 6, firmware 7).
#: Firmware 7 renamed the identity settings (Zaber's FW7 protocol manual); a device of
#: either series rejects the other series' name with ``RJ BADCOMMAND``.
FIRMWARE_SETTING_NAMES: dict[str, tuple[str, str]] = {
    "device_id": ("deviceid", "device.id"),
    "peripheral_id": ("peripheralid", "peripheral.id"),
}
#: ``move abs``/``move rel`` take optional speed and acceleration arguments from 7.25 on.
MOVE_SPEED_ARGS_SINCE = (7, 25)

_DEVICE_SETTINGS = (
    "device_id",
    "system.serial",
    "version",
    "comm.checksum",
    "comm.alert",
    "system.axiscount",
)
_AXIS_SETTINGS = ("pos", "maxspeed", "accel", "limit.min", "limit.max", "peripheral_id")
_READ_ONLY = frozenset(
    {"device_id", "system.serial", "version", "system.axiscount", "peripheral_id"}
)


def _canonical_setting(name: str, firmware: int) -> str | None:
    """The internal key of a setting name as a device of ``firmware`` knows it (None:
    unknown to that firmware, e.g. ``device.id`` on firmware 6)."""
    for key, names in FIRMWARE_SETTING_NAMES.items():
        if name in names:
            return key if names[0 if firmware == 6 else 1] == name else None
        if name == key:
            return None
    return name


@dataclass(frozen=True)
class AxisSnapshot:
    """What an emulated axis is doing (for test assertions)."""

    position: int
    physical: float
    busy: bool
    flags: frozenset[str]


@dataclass
class EmulatorStats:
    """Counters of what the emulator received and sent."""

    commands: int = 0
    bad_checksum: int = 0
    replies: int = 0
    dropped: int = 0
    garbled: int = 0
    delayed: int = 0
    delayed_sent: int = 0
    alerts: int = 0


@dataclass(order=True)
class _Event:
    when: float
    seq: int
    action: Callable[[], None] = field(compare=False)


class ZaberEmulator:
    """A chain of emulated Zaber devices behind one pty or 127.0.0.1 TCP port.

    Args:
        devices: the chain (default: one single-axis device at address 1).
        transport: ``"pty"`` or ``"tcp"``.
        tcp_port: TCP port to listen on (0 = any free port).
        speedup: motion runs this many times faster than real time.
        checksum: initial comm.checksum (devices ship with 0).
        alert: initial comm.alert.
        firmware: 6 or 7: make every device of the chain behave like that firmware
            series (None: as each :class:`DeviceSpec` says, default 7).
    """

    def __init__(
        self,
        devices: list[DeviceSpec] | tuple[DeviceSpec, ...] | None = None,
        *,
        transport: Transport = "pty",
        tcp_port: int = 0,
        speedup: float = 1.0,
        checksum: bool = False,
        alert: bool = False,
        firmware: int | None = None,
    ) -> None:
        specs = list(devices) if devices else [DeviceSpec()]
        if firmware is not None:
            specs = [dataclasses.replace(spec, firmware=firmware) for spec in specs]
        addresses = [spec.address for spec in specs]
        if len(set(addresses)) != len(addresses) or not all(1 <= a <= 99 for a in addresses):
            raise ValueError(f"device addresses must be unique and 1-99, got {addresses}")
        if speedup <= 0:
            raise ValueError("speedup must be positive")
        if transport not in ("pty", "tcp"):
            raise ValueError(f"unknown transport {transport!r}")
        self._devices = [
            _Device(spec, [_Axis(i + 1, a) for i, a in enumerate(spec.axes)], checksum, alert)
            for spec in sorted(specs, key=lambda s: s.address)
        ]
        self._transport: Transport = transport
        self._tcp_port = tcp_port
        self.speedup = float(speedup)
        self._lock = threading.RLock()
        self._events: list[_Event] = []
        self._seq = itertools.count()
        self._reply_faults: list[_ReplyFault] = []
        self._inbuf = bytearray()
        self._command_text = ""  # text of the command being answered (for reply faults)
        self._link: _PtyLink | _TcpLink | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._wake_r, self._wake_w = -1, -1
        self._t0 = time.monotonic()
        self.stats = EmulatorStats()
        #: Command lines received (decoded, newest last) for protocol assertions.
        self.received: deque[str] = deque(maxlen=2000)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> ZaberEmulator:
        """Open the pty / TCP listener and start serving in a background thread."""
        with self._lock:
            if self._thread is not None:
                return self
            self._link = _PtyLink() if self._transport == "pty" else _TcpLink(self._tcp_port)
            self._wake_r, self._wake_w = os.pipe()
            os.set_blocking(self._wake_r, False)
            self._stopping.clear()
            self._thread = threading.Thread(target=self._serve, name="zaber-emulator", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and release the pty / socket (idempotent)."""
        thread = self._thread
        if thread is None:
            return
        self._stopping.set()
        self._wake()
        thread.join(timeout=5.0)
        with self._lock:
            self._thread = None
            if self._link is not None:
                self._link.close()
            for fd in (self._wake_r, self._wake_w):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._wake_r = self._wake_w = -1

    def __enter__(self) -> ZaberEmulator:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def url(self) -> str:
        """What the driver opens: a ``/dev/pts/N`` path or ``socket://127.0.0.1:PORT``."""
        if self._link is None:
            raise RuntimeError("emulator not started")
        return self._link.url

    @property
    def bound_address(self) -> tuple[str, int] | None:
        """(host, port) the TCP server listens on; None for a pty."""
        link = self._link
        if isinstance(link, _TcpLink):
            host, port = link.listener.getsockname()[:2]
            return str(host), int(port)
        return None

    # ------------------------------------------------------------------ inspection (thread-safe)

    def snapshot(self, device: int = 1, axis: int = 1) -> AxisSnapshot:
        """Position (reported microsteps), physical position, busy and flags of one axis."""
        with self._lock:
            now = self._now()
            ax = self._axis(device, axis)
            self._settle(self._device(device), ax, now)
            return AxisSnapshot(
                ax.reported(now), ax.phys_at(now), ax.busy(now), frozenset(ax.flags)
            )

    def firmware(self, device: int) -> int:
        """Firmware series (6 or 7) of ``device``."""
        with self._lock:
            return self._device(device).spec.firmware

    def device_checksum(self, device: int) -> bool:
        """Current ``comm.checksum`` of ``device``."""
        with self._lock:
            return self._device(device).checksum

    def stop_axis(self, device: int, axis: int) -> None:
        """Stop a moving axis as a ``stop`` from elsewhere would (no reply is sent): it
        decelerates and raises NI."""
        with self._lock:
            dev = self._device(device)
            self._cmd_stop(dev, axis, [self._axis(device, axis)], [], self._now())

    def is_powered(self, device: int) -> bool:
        """False while ``device`` is off after a power cycle (it answers nothing then)."""
        with self._lock:
            return self._device(device).off_until <= time.monotonic()

    def setting(self, device: int, axis: int, name: str) -> int:
        """Current value of an axis setting (pos, maxspeed, accel, limit.min, limit.max)."""
        with self._lock:
            ax = self._axis(device, axis)
            value = self._get_axis_setting(ax, name, self._now())
            assert value is not None
            return value

    # ------------------------------------------------------------------ fault injection

    def drop_replies(
        self, count: int | None = 1, *, device: int | None = None, command: str | None = None
    ) -> None:
        """Execute the next ``count`` commands but send no reply (None = all).

        ``device`` / ``command`` restrict the fault to one device / to commands
        starting with ``command`` (e.g. ``"move abs"``), for this and the methods below.
        """
        self._add_reply_fault(_ReplyFault("drop", count, device, command=command))

    def garble_replies(
        self, count: int | None = 1, *, device: int | None = None, command: str | None = None
    ) -> None:
        """Corrupt one byte in each of the next ``count`` replies (None = all)."""
        self._add_reply_fault(_ReplyFault("garble", count, device, command=command))

    def delay_replies(
        self,
        delay_s: float,
        count: int | None = 1,
        *,
        device: int | None = None,
        command: str | None = None,
    ) -> None:
        """Send each of the next ``count`` replies ``delay_s`` real seconds late."""
        self._add_reply_fault(_ReplyFault("delay", count, device, delay_s, command))

    def clear_faults(self) -> None:
        """Remove pending reply faults and pending move faults; revive dead devices."""
        with self._lock:
            self._reply_faults.clear()
            for dev in self._devices:
                dev.dead = False
                for ax in dev.axes:
                    ax.pending_fault = None

    def set_dead(self, device: int, dead: bool = True) -> None:
        """A dead device neither executes nor answers anything."""
        with self._lock:
            self._device(device).dead = dead

    def stick_next_move(self, device: int, axis: int) -> None:
        """The next move goes part of the way and then stays BUSY until stop/estop."""
        self._set_move_fault(device, axis, _MoveFault("stuck", 0.3))

    def stall_next_move(self, device: int, axis: int, at_fraction: float = 0.5) -> None:
        """The next move stalls at ``at_fraction`` of its distance and raises FS."""
        self._set_move_fault(device, axis, _MoveFault("stall", at_fraction, "FS"))

    def limit_on_next_move(
        self, device: int, axis: int, at_fraction: float = 0.5, *, flag: str = "WL"
    ) -> None:
        """The next move is stopped by a limit sensor at ``at_fraction``: WL (or FE)."""
        if flag not in ("WL", "FE"):
            raise ValueError("flag must be WL or FE")
        self._set_move_fault(device, axis, _MoveFault("limit", at_fraction, flag))

    def drift_next_move(self, device: int, axis: int, microsteps: int) -> None:
        """The next move ends ``microsteps`` away from its target, with no flag."""
        self._set_move_fault(device, axis, _MoveFault("drift", 1.0, drift=microsteps))

    def disconnect_on_next_move(self, device: int, axis: int, at_fraction: float = 0.5) -> None:
        """The line drops when the next move reaches ``at_fraction`` of its duration."""
        self._set_move_fault(device, axis, _MoveFault("disconnect", at_fraction))

    def power_cycle_on_next_move(
        self, device: int, axis: int, at_fraction: float = 0.5, *, off_s: float = 0.1
    ) -> None:
        """The device loses power at ``at_fraction`` of the next move (off ``off_s`` s)."""
        self._set_move_fault(device, axis, _MoveFault("power", at_fraction, off_s=off_s))

    def set_flags(self, device: int, axis: int, *flags: str) -> None:
        """Raise warning flags on an axis directly (e.g. ``"WT"`` temperature, ``"WV"`` voltage)."""
        unknown = set(flags) - set(protocol.WARNING_FLAGS)
        if unknown:
            raise ValueError(f"unknown warning flags {sorted(unknown)}")
        with self._lock:
            self._axis(device, axis).flags.update(flags)

    def disconnect(self) -> None:
        """Drop the line now (pty: closed for good; TCP: current client closed)."""
        with self._lock:
            if self._link is not None:
                self._link.disconnect()

    def power_cycle(self, device: int, *, off_s: float = 0.1) -> None:
        """Power-cycle ``device`` now: motion stops, positions lost (WR), silent ``off_s`` s."""
        with self._lock:
            self._power_cycle(self._device(device), off_s)

    # ------------------------------------------------------------------ internals: helpers

    def _now(self) -> float:
        """Scaled (motion) time in seconds."""
        return (time.monotonic() - self._t0) * self.speedup

    def _real_time(self, scaled: float) -> float:
        return self._t0 + scaled / self.speedup

    def _device(self, address: int) -> _Device:
        for dev in self._devices:
            if dev.address == address:
                return dev
        raise KeyError(f"no emulated device {address}")

    def _axis(self, device: int, axis: int) -> _Axis:
        dev = self._device(device)
        if not 1 <= axis <= len(dev.axes):
            raise KeyError(f"device {device} has no axis {axis}")
        return dev.axes[axis - 1]

    def _add_reply_fault(self, fault: _ReplyFault) -> None:
        with self._lock:
            self._reply_faults.append(fault)

    def _set_move_fault(self, device: int, axis: int, fault: _MoveFault) -> None:
        if not 0.0 <= fault.fraction <= 1.0:
            raise ValueError("at_fraction must be within 0..1")
        with self._lock:
            self._axis(device, axis).pending_fault = fault

    def _wake(self) -> None:
        if self._wake_w >= 0:
            try:
                os.write(self._wake_w, b"x")
            except OSError:
                pass

    def _schedule(self, real_when: float, action: Callable[[], None]) -> None:
        heapq.heappush(self._events, _Event(real_when, next(self._seq), action))
        self._wake()

    def _power_cycle(self, dev: _Device, off_s: float) -> None:
        now = self._now()
        for ax in dev.axes:
            ax.power_loss(now)
        dev.off_until = time.monotonic() + off_s

    # ------------------------------------------------------------------ internals: serving

    def _serve(self) -> None:
        while not self._stopping.is_set():
            with self._lock:
                link = self._link
                timeout = 0.2
                if self._events:
                    timeout = min(timeout, max(0.0, self._events[0].when - time.monotonic()))
                fds = [self._wake_r] + (link.read_fds() if link else [])
            try:
                ready, _, _ = select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                ready = []  # a descriptor was closed under us (disconnect); loop again
            with self._lock:
                if self._stopping.is_set():
                    return
                if self._wake_r in ready:
                    try:
                        os.read(self._wake_r, 4096)
                    except OSError:
                        pass
                if link is not None and link is self._link:
                    data = link.on_ready([fd for fd in ready if fd != self._wake_r])
                    if data:
                        self._feed(data)
                self._run_due_events()

    def _run_due_events(self) -> None:
        while self._events and self._events[0].when <= time.monotonic():
            heapq.heappop(self._events).action()

    def _send(self, data: bytes) -> None:
        if self._link is not None:
            self._link.write(data)

    def _feed(self, data: bytes) -> None:
        self._inbuf += data
        while True:
            cut = min(
                (i for i in (self._inbuf.find(b"\n"), self._inbuf.find(b"\r")) if i >= 0),
                default=-1,
            )
            if cut < 0:
                if len(self._inbuf) > 1024:
                    self._inbuf.clear()
                return
            raw = bytes(self._inbuf[:cut])
            del self._inbuf[: cut + 1]
            if raw.strip():
                self._handle_line(raw)

    def _handle_line(self, raw: bytes) -> None:
        self._run_due_events()
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            return
        if any(not 32 <= ord(c) <= 126 for c in text) or "/" not in text:
            return  # unsupported characters: a device discards the incomplete command
        self.received.append(text[text.find("/") :])
        self.stats.commands += 1
        self._command_text = ""
        try:
            command, _ = protocol.parse_command(text)
        except ChecksumError:
            self.stats.bad_checksum += 1
            return  # modelling choice: a command with a wrong checksum is dropped silently
        except protocol.CommandSyntaxError as exc:
            for dev in self._targets(exc.device):
                self._reply(dev, 0, None, rejected=True, data=exc.reason)
            return
        if command.device > protocol.MAX_DEVICE:
            return
        for dev in self._targets(command.device):
            self._execute(dev, command)

    def _targets(self, address: int) -> list[_Device]:
        now = time.monotonic()
        return [
            dev
            for dev in self._devices
            if (address in (0, dev.address)) and not dev.dead and dev.off_until <= now
        ]

    # ------------------------------------------------------------------ replies

    def _reply(
        self,
        dev: _Device,
        axis: int,
        message_id: int | None,
        *,
        rejected: bool = False,
        data: str = "0",
        now: float | None = None,
    ) -> None:
        # one timestamp per command: status, flags and data must describe the same instant
        now = self._now() if now is None else now
        axes = dev.axes if axis == 0 else [dev.axes[axis - 1]] if axis <= len(dev.axes) else []
        for ax in axes:
            self._settle(dev, ax, now)
        flags: set[str] = set()
        for ax in axes:
            flags |= ax.flags
        busy = any(ax.busy(now) for ax in axes)
        line = protocol.format_reply(
            dev.address,
            axis,
            message_id=message_id,
            rejected=rejected,
            busy=busy,
            warning=protocol.highest_warning(flags),
            data=data,
            checksum=dev.checksum,
        )
        self._deliver(dev, line)

    def _deliver(self, dev: _Device, line: bytes) -> None:
        self.stats.replies += 1
        fault = next(
            (
                f
                for f in self._reply_faults
                if f.device in (None, dev.address)
                and (f.command is None or self._command_text.startswith(f.command))
            ),
            None,
        )
        if fault is not None:
            if fault.remaining is not None:
                fault.remaining -= 1
                if fault.remaining <= 0:
                    self._reply_faults.remove(fault)
            if fault.kind == "drop":
                self.stats.dropped += 1
                return
            if fault.kind == "garble":
                self.stats.garbled += 1
                line = _garble(line, self.stats.garbled)
            else:
                self.stats.delayed += 1

                def send_late(late: bytes = line) -> None:
                    self.stats.delayed_sent += 1
                    self._send(late)

                self._schedule(time.monotonic() + fault.delay_s, send_late)
                return
        self._send(line)

    def _settle(self, dev: _Device, ax: _Axis, now: float) -> None:
        """Finish ``ax``'s motion if its time is over, with the alert it triggers."""
        if ax.settle(now):
            self._alert(dev, ax)

    def _alert(self, dev: _Device, ax: _Axis) -> None:
        if dev.alert and not dev.dead and dev.off_until <= time.monotonic():
            self.stats.alerts += 1
            now = self._now()
            self._send(
                protocol.format_alert(
                    dev.address,
                    ax.number,
                    busy=ax.busy(now),
                    warning=protocol.highest_warning(ax.flags),
                    checksum=dev.checksum,
                )
            )

    # ------------------------------------------------------------------ commands

    def _execute(self, dev: _Device, cmd: protocol.Command) -> None:
        self._command_text = cmd.text
        mid = cmd.message_id
        if cmd.axis > len(dev.axes):
            self._reply(dev, cmd.axis, mid, rejected=True, data="BADAXIS")
            return
        words = cmd.text.split()
        verb = words[0] if words else ""
        args = words[1:]
        axes = dev.axes if cmd.axis == 0 else [dev.axes[cmd.axis - 1]]
        now = self._now()
        for ax in dev.axes:
            self._settle(dev, ax, now)
        handler = {
            "": self._cmd_status,
            "home": self._cmd_home,
            "move": self._cmd_move,
            "stop": self._cmd_stop,
            "estop": self._cmd_estop,
            "get": self._cmd_get,
            "set": self._cmd_set,
            "warnings": self._cmd_warnings,
            "system": self._cmd_system,
        }.get(verb)
        if handler is None:
            self._reply(dev, cmd.axis, mid, rejected=True, data="BADCOMMAND")
            return
        outcome = handler(dev, cmd.axis, axes, args, now)
        post: Callable[[], None] | None = None
        if isinstance(outcome, tuple):
            outcome, post = outcome
        if outcome.startswith("RJ "):
            self._reply(dev, cmd.axis, mid, rejected=True, data=outcome[3:], now=now)
        else:
            self._reply(dev, cmd.axis, mid, data=outcome, now=now)
        if post is not None:
            post()

    def _cmd_status(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        return "0"

    def _cmd_home(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if args:
            return "RJ BADDATA"
        for ax in axes:
            self._start_motion(dev, ax, target_phys=0.0, kind="home", now=now)
        return "0"

    def _cmd_move(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if not args or args[0] not in ("abs", "rel", "min", "max"):
            return "RJ BADCOMMAND"
        mode, rest = args[0], args[1:]
        speed: int | None = None
        accel: int | None = None
        if mode in ("abs", "rel"):
            # move abs|rel <value> [speed accel]: the optional pair only from 7.25 on
            with_speed = dev.spec.version_number >= MOVE_SPEED_ARGS_SINCE
            if len(rest) not in ((1, 3) if with_speed else (1,)):
                return "RJ BADDATA"
            if not all(_is_int(token) for token in rest):
                return "RJ BADDATA"
            value = int(rest[0])
            if len(rest) == 3:
                speed, accel = int(rest[1]), int(rest[2])
                if speed < 0 or accel < 0:
                    return "RJ BADDATA"
                speed, accel = speed or None, accel or None  # 0: the setting's value
        elif rest:
            return "RJ BADDATA"
        else:
            value = 0
        targets: list[tuple[_Axis, int]] = []
        for ax in axes:
            current = ax.reported(now)
            target = {
                "abs": value,
                "rel": current + value,
                "min": ax.limit_min,
                "max": ax.limit_max,
            }[mode]
            if not ax.limit_min <= target <= ax.limit_max:
                return "RJ BADDATA"
            targets.append((ax, target))
        for ax, target in targets:
            self._start_motion(
                dev,
                ax,
                target_phys=target + ax.offset,
                kind="move",
                now=now,
                speed=speed,
                accel=accel,
            )
        return "0"

    def _cmd_stop(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if args:
            return "RJ BADDATA"
        for ax in axes:
            if not ax.busy(now):
                continue
            ax.flags.add("NI")
            if ax.stuck or ax.motion is None:
                ax.halt(now)
                continue
            pos, vel = ax.phys_at(now), ax.motion.profile.velocity(now)
            ax.phys = pos
            ax.motion = _Motion(_Decel(now, pos, vel, ax.acceleration), "stop")
            self._schedule_settle(dev, ax, ax.motion)
        return "0"

    def _cmd_estop(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if args:
            return "RJ BADDATA"
        for ax in axes:
            if ax.busy(now):
                ax.flags.add("NI")
            ax.halt(now)
        return "0"

    def _cmd_get(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if len(args) != 1:
            return "RJ BADCOMMAND" if not args else "RJ BADDATA"
        name = _canonical_setting(args[0], dev.spec.firmware)
        if name in _DEVICE_SETTINGS:
            if axis != 0:
                return "RJ DEVICEONLY"
            return {
                "device_id": str(dev.spec.device_id),
                "system.serial": str(dev.spec.serial),
                "version": dev.spec.version_text,
                "comm.checksum": str(int(dev.checksum)),
                "comm.alert": str(int(dev.alert)),
                "system.axiscount": str(len(dev.axes)),
            }[name]
        if name in _AXIS_SETTINGS:
            # axis 0: one value per axis, in axis order (the manual's "get" of a device)
            values = [self._get_axis_setting(ax, name, now, dev) for ax in axes]
            return " ".join(str(v) for v in values)
        return "RJ BADCOMMAND"

    @staticmethod
    def _get_axis_setting(
        ax: _Axis, name: str, now: float, dev: _Device | None = None
    ) -> int | None:
        return {
            "pos": ax.reported(now),
            "maxspeed": ax.maxspeed,
            "accel": ax.accel,
            "limit.min": ax.limit_min,
            "limit.max": ax.limit_max,
            "peripheral_id": dev.spec.peripheral_id if dev is not None else 0,
        }.get(name)

    def _cmd_set(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if len(args) != 2:
            return "RJ BADCOMMAND" if not args else "RJ BADDATA"
        name = _canonical_setting(args[0], dev.spec.firmware)
        raw = args[1]
        if name not in _DEVICE_SETTINGS and name not in _AXIS_SETTINGS:
            return "RJ BADCOMMAND"
        if name in _READ_ONLY or not _is_int(raw):
            return "RJ BADDATA"
        value = int(raw)
        if name in _DEVICE_SETTINGS:
            if axis != 0:
                return "RJ DEVICEONLY"
            if value not in (0, 1):
                return "RJ BADDATA"
            if name == "comm.checksum":
                dev.checksum = bool(value)  # applies to this very reply, as on a device
            else:
                dev.alert = bool(value)
            return "0"
        for ax in axes:
            if name in ("maxspeed", "accel") and value < 1:
                return "RJ BADDATA"
            if name == "pos" and (ax.busy(now) or not ax.limit_min <= value <= ax.limit_max):
                return "RJ BADDATA"
        for ax in axes:
            if name == "pos":
                ax.offset = ax.phys - value
                ax.flags.discard("WR")
            elif name == "maxspeed":
                ax.maxspeed = value
            elif name == "accel":
                ax.accel = value
            elif name == "limit.min":
                ax.limit_min = value
            else:
                ax.limit_max = value
        return "0"

    def _cmd_warnings(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str:
        if args not in ([], ["clear"]):
            return "RJ BADDATA"
        flags: set[str] = set()
        for ax in axes:
            flags |= ax.flags
        ordered = [f for f in protocol.WARNING_PRIORITY if f in flags]
        if args == ["clear"]:
            for ax in axes:
                ax.flags -= protocol.CLEARABLE_FLAGS
        return " ".join([f"{len(ordered):02d}", *ordered])

    def _cmd_system(
        self, dev: _Device, axis: int, axes: list[_Axis], args: list[str], now: float
    ) -> str | tuple[str, Callable[[], None]]:
        if args != ["reset"]:
            return "RJ BADCOMMAND"
        if axis != 0:
            return "RJ DEVICEONLY"
        return "0", lambda: self._power_cycle(dev, 0.05)

    # ------------------------------------------------------------------ motion

    def _start_motion(
        self,
        dev: _Device,
        ax: _Axis,
        *,
        target_phys: float,
        kind: Literal["move", "home"],
        now: float,
        speed: int | None = None,
        accel: int | None = None,
    ) -> None:
        # Like the firmware: NI marks an interrupted motion and stays set until
        # "warnings clear" -- a later, successful move does not clear it.
        if ax.busy(now):
            ax.flags.add("NI")  # the running motion is interrupted
        velocity = protocol.data_to_speed(speed) if speed else ax.speed
        acceleration = protocol.data_to_accel(accel) if accel else ax.acceleration
        start = ax.phys_at(now)
        ax.halt(now)
        ax.phys = start
        fault = ax.pending_fault if kind == "move" else None
        if fault is not None:
            ax.pending_fault = None
        end = target_phys
        end_flags: tuple[str, ...] = ()
        stuck_after = False
        if fault is not None:
            if fault.kind in ("stall", "limit", "stuck"):
                end = start + fault.fraction * (target_phys - start)
                end_flags = (fault.flag,) if fault.flag else ()
                stuck_after = fault.kind == "stuck"
            elif fault.kind == "drift":
                end = target_phys + fault.drift
        if kind == "move" and ax.offset != 0.0:
            end = min(max(end, 0.0), float(ax.spec.limit_max))  # physical end stops
        profile = _Trapezoid(now, start, end, velocity, acceleration)
        motion = _Motion(profile, kind, end_flags, stuck_after)
        ax.motion = motion
        self._schedule_settle(dev, ax, motion)
        if fault is not None and fault.kind in ("disconnect", "power"):
            full = _Trapezoid(now, start, target_phys, velocity, acceleration)
            at = self._real_time(now + fault.fraction * (full.end_time - now))
            if fault.kind == "disconnect":
                self._schedule(at, self._fault_disconnect)
            else:
                off_s = fault.off_s
                self._schedule(at, lambda: self._power_cycle(dev, off_s))

    def _fault_disconnect(self) -> None:
        if self._link is not None:
            self._link.disconnect()

    def _schedule_settle(self, dev: _Device, ax: _Axis, motion: _Motion) -> None:
        def settle() -> None:
            if ax.motion is motion:
                self._settle(dev, ax, self._now())

        self._schedule(self._real_time(motion.profile.end_time) + 1e-4, settle)


def _is_int(text: str) -> bool:
    return text.lstrip("+-").isdigit() and len(text) < 20


def _garble(line: bytes, salt: int) -> bytes:
    """Change one byte of the body (not the start char nor the terminator)."""
    body_end = len(line.rstrip(b"\r\n"))
    index = 1 + (salt * 7) % max(1, body_end - 1)
    value = line[index]
    replacement = value + 1 if value < 126 else value - 1
    if replacement in (ord("\r"), ord("\n")):
        replacement = ord("#")
    return line[:index] + bytes([replacement]) + line[index + 1 :]


__all__ = ["AxisSnapshot", "AxisSpec", "DeviceSpec", "EmulatorStats", "ZaberEmulator"]
