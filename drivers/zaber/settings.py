"""The device settings a Zaber axis driver depends on, and the motion timeouts they imply.

:class:`AxisSettings` reads the travel limits (``limit.min``/``limit.max``) and the
stored ``maxspeed``/``accel`` at connect, decides how configured speeds reach the
device, reads the settings back for bring-up checks and restores what it wrote at
close.  Units: positions and travel in microsteps, speeds in microsteps/s,
accelerations in microsteps/s^2, times in s.

With configured speeds, firmware 7.25 and later gets them as ``move abs`` arguments
(the stored settings stay as they are); older firmware has ``maxspeed``/``accel``
written at connect and set back by :meth:`AxisSettings.restore` (see
:mod:`drivers.zaber.axis`).  Homing always runs at the device's stored speeds.
"""

from __future__ import annotations

from drivers.errors import DeviceError
from drivers.zaber import protocol
from drivers.zaber.config import ZaberAxisConfig
from drivers.zaber.link import AxisLink

#: ``move abs <pos> <speed> <accel>`` exists from this firmware version on.
MOVE_SPEED_ARGS_SINCE = (7, 25)


class AxisSettings:
    """Travel limits and speeds of one axis, as read and set up at connect.

    Args:
        link: requests to the axis.
        config: configured speeds (mm/s, mm/s^2), microstep size and timeout terms.

    Attributes:
        limits_usteps: the device's (limit.min, limit.max) (microsteps).
        speed, accel: of moves (microsteps/s, microsteps/s^2).
        home_speed, home_accel: of homing: the device's stored ``maxspeed``/``accel``.
        move_args: ``" <speed> <accel>"`` appended to ``move abs`` (firmware >= 7.25),
            else ``""``.
        changed: settings written at connect with the value found before
            (restored by :meth:`restore`).
    """

    def __init__(self, link: AxisLink, config: ZaberAxisConfig) -> None:
        self._link = link
        self._cfg = config
        self.limits_usteps = (0, 0)
        self.speed = 1.0
        self.accel = 1.0
        self.home_speed = 1.0
        self.home_accel = 1.0
        self.move_args = ""
        self.changed: dict[str, int] = {}

    def load(self, firmware: tuple[int, int]) -> None:
        """Read the travel limits, then set up the speeds for ``firmware`` (major, minor).

        Raises DeviceError when the device reports an empty travel.
        """
        low = self._link.get_int("limit.min")
        high = self._link.get_int("limit.max")
        if not low < high:
            raise DeviceError(
                f"device reports an empty travel: limit.min {low} >= limit.max {high}",
                device=self._link.label,
                hint="the device's limit settings (Zaber Launcher)",
            )
        self.limits_usteps = (low, high)
        self._setup_speeds(firmware)

    def _setup_speeds(self, firmware: tuple[int, int]) -> None:
        """Per-move speed arguments (firmware >= 7.25) or settings written and restored."""
        cfg = self._cfg
        stored_speed = self._link.get_int("maxspeed")
        stored_accel = self._link.get_int("accel")
        self.home_speed = protocol.data_to_speed(stored_speed)
        self.home_accel = protocol.data_to_accel(stored_accel)
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
        self.move_args = ""
        if speed_data is None and accel_data is None:
            pass
        elif firmware >= MOVE_SPEED_ARGS_SINCE:
            # both arguments go together; the one not configured is the stored setting
            self.move_args = f" {speed_data or stored_speed} {accel_data or stored_accel}"
        else:
            for name, data, stored in (
                ("maxspeed", speed_data, stored_speed),
                ("accel", accel_data, stored_accel),
            ):
                if data is not None and data != stored:
                    self.changed.setdefault(name, stored)
                    self._link.request(f"set {name} {data}")
        self.speed = protocol.data_to_speed(speed_data or stored_speed)
        self.accel = protocol.data_to_accel(accel_data or stored_accel)

    @property
    def speed_mode(self) -> str:
        """How configured speeds reach the device: ``"per-move"`` (``move abs`` arguments,
        firmware >= 7.25), ``"written"`` (set at connect, restored at close) or
        ``"stored"`` (none configured: the device's own settings)."""
        if self.move_args:
            return "per-move"
        return "written" if self.changed else "stored"

    def read_back(self) -> dict[str, str]:
        """The settings the station relies on, read from the device now (raw values):
        ``version``, ``limit.min``, ``limit.max``, ``maxspeed``, ``accel``,
        ``comm.checksum``, ``pos`` and the active ``warnings``."""
        link = self._link
        out = {"version": link.request("get version", axis=0).data}
        for name in ("limit.min", "limit.max", "maxspeed", "accel"):
            out[name] = link.request(f"get {name}").data
        out["comm.checksum"] = link.get_optional("comm.checksum", axis=0) or "unknown"
        out["pos"] = link.status().data
        out["warnings"] = " ".join(sorted(link.warnings())) or "none"
        return out

    def restore(self) -> None:
        """Write back the settings changed at connect (best effort: a failure is ignored;
        nothing is sent when the port is closed)."""
        changed, self.changed = self.changed, {}
        if not self._link.port.is_open:
            return
        for name, value in changed.items():
            try:
                self._link.request(f"set {name} {value}")
            except DeviceError:
                pass

    # ------------------------------------------------------------------ derived timeouts

    def _timeout_s(self, kinematic_s: float) -> float:
        """A motion timeout (s): the kinematic estimate x1.5 x ``timeout_scale`` plus
        ``timeout_margin_s``."""
        cfg = self._cfg
        return kinematic_s * cfg.timeout_scale * 1.5 + cfg.timeout_margin_s

    def move_timeout_s(self, distance_usteps: float) -> float:
        """Timeout (s) of a move over ``distance_usteps`` at the move speeds."""
        return self._timeout_s(protocol.move_duration_s(distance_usteps, self.speed, self.accel))

    def home_timeout_s(self) -> float:
        """Timeout (s) of homing: twice the whole travel at the homing speeds."""
        low, high = self.limits_usteps
        return self._timeout_s(
            2.0 * protocol.move_duration_s(high - low, self.home_speed, self.home_accel)
        )

    def stop_timeout_s(self) -> float:
        """Time (s) a stop may take: twice the deceleration time from the move speed,
        x ``timeout_scale``, plus ``timeout_margin_s``."""
        cfg = self._cfg
        return (self.speed / self.accel) * cfg.timeout_scale * 2.0 + cfg.timeout_margin_s


__all__ = ["MOVE_SPEED_ARGS_SINCE", "AxisSettings"]
