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

This module holds the transport: the serving thread, line framing, and the replies'
way out through the reply faults.  The pieces it composes: the devices' state and
kinematics (:mod:`drivers.sim.zaber_axes`), their time and timed events
(:mod:`drivers.sim.zaber_clock`), the commands (:mod:`drivers.sim.zaber_commands`,
settings in :mod:`drivers.sim.zaber_settings`) and the fault API
(:mod:`drivers.sim.zaber_faults`).
"""

from __future__ import annotations

import dataclasses
import os
import select
import threading
import time
from collections import deque
from dataclasses import dataclass
from types import TracebackType

from drivers.errors import ChecksumError
from drivers.sim.emulator_links import PtyLink, TcpLink, Transport
from drivers.sim.zaber_axes import AxisSpec, DeviceSpec, EmulatedChain, EmulatedDevice
from drivers.sim.zaber_clock import EmulatorClock
from drivers.sim.zaber_commands import ZaberCommandInterpreter
from drivers.sim.zaber_faults import ReplyFaults, ZaberFaultInjection, garble
from drivers.sim.zaber_settings import axis_setting
from drivers.zaber import protocol


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


class ZaberEmulator(ZaberFaultInjection):
    """A chain of emulated Zaber devices behind one pty or 127.0.0.1 TCP port.

    The fault-injection methods (``drop_replies``, ``stall_next_move``, ``power_cycle``...)
    are :class:`~drivers.sim.zaber_faults.ZaberFaultInjection`'s.

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
        self._chain = EmulatedChain(specs, checksum=checksum, alert=alert)
        self._wake_r, self._wake_w = -1, -1  # the pipe that wakes the serving thread
        self._clock = EmulatorClock(speedup, wake=self._wake)
        if transport not in ("pty", "tcp"):
            raise ValueError(f"unknown transport {transport!r}")
        self._transport: Transport = transport
        self._tcp_port = tcp_port
        self._lock = threading.RLock()
        self._commands = ZaberCommandInterpreter(
            self._clock,
            deliver=self._deliver,
            send_alert=self._send_alert,
            disconnect=self.disconnect,
        )
        self._reply_faults = ReplyFaults()
        self._inbuf = bytearray()
        self._link: PtyLink | TcpLink | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self.stats = EmulatorStats()
        #: Command lines received (decoded, newest last) for protocol assertions.
        self.received: deque[str] = deque(maxlen=2000)

    @property
    def speedup(self) -> float:
        """Motion runs this many times faster than real time."""
        return self._clock.speedup

    @speedup.setter
    def speedup(self, value: float) -> None:
        self._clock.speedup = float(value)

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
            now = self._clock.now()
            ax = self._chain.axis(device, axis)
            self._commands.settle(self._chain.device(device), ax, now)
            return AxisSnapshot(
                ax.reported(now), ax.phys_at(now), ax.busy(now), frozenset(ax.flags)
            )

    def firmware(self, device: int) -> int:
        """Firmware series (6 or 7) of ``device``."""
        with self._lock:
            return self._chain.device(device).spec.firmware

    def device_checksum(self, device: int) -> bool:
        """Current ``comm.checksum`` of ``device``."""
        with self._lock:
            return self._chain.device(device).checksum

    def stop_axis(self, device: int, axis: int) -> None:
        """Stop a moving axis as a ``stop`` from elsewhere would (no reply is sent): it
        decelerates and raises NI."""
        with self._lock:
            dev, ax = self._chain.device(device), self._chain.axis(device, axis)
            self._commands.stop(dev, [ax], self._clock.now())

    def is_powered(self, device: int) -> bool:
        """False while ``device`` is off after a power cycle (it answers nothing then)."""
        with self._lock:
            return self._chain.device(device).off_until <= time.monotonic()

    def setting(self, device: int, axis: int, name: str) -> int:
        """Current value of an axis setting (pos, maxspeed, accel, limit.min, limit.max)."""
        with self._lock:
            ax = self._chain.axis(device, axis)
            value = axis_setting(ax, name, self._clock.now())
            assert value is not None
            return value

    def disconnect(self) -> None:
        """Drop the line now (pty: closed for good; TCP: current client closed)."""
        with self._lock:
            if self._link is not None:
                self._link.disconnect()

    # ------------------------------------------------------------------ internals: serving

    def _wake(self) -> None:
        if self._wake_w >= 0:
            try:
                os.write(self._wake_w, b"x")
            except OSError:
                pass

    def _serve(self) -> None:
        while not self._stopping.is_set():
            with self._lock:
                link = self._link
                timeout = self._clock.seconds_to_next(0.2)
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
                self._clock.run_due()

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
        self._clock.run_due()
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            return
        if any(not 32 <= ord(c) <= 126 for c in text) or "/" not in text:
            return  # unsupported characters: a device discards the incomplete command
        self.received.append(text[text.find("/") :])
        self.stats.commands += 1
        try:
            command, _ = protocol.parse_command(text)
        except ChecksumError:
            self.stats.bad_checksum += 1
            return  # modelling choice: a command with a wrong checksum is dropped silently
        except protocol.CommandSyntaxError as exc:
            for dev in self._chain.addressed(exc.device, time.monotonic()):
                self._commands.reply(dev, 0, None, rejected=True, data=exc.reason)
            return
        if command.device > protocol.MAX_DEVICE:
            return
        for dev in self._chain.addressed(command.device, time.monotonic()):
            self._commands.execute(dev, command)

    # ------------------------------------------------------------------ internals: sending

    def _send(self, data: bytes) -> None:
        if self._link is not None:
            self._link.write(data)

    def _send_alert(self, line: bytes) -> None:
        self.stats.alerts += 1
        self._send(line)

    def _deliver(self, dev: EmulatedDevice, line: bytes, command: str) -> None:
        """Send ``dev``'s reply to ``command`` (its text), as the reply faults say."""
        self.stats.replies += 1
        fault = self._reply_faults.take(dev.address, command)
        if fault is not None:
            if fault.kind == "drop":
                self.stats.dropped += 1
                return
            if fault.kind == "garble":
                self.stats.garbled += 1
                line = garble(line, self.stats.garbled)
            else:
                self.stats.delayed += 1

                def send_late(late: bytes = line) -> None:
                    self.stats.delayed_sent += 1
                    self._send(late)

                self._clock.schedule(time.monotonic() + fault.delay_s, send_late)
                return
        self._send(line)


__all__ = ["AxisSnapshot", "AxisSpec", "DeviceSpec", "EmulatorStats", "ZaberEmulator"]
