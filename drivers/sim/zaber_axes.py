"""The devices and axes of the emulated Zaber chain: their specifications, motion profiles and state.

Units are the devices' own: positions in microsteps, the ``maxspeed`` and ``accel``
settings in Zaber's data units (:func:`drivers.zaber.protocol.data_to_speed` and
:func:`~drivers.zaber.protocol.data_to_accel` convert them to microsteps/s and
microsteps/s²), times in the emulator's scaled seconds (real seconds × ``speedup``, see
:class:`~drivers.sim.zaber_clock.EmulatorClock`). :class:`~drivers.sim.zaber_emulator.ZaberEmulator`
owns the state; :class:`~drivers.sim.zaber_commands.ZaberCommandInterpreter` runs the protocol on it.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from drivers.zaber import protocol

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
            (see :data:`drivers.sim.zaber_settings.FIRMWARE_SETTING_NAMES`).
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


class MotionProfile(ABC):
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


class TrapezoidProfile(MotionProfile):
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


class DecelerationProfile(MotionProfile):
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
class MoveFault:
    kind: Literal["stall", "limit", "stuck", "drift", "disconnect", "power"]
    fraction: float = 0.5
    flag: str = ""
    drift: int = 0
    off_s: float = 0.0


@dataclass
class Motion:
    profile: MotionProfile
    kind: Literal["move", "home", "stop"]
    end_flags: tuple[str, ...] = ()
    stuck_after: bool = False


class EmulatedAxis:
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
        self.motion: Motion | None = None
        self.stuck = False
        self.pending_fault: MoveFault | None = None

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
class EmulatedDevice:
    spec: DeviceSpec
    axes: list[EmulatedAxis]
    checksum: bool
    alert: bool
    dead: bool = False
    off_until: float = 0.0  # real time until which the device is powered off

    @property
    def address(self) -> int:
        return self.spec.address

    def responsive(self, real_now: float) -> bool:
        """Alive and powered at monotonic time ``real_now``: it executes and answers commands."""
        return not self.dead and self.off_until <= real_now


class EmulatedChain:
    """The devices of one chain, in address order, looked up by address.

    Raises:
        ValueError: device addresses that repeat or lie outside 1-99.
    """

    def __init__(self, specs: Sequence[DeviceSpec], *, checksum: bool, alert: bool) -> None:
        addresses = [spec.address for spec in specs]
        if len(set(addresses)) != len(addresses) or not all(1 <= a <= 99 for a in addresses):
            raise ValueError(f"device addresses must be unique and 1-99, got {addresses}")
        self.devices = [
            EmulatedDevice(
                spec, [EmulatedAxis(i + 1, a) for i, a in enumerate(spec.axes)], checksum, alert
            )
            for spec in sorted(specs, key=lambda s: s.address)
        ]

    def device(self, address: int) -> EmulatedDevice:
        """The device at ``address`` (KeyError if there is none)."""
        for dev in self.devices:
            if dev.address == address:
                return dev
        raise KeyError(f"no emulated device {address}")

    def axis(self, device: int, axis: int) -> EmulatedAxis:
        """Axis ``axis`` (1-based) of the device at ``device`` (KeyError if there is none)."""
        dev = self.device(device)
        if not 1 <= axis <= len(dev.axes):
            raise KeyError(f"device {device} has no axis {axis}")
        return dev.axes[axis - 1]

    def addressed(self, address: int, real_now: float) -> list[EmulatedDevice]:
        """The devices that execute a command sent to ``address`` (0: every device) at
        monotonic time ``real_now``: those at that address that are alive and powered."""
        return [
            dev for dev in self.devices if address in (0, dev.address) and dev.responsive(real_now)
        ]
