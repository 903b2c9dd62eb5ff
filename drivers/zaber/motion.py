"""Motion supervision of one Zaber axis: start, wait for IDLE, check flags and position.

:class:`MotionSupervisor` sends ``home`` and ``move abs`` without waiting
(returning a :class:`PendingMotion`), waits for a started motion to end
(:meth:`MotionSupervisor.finish`), stops the axis, and keeps whether the driver
still trusts the axis's position.  Targets are in microsteps (already checked
against the limits by the caller), positions returned in mm, times in s.

It carries out the safety rules listed in :mod:`drivers.zaber.axis`: no move without
a trusted reference, a deadline on every motion (``stop`` and :class:`MotionTimeout`
past it), warning flags mapped to typed errors once idle (fault flags then cleared),
the idle position compared to the target (:class:`PositionMismatch`), and NI
(command interrupted) cleared by :meth:`MotionSupervisor.stop` and before each
motion, so an NI seen after a motion belongs to that motion.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

from drivers.errors import (
    DeviceBusy,
    DeviceError,
    MotionTimeout,
    MoveInterrupted,
    NotReferenced,
    PositionMismatch,
)
from drivers.zaber import protocol
from drivers.zaber.config import ZaberAxisConfig
from drivers.zaber.link import AxisLink
from drivers.zaber.protocol import Reply
from drivers.zaber.settings import AxisSettings


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


class MotionSupervisor:
    """Starts, waits for, checks and stops the motions of one axis.

    Args:
        link: requests to the axis.
        config: tolerance (um), poll interval (s) and microstep size.
        settings: move arguments and the derived motion timeouts.

    Attributes:
        needs_home: the driver no longer trusts the position (a fault, or WR seen);
            moves are refused until a homing succeeded.
        stops: :meth:`stop` calls so far (see :attr:`PendingMotion.stops`).
    """

    def __init__(self, link: AxisLink, config: ZaberAxisConfig, settings: AxisSettings) -> None:
        self._link = link
        self._cfg = config
        self._settings = settings
        self.needs_home = False
        self.stops = 0

    # ------------------------------------------------------------------ reference

    def is_homed(self) -> bool:
        """True if the device has a reference (no WR) and the driver still trusts it."""
        return self._link.has_reference(self._link.status()) and not self.needs_home

    def position_mm(self) -> float:
        """Current position (mm). Raises NotReferenced when the axis is not homed."""
        status = self._link.status()
        if self.needs_home or not self._link.has_reference(status):
            raise NotReferenced("position unknown: axis not homed", device=self._link.label)
        return self._cfg.usteps_to_mm(status.data_int())

    # ------------------------------------------------------------------ start

    def start_home(self, timeout_s: float | None = None) -> PendingMotion:
        """Send ``home`` and return without waiting (``timeout_s`` s; None = derived).

        Stale fault flags are cleared first, so the flags seen after homing are
        homing's own.  Raises DeviceBusy if moving.
        """
        link = self._link
        status = link.status()
        if status.busy:
            raise DeviceBusy("cannot home: axis already moving", device=link.label)
        # the shown flag may hide others (WR outranks NI): read the full list
        if status.warning != protocol.NO_WARNING and link.warnings() & protocol.CLEARABLE_FLAGS:
            link.clear_warnings()
        reply = link.request("home")
        if timeout_s is None:
            timeout_s = self._settings.home_timeout_s()
        return PendingMotion(
            "home", None, time.monotonic() + timeout_s, reply.attempts > 1, self.stops
        )

    def start_move(
        self, target: int, target_mm: float, timeout_s: float | None = None
    ) -> PendingMotion:
        """Send ``move abs`` to ``target`` (microsteps, within the limits; ``target_mm``
        is the requested target, for messages) and return without waiting.

        Raises NotReferenced, DeviceBusy, CommandRejected, or the error for a fault
        flag still set on the device.
        """
        link = self._link
        status = link.status()
        if status.warning == "WR" or self.needs_home:
            self.needs_home = self.needs_home or status.warning == "WR"
            raise NotReferenced(
                f"refusing to move to {target_mm} mm: axis not homed", device=link.label
            )
        if status.busy:
            raise DeviceBusy(
                f"cannot move to {target_mm} mm: axis already moving", device=link.label
            )
        if status.warning != "--":
            flags = link.warnings()
            self._raise_for_flags(flags, f"before moving to {target_mm} mm", ignore={"NI"})
            if "NI" in flags:  # a stale interruption (an earlier stop): not this move's
                link.clear_warnings()
        start = status.data_int()
        reply = link.request(f"move abs {target}{self._settings.move_args}")
        if reply.warning == "WR":  # power lost between the check and the move
            link.quiet_stop()
            self.needs_home = True
            raise NotReferenced("device lost its reference (power cycle?)", device=link.label)
        if timeout_s is None:
            timeout_s = self._settings.move_timeout_s(target - start)
        return PendingMotion(
            "move", target, time.monotonic() + timeout_s, reply.attempts > 1, self.stops
        )

    # ------------------------------------------------------------------ finish

    def finish(self, pending: PendingMotion) -> float:
        """Wait for a started motion, check flags and position; return position (mm)."""
        ignore = {"NI"} if pending.resent else set()
        if pending.kind == "home":
            self.wait(pending.deadline, context="homing", ignore=ignore)
            self._check_not_stopped(pending, "homing")
            self.needs_home = False
            return self.position_mm()
        assert pending.target_usteps is not None
        target_mm = self._cfg.usteps_to_mm(pending.target_usteps)
        context = f"moving to {target_mm:.4f} mm"
        self.wait(pending.deadline, context=context, ignore=ignore)
        self._check_not_stopped(pending, context)
        # read back with a fresh query once idle (not the data of the poll that saw IDLE)
        final = self._link.status()
        if final.busy:
            raise DeviceBusy(
                "axis moving again right after the move ended", device=self._link.label
            )
        actual = final.data_int()
        actual_mm = self._cfg.usteps_to_mm(actual)
        tolerance_mm = self._cfg.tolerance_um / 1000.0
        if abs(actual_mm - target_mm) > tolerance_mm + 1e-12:
            raise PositionMismatch(
                f"idle at {actual_mm:.4f} mm, commanded {target_mm:.4f} mm "
                f"(off by {(actual_mm - target_mm) * 1000:.2f} um, tolerance {self._cfg.tolerance_um} um)",
                target_mm=target_mm,
                actual_mm=actual_mm,
                tolerance_mm=tolerance_mm,
                device=self._link.label,
            )
        return actual_mm

    def _check_not_stopped(self, pending: PendingMotion, context: str) -> None:
        """MoveInterrupted if ``stop()`` ran during the motion (it cleared the NI flag)."""
        if self.stops != pending.stops:
            raise MoveInterrupted(
                f"{context}: stopped by a stop command", device=self._link.label, flags={"NI"}
            )

    def wait(self, deadline: float, *, context: str, ignore: set[str] | None = None) -> Reply:
        """Poll until idle (``deadline``: ``time.monotonic()``); then map the flags to
        errors, except those in ``ignore``.  Returns the final status reply.

        Past the deadline the axis is sent ``stop`` and MotionTimeout is raised.
        """
        ignore = ignore or set()
        while True:
            status = self._link.status()
            if not status.busy:
                if status.warning != "--":
                    self._raise_for_flags(self._link.warnings(), context, ignore=ignore)
                return status
            if time.monotonic() >= deadline:
                self._link.quiet_stop()
                raise MotionTimeout(
                    f"still BUSY at the deadline while {context} "
                    f"(position {self._cfg.usteps_to_mm(status.data_int()):.4f} mm); stop sent",
                    device=self._link.label,
                )
            time.sleep(self._cfg.poll_interval_s)

    def _raise_for_flags(self, flags: frozenset[str], context: str, *, ignore: set[str]) -> None:
        """Raise the typed error for ``flags`` (after clearing them on the device)."""
        error = protocol.error_for_flags(
            flags, device=self._link.label, context=context, ignore=ignore
        )
        if error is None:
            return
        if flags & protocol.POSITION_LOST_FLAGS:
            self.needs_home = True
        if flags & protocol.CLEARABLE_FLAGS - ignore:
            try:
                self._link.clear_warnings()
            except DeviceError:
                pass
        raise error

    # ------------------------------------------------------------------ stop

    def stop(self) -> None:
        """Decelerate to a stop and wait until idle (estop if it does not stop in time).

        The NI flag the stop leaves is then cleared (a motion being waited for in
        another thread still ends with MoveInterrupted).
        """
        self.stops += 1
        self._link.request("stop")
        timeout = self._settings.stop_timeout_s()
        deadline = time.monotonic() + timeout
        while (status := self._link.status()).busy:
            if time.monotonic() >= deadline:
                self._link.request("estop")
                raise MotionTimeout(
                    f"still moving {timeout:.2f} s after stop; estop sent",
                    device=self._link.label,
                )
            time.sleep(self._cfg.poll_interval_s)
        self._clear_interrupted(status)

    def _clear_interrupted(self, status: Reply) -> None:
        """Clear the NI a stop leaves behind, unless a fault flag is also set (that one
        is left for the next motion's check to report)."""
        if status.warning == protocol.NO_WARNING:
            return
        flags = self._link.warnings()
        if "NI" in flags and not flags & (protocol.FAULT_FLAGS | protocol.POSITION_LOST_FLAGS):
            self._link.clear_warnings()


__all__ = ["MotionSupervisor", "PendingMotion"]
