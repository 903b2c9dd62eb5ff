"""The settings and the stateless commands of the emulated Zaber devices (``get``, ``set``,
``warnings``), per firmware series.

Each command takes the device, the addressed axis number (0: the device), the addressed
axes, the command's arguments and the emulator's scaled time, and returns the reply's
data (``"RJ REASON"`` for a rejection). Positions and limits are in microsteps,
``maxspeed`` and ``accel`` in Zaber's data units. Commands that start motion or
schedule events are :class:`~drivers.sim.zaber_commands.ZaberCommandInterpreter`'s.
"""

from __future__ import annotations

from drivers.sim.zaber_axes import EmulatedAxis, EmulatedDevice
from drivers.zaber import protocol

#: Settings whose name differs between the firmware series: (firmware 6, firmware 7).
#: Firmware 7 renamed the identity settings (Zaber's FW7 protocol manual); a device of
#: either series rejects the other series' name with ``RJ BADCOMMAND``.
FIRMWARE_SETTING_NAMES: dict[str, tuple[str, str]] = {
    "device_id": ("deviceid", "device.id"),
    "peripheral_id": ("peripheralid", "peripheral.id"),
}
#: ``move abs``/``move rel`` take optional speed and acceleration arguments from 7.25 on.
MOVE_SPEED_ARGS_SINCE = (7, 25)

DEVICE_SETTINGS = (
    "device_id",
    "system.serial",
    "version",
    "comm.checksum",
    "comm.alert",
    "system.axiscount",
)
AXIS_SETTINGS = ("pos", "maxspeed", "accel", "limit.min", "limit.max", "peripheral_id")
READ_ONLY = frozenset(
    {"device_id", "system.serial", "version", "system.axiscount", "peripheral_id"}
)


def canonical_setting(name: str, firmware: int) -> str | None:
    """The internal key of a setting name as a device of ``firmware`` knows it (None:
    unknown to that firmware, e.g. ``device.id`` on firmware 6)."""
    for key, names in FIRMWARE_SETTING_NAMES.items():
        if name in names:
            return key if names[0 if firmware == 6 else 1] == name else None
        if name == key:
            return None
    return name


def is_int(text: str) -> bool:
    """A decimal integer as the protocol writes one (optional sign, under 20 digits)."""
    return text.lstrip("+-").isdigit() and len(text) < 20


def axis_setting(
    ax: EmulatedAxis, name: str, now: float, dev: EmulatedDevice | None = None
) -> int | None:
    """An axis setting's value at scaled time ``now`` (None for an unknown name)."""
    return {
        "pos": ax.reported(now),
        "maxspeed": ax.maxspeed,
        "accel": ax.accel,
        "limit.min": ax.limit_min,
        "limit.max": ax.limit_max,
        "peripheral_id": dev.spec.peripheral_id if dev is not None else 0,
    }.get(name)


def get_setting(
    dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
) -> str:
    """``get NAME``: a device setting (axis 0 only) or each addressed axis's, in axis order."""
    if len(args) != 1:
        return "RJ BADCOMMAND" if not args else "RJ BADDATA"
    name = canonical_setting(args[0], dev.spec.firmware)
    if name in DEVICE_SETTINGS:
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
    if name in AXIS_SETTINGS:
        # axis 0: one value per axis, in axis order (the manual's "get" of a device)
        values = [axis_setting(ax, name, now, dev) for ax in axes]
        return " ".join(str(v) for v in values)
    return "RJ BADCOMMAND"


def set_setting(
    dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
) -> str:
    """``set NAME VALUE``: a device setting (axis 0 only, 0 or 1) or the addressed axes'."""
    if len(args) != 2:
        return "RJ BADCOMMAND" if not args else "RJ BADDATA"
    name = canonical_setting(args[0], dev.spec.firmware)
    raw = args[1]
    if name not in DEVICE_SETTINGS and name not in AXIS_SETTINGS:
        return "RJ BADCOMMAND"
    if name in READ_ONLY or not is_int(raw):
        return "RJ BADDATA"
    value = int(raw)
    if name in DEVICE_SETTINGS:
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


def warning_flags(
    dev: EmulatedDevice, axis: int, axes: list[EmulatedAxis], args: list[str], now: float
) -> str:
    """``warnings [clear]``: the addressed axes' flags by priority; ``clear`` then clears the
    clearable ones (the reply still lists them)."""
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
