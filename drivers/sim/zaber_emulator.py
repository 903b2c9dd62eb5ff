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
import heapq
import itertools
import os
import select
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Literal

from drivers.errors import ChecksumError
from drivers.sim.emulator_links import PtyLink, TcpLink, Transport
from drivers.sim.zaber_axes import (
    AxisSpec,
    DecelerationProfile,
    DeviceSpec,
    EmulatedAxis,
    EmulatedDevice,
    Motion,
    MoveFault,
    ReplyFault,
    TrapezoidProfile,
)
from drivers.sim.zaber_settings import (
    MOVE_SPEED_ARGS_SINCE,
    axis_setting,
    get_setting,
    is_int,
    set_setting,
    warning_flags,
)
from drivers.zaber import protocol

# --------------------------------------------------------------------------- emulator


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
            EmulatedDevice(
                spec, [EmulatedAxis(i + 1, a) for i, a in enumerate(spec.axes)], checksum, alert
            )
            for spec in sorted(specs, key=lambda s: s.address)
        ]
        self._transport: Transport = transport
        self._tcp_port = tcp_port
        self.speedup = float(speedup)
        self._lock = threading.RLock()
        self._events: list[_Event] = []
        self._seq = itertools.count()
        self._reply_faults: list[ReplyFault] = []
        self._inbuf = bytearray()
        self._command_text = ""  # text of the command being answered (for reply faults)
        self._link: PtyLink | TcpLink | None = None
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
            self._link = PtyLink() if self._transport == "pty" else TcpLink(self._tcp_port)
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
        if isinstance(link, TcpLink):
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
            value = axis_setting(ax, name, self._now())
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
        self._add_reply_fault(ReplyFault("drop", count, device, command=command))

    def garble_replies(
        self, count: int | None = 1, *, device: int | None = None, command: str | None = None
    ) -> None:
        """Corrupt one byte in each of the next ``count`` replies (None = all)."""
        self._add_reply_fault(ReplyFault("garble", count, device, command=command))

    def delay_replies(
        self,
        delay_s: float,
        count: int | None = 1,
        *,
        device: int | None = None,
        command: str | None = None,
    ) -> None:
        """Send each of the next ``count`` replies ``delay_s`` real seconds late."""
        self._add_reply_fault(ReplyFault("delay", count, device, delay_s, command))

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
        self._set_move_fault(device, axis, MoveFault("stuck", 0.3))

    def stall_next_move(self, device: int, axis: int, at_fraction: float = 0.5) -> None:
        """The next move stalls at ``at_fraction`` of its distance and raises FS."""
        self._set_move_fault(device, axis, MoveFault("stall", at_fraction, "FS"))

    def limit_on_next_move(
        self, device: int, axis: int, at_fraction: float = 0.5, *, flag: str = "WL"
    ) -> None:
        """The next move is stopped by a limit sensor at ``at_fraction``: WL (or FE)."""
        if flag not in ("WL", "FE"):
            raise ValueError("flag must be WL or FE")
        self._set_move_fault(device, axis, MoveFault("limit", at_fraction, flag))

    def drift_next_move(self, device: int, axis: int, microsteps: int) -> None:
        """The next move ends ``microsteps`` away from its target, with no flag."""
        self._set_move_fault(device, axis, MoveFault("drift", 1.0, drift=microsteps))

    def disconnect_on_next_move(self, device: int, axis: int, at_fraction: float = 0.5) -> None:
        """The line drops when the next move reaches ``at_fraction`` of its duration."""
        self._set_move_fault(device, axis, MoveFault("disconnect", at_fraction))

    def power_cycle_on_next_move(
        self, device: int, axis: int, at_fraction: float = 0.5, *, off_s: float = 0.1
    ) -> None:
        """The device loses power at ``at_fraction`` of the next move (off ``off_s`` s)."""
        self._set_move_fault(device, axis, MoveFault("power", at_fraction, off_s=off_s))

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

    def _device(self, address: int) -> EmulatedDevice:
        for dev in self._devices:
            if dev.address == address:
                return dev
        raise KeyError(f"no emulated device {address}")

    def _axis(self, device: int, axis: int) -> EmulatedAxis:
        dev = self._device(device)
        if not 1 <= axis <= len(dev.axes):
            raise KeyError(f"device {device} has no axis {axis}")
        return dev.axes[axis - 1]

    def _add_reply_fault(self, fault: ReplyFault) -> None:
        with self._lock:
            self._reply_faults.append(fault)

    def _set_move_fault(self, device: int, axis: int, fault: MoveFault) -> None:
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

    def _power_cycle(self, dev: EmulatedDevice, off_s: float) -> None:
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

    def _targets(self, address: int) -> list[EmulatedDevice]:
        now = time.monotonic()
        return [
            dev
            for dev in self._devices
            if (address in (0, dev.address)) and not dev.dead and dev.off_until <= now
        ]

    # ------------------------------------------------------------------ replies

    def _reply(
        self,
        dev: EmulatedDevice,
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

    def _deliver(self, dev: EmulatedDevice, line: bytes) -> None:
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

    def _settle(self, dev: EmulatedDevice, ax: EmulatedAxis, now: float) -> None:
        """Finish ``ax``'s motion if its time is over, with the alert it triggers."""
        if ax.settle(now):
            self._alert(dev, ax)

    def _alert(self, dev: EmulatedDevice, ax: EmulatedAxis) -> None:
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

    def _execute(self, dev: EmulatedDevice, cmd: protocol.Command) -> None:
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
            "get": get_setting,
            "set": set_setting,
            "warnings": warning_flags,
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
        self, dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
    ) -> str:
        return "0"

    def _cmd_home(
        self, dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
    ) -> str:
        if args:
            return "RJ BADDATA"
        for ax in axes:
            self._start_motion(dev, ax, target_phys=0.0, kind="home", now=now)
        return "0"

    def _cmd_move(
        self, dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
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
            if not all(is_int(token) for token in rest):
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
        targets: list[tuple[EmulatedAxis, int]] = []
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
        self, dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
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
            ax.motion = Motion(DecelerationProfile(now, pos, vel, ax.acceleration), "stop")
            self._schedule_settle(dev, ax, ax.motion)
        return "0"

    def _cmd_estop(
        self, dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
    ) -> str:
        if args:
            return "RJ BADDATA"
        for ax in axes:
            if ax.busy(now):
                ax.flags.add("NI")
            ax.halt(now)
        return "0"

    def _cmd_system(
        self, dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
    ) -> str | tuple[str, Callable[[], None]]:
        if args != ["reset"]:
            return "RJ BADCOMMAND"
        if axis != 0:
            return "RJ DEVICEONLY"
        return "0", lambda: self._power_cycle(dev, 0.05)

    # ------------------------------------------------------------------ motion

    def _start_motion(
        self,
        dev: EmulatedDevice,
        ax: EmulatedAxis,
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
        profile = TrapezoidProfile(now, start, end, velocity, acceleration)
        motion = Motion(profile, kind, end_flags, stuck_after)
        ax.motion = motion
        self._schedule_settle(dev, ax, motion)
        if fault is not None and fault.kind in ("disconnect", "power"):
            full = TrapezoidProfile(now, start, target_phys, velocity, acceleration)
            at = self._real_time(now + fault.fraction * (full.end_time - now))
            if fault.kind == "disconnect":
                self._schedule(at, self._fault_disconnect)
            else:
                off_s = fault.off_s
                self._schedule(at, lambda: self._power_cycle(dev, off_s))

    def _fault_disconnect(self) -> None:
        if self._link is not None:
            self._link.disconnect()

    def _schedule_settle(self, dev: EmulatedDevice, ax: EmulatedAxis, motion: Motion) -> None:
        def settle() -> None:
            if ax.motion is motion:
                self._settle(dev, ax, self._now())

        self._schedule(self._real_time(motion.profile.end_time) + 1e-4, settle)


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
