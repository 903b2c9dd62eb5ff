"""Fault injection into the emulated Zaber chain: spoiled replies, dead or unpowered devices,
spoiled moves and raised warning flags.

:class:`ZaberFaultInjection` is the public fault API of
:class:`~drivers.sim.zaber_emulator.ZaberEmulator` (which inherits it).  A reply fault waits
in :class:`ReplyFaults` until a reply it matches is sent; a move fault waits on its axis
(:attr:`~drivers.sim.zaber_axes.EmulatedAxis.pending_fault`) until the axis's next move,
which :class:`~drivers.sim.zaber_commands.ZaberCommandInterpreter` spoils accordingly.
Fractions are of the move's distance (stall, limit, stuck) or of its duration (disconnect,
power); delays and off times are real seconds.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Literal

from drivers.sim.zaber_axes import EmulatedChain, MoveFault
from drivers.sim.zaber_commands import ZaberCommandInterpreter
from drivers.zaber import protocol


@dataclass
class ReplyFault:
    kind: Literal["drop", "garble", "delay"]
    remaining: int | None  # None = forever
    device: int | None
    delay_s: float = 0.0
    command: str | None = None  # only replies to commands starting with this


class ReplyFaults:
    """The pending reply faults; the first armed that matches a reply applies to it."""

    def __init__(self) -> None:
        self._pending: list[ReplyFault] = []

    def add(self, fault: ReplyFault) -> None:
        """Arm ``fault`` (after those already pending)."""
        self._pending.append(fault)

    def clear(self) -> None:
        """Disarm every pending reply fault."""
        self._pending.clear()

    def take(self, device: int, command: str) -> ReplyFault | None:
        """The fault for a reply of ``device`` to ``command`` (its text), one use of it
        spent (a used-up fault is disarmed); None if the reply goes out unharmed."""
        fault = next(
            (
                f
                for f in self._pending
                if f.device in (None, device)
                and (f.command is None or command.startswith(f.command))
            ),
            None,
        )
        if fault is not None and fault.remaining is not None:
            fault.remaining -= 1
            if fault.remaining <= 0:
                self._pending.remove(fault)
        return fault


def garble(line: bytes, salt: int) -> bytes:
    """``line`` with one byte of the body changed (not the start char nor the terminator),
    at a place that varies with ``salt``, so that its checksum fails."""
    body_end = len(line.rstrip(b"\r\n"))
    index = 1 + (salt * 7) % max(1, body_end - 1)
    value = line[index]
    replacement = value + 1 if value < 126 else value - 1
    if replacement in (ord("\r"), ord("\n")):
        replacement = ord("#")
    return line[:index] + bytes([replacement]) + line[index + 1 :]


class ZaberFaultInjection:
    """The fault-injection methods of :class:`~drivers.sim.zaber_emulator.ZaberEmulator`
    (a mixin: it works on the emulator's lock, chain, command interpreter and reply faults).

    Thread-safe: each method takes the emulator's lock.  ``device`` is a device address,
    ``axis`` an axis number (from 1); an unknown one raises ``KeyError``.
    """

    _lock: threading.RLock
    _chain: EmulatedChain
    _commands: ZaberCommandInterpreter
    _reply_faults: ReplyFaults

    # ------------------------------------------------------------------ replies

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
            for dev in self._chain.devices:
                dev.dead = False
                for ax in dev.axes:
                    ax.pending_fault = None

    # ------------------------------------------------------------------ devices

    def set_dead(self, device: int, dead: bool = True) -> None:
        """A dead device neither executes nor answers anything."""
        with self._lock:
            self._chain.device(device).dead = dead

    def power_cycle(self, device: int, *, off_s: float = 0.1) -> None:
        """Power-cycle ``device`` now: motion stops, positions lost (WR), silent ``off_s`` s."""
        with self._lock:
            self._commands.power_cycle(self._chain.device(device), off_s)

    def set_flags(self, device: int, axis: int, *flags: str) -> None:
        """Raise warning flags on an axis directly (e.g. ``"WT"`` temperature, ``"WV"`` voltage)."""
        unknown = set(flags) - set(protocol.WARNING_FLAGS)
        if unknown:
            raise ValueError(f"unknown warning flags {sorted(unknown)}")
        with self._lock:
            self._chain.axis(device, axis).flags.update(flags)

    # ------------------------------------------------------------------ the next move

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

    # ------------------------------------------------------------------ internals

    def _add_reply_fault(self, fault: ReplyFault) -> None:
        with self._lock:
            self._reply_faults.add(fault)

    def _set_move_fault(self, device: int, axis: int, fault: MoveFault) -> None:
        if not 0.0 <= fault.fraction <= 1.0:
            raise ValueError("at_fraction must be within 0..1")
        with self._lock:
            self._chain.axis(device, axis).pending_fault = fault
