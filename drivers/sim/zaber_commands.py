"""The command interpreter of the emulated Zaber chain: runs ASCII-protocol commands on the
emulated devices and words their replies and alerts.

Motion has kinematics: ``home`` and ``move abs|rel|min|max`` start trapezoidal profiles
from the axis's ``maxspeed`` and ``accel`` (Zaber data units; ``move abs|rel`` may
override both from firmware 7.25 on), ``stop`` decelerates at ``accel``, ``estop`` halts
at once, and ``system reset`` power-cycles the device.  A motion settles (reaching its
end position, raising its end flags and, with ``comm.alert`` on, sending an alert) when
its time is over: at the latest by an event on the :class:`~drivers.sim.zaber_clock.EmulatorClock`,
earlier if a command or an inspection looks at the axis first.  A pending
:class:`~drivers.sim.zaber_axes.MoveFault` of an axis spoils the next move it makes.

Positions are in microsteps, times in scaled seconds unless named real.  The settings
commands (``get``, ``set``, ``warnings``) are :mod:`drivers.sim.zaber_settings`'.  Not
thread-safe: the emulator calls it with its lock held.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Literal

from drivers.sim.zaber_axes import (
    DecelerationProfile,
    EmulatedAxis,
    EmulatedDevice,
    Motion,
    TrapezoidProfile,
)
from drivers.sim.zaber_clock import EmulatorClock
from drivers.sim.zaber_settings import (
    MOVE_SPEED_ARGS_SINCE,
    get_setting,
    is_int,
    set_setting,
    warning_flags,
)
from drivers.zaber import protocol

#: A command's outcome: the reply's data (``"RJ REASON"`` for a rejection), optionally with
#: an action to run once the reply is out.
Outcome = str | tuple[str, Callable[[], None]]


class ZaberCommandInterpreter:
    """Executes commands on the emulated devices and hands out their replies and alerts.

    Args:
        clock: the emulator's time base and event queue.
        deliver: sends ``(device, reply line, text of the command answered)``; the
            emulator applies its reply faults there.
        send_alert: sends an alert line.
        disconnect: drops the line (for a ``disconnect`` move fault).
    """

    def __init__(
        self,
        clock: EmulatorClock,
        *,
        deliver: Callable[[EmulatedDevice, bytes, str], None],
        send_alert: Callable[[bytes], None],
        disconnect: Callable[[], None],
    ) -> None:
        self._clock = clock
        self._deliver = deliver
        self._send_alert = send_alert
        self._disconnect = disconnect

    # ------------------------------------------------------------------ commands

    def execute(self, dev: EmulatedDevice, cmd: protocol.Command) -> None:
        """Run ``cmd`` on ``dev`` (the caller checked it is addressed) and reply."""
        mid = cmd.message_id
        if cmd.axis > len(dev.axes):
            self.reply(dev, cmd.axis, mid, rejected=True, data="BADAXIS", command=cmd.text)
            return
        words = cmd.text.split()
        verb = words[0] if words else ""
        args = words[1:]
        axes = dev.axes if cmd.axis == 0 else [dev.axes[cmd.axis - 1]]
        now = self._clock.now()
        for ax in dev.axes:
            self.settle(dev, ax, now)
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
            self.reply(dev, cmd.axis, mid, rejected=True, data="BADCOMMAND", command=cmd.text)
            return
        outcome = handler(dev, cmd.axis, axes, args, now)
        post: Callable[[], None] | None = None
        if isinstance(outcome, tuple):
            outcome, post = outcome
        rejected = outcome.startswith("RJ ")
        data = outcome[3:] if rejected else outcome
        self.reply(dev, cmd.axis, mid, rejected=rejected, data=data, now=now, command=cmd.text)
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
        self.stop(dev, axes, now)
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
    ) -> Outcome:
        if args != ["reset"]:
            return "RJ BADCOMMAND"
        if axis != 0:
            return "RJ DEVICEONLY"
        return "0", lambda: self.power_cycle(dev, 0.05)

    # ------------------------------------------------------------------ replies and alerts

    def reply(
        self,
        dev: EmulatedDevice,
        axis: int,
        message_id: int | None,
        *,
        rejected: bool = False,
        data: str = "0",
        now: float | None = None,
        command: str = "",
    ) -> None:
        """Reply from ``dev`` about ``axis`` (0: the device) to ``command`` (its text; ``""``
        for one that did not parse), with the status and flags at scaled time ``now``
        (default: the current time)."""
        # one timestamp per command: status, flags and data must describe the same instant
        now = self._clock.now() if now is None else now
        axes = dev.axes if axis == 0 else [dev.axes[axis - 1]] if axis <= len(dev.axes) else []
        for ax in axes:
            self.settle(dev, ax, now)
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
        self._deliver(dev, line, command)

    def settle(self, dev: EmulatedDevice, ax: EmulatedAxis, now: float) -> None:
        """Finish ``ax``'s motion if its time is over, with the alert it triggers."""
        if ax.settle(now):
            self._alert(dev, ax)

    def _alert(self, dev: EmulatedDevice, ax: EmulatedAxis) -> None:
        if dev.alert and dev.responsive(time.monotonic()):
            now = self._clock.now()
            self._send_alert(
                protocol.format_alert(
                    dev.address,
                    ax.number,
                    busy=ax.busy(now),
                    warning=protocol.highest_warning(ax.flags),
                    checksum=dev.checksum,
                )
            )

    # ------------------------------------------------------------------ motion and power

    def stop(self, dev: EmulatedDevice, axes: list[EmulatedAxis], now: float) -> None:
        """Stop the moving ones of ``axes`` as ``stop`` does: they decelerate at ``accel``
        (a stuck axis halts at once) and raise NI."""
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

    def power_cycle(self, dev: EmulatedDevice, off_s: float) -> None:
        """Cut ``dev``'s power for ``off_s`` real seconds: motion stops, positions are lost
        (WR), and it neither executes nor answers anything meanwhile."""
        now = self._clock.now()
        for ax in dev.axes:
            ax.power_loss(now)
        dev.off_until = time.monotonic() + off_s

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
            at = self._clock.real_time(now + fault.fraction * (full.end_time - now))
            if fault.kind == "disconnect":
                self._clock.schedule(at, self._disconnect)
            else:
                off_s = fault.off_s
                self._clock.schedule(at, lambda: self.power_cycle(dev, off_s))

    def _schedule_settle(self, dev: EmulatedDevice, ax: EmulatedAxis, motion: Motion) -> None:
        def settle() -> None:
            if ax.motion is motion:
                self.settle(dev, ax, self._clock.now())

        self._clock.schedule(self._clock.real_time(motion.profile.end_time) + 1e-4, settle)
