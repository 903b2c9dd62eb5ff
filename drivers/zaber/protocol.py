"""Zaber ASCII protocol: formatting, parsing and checksums.  Pure functions, no I/O.

Message forms (Zaber ASCII Protocol Manual, "Message Format")::

    command  /1 1 12 move abs 10000:CC\\n      device, axis, message id, command, data
    reply    @01 1 12 OK BUSY -- 0:CC\\r\\n      device, axis, id, OK|RJ, IDLE|BUSY, warning, data
    info     #01 0 12 some text:CC\\r\\n
    alert    !01 1 IDLE --:CC\\r\\n               sent spontaneously when comm.alert is 1

Device 0 addresses every device, axis 0 the whole device.  The message id
(0-99) is optional; when a command carries one, the device echoes it.

Checksum (the manual's "Checksumming" section): the sum of the byte values of
the message **after** the start character (``/``, ``@``, ``#``, ``!``) up to
but not including the ``:``, taken modulo 256 and negated (two's complement),
sent as two upper-case hex digits.  So ``(sum(body) + CC) % 256 == 0``.
Cross-checked against Zaber's own code: the ``zproto`` crate
(``src/ascii/checksum.rs``: ``((sum ^ 0xFF) + 1) & 0xFF``) and the test
vectors of Zaber's ``zaber.serial`` Python library
(``"@01 0 OK IDLE -- 0:8D"``, ``"@01 0 OK IDLE -- 7z:0C"``), which only hold
when the start character is excluded; ``tests/test_zaber_protocol.py`` pins
them.

Units: positions are integer microsteps; ``maxspeed`` data is
microsteps/s x 1.6384; ``accel`` data is microsteps/s^2 x 1.6384 / 10000.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass

from drivers.errors import (
    ChecksumError,
    CommandRejected,
    DeviceError,
    DeviceFault,
    GarbledReply,
    LimitHit,
    MoveInterrupted,
    NotReferenced,
    StageStalled,
)

COMMAND_START = "/"
REPLY_START = "@"
INFO_START = "#"
ALERT_START = "!"

MAX_DEVICE = 99
MAX_AXIS = 9
MAX_MESSAGE_ID = 99

#: maxspeed data units per (microstep/s).
SPEED_DATA_PER_USTEP_S = 1.6384
#: accel data units per (microstep/s^2).
ACCEL_DATA_PER_USTEP_S2 = 1.6384 / 10000.0

NO_WARNING = "--"

#: Warning flags, highest precedence first (the reply shows the highest active one).
WARNING_FLAGS: dict[str, str] = {
    "FD": "driver disabled (over-temperature)",
    "FQ": "encoder error: position may be unreliable",
    "FS": "stalled and stopped",
    "FT": "excessive twist (lockstep group)",
    "FB": "stream bounds error",
    "FP": "interpolated path deviation",
    "FE": "limit error: limit sensor cannot be reached or is faulty",
    "WH": "device not homed (has a reference, calibration disabled)",
    "WL": "unexpected limit trigger",
    "WP": "invalid calibration type",
    "WV": "supply voltage out of range",
    "WT": "controller temperature high",
    "WM": "displaced when stationary",
    "WR": "no reference position",
    "NC": "manual control",
    "NI": "command interrupted",
    "ND": "stream discontinuity",
    "NU": "setting update pending",
    "NJ": "joystick calibrating",
}
WARNING_PRIORITY: tuple[str, ...] = tuple(WARNING_FLAGS)

#: Flags that mean the device stopped a motion by itself (faults).
FAULT_FLAGS = frozenset(flag for flag in WARNING_PRIORITY if flag.startswith("F"))
#: Flags after which the axis position can no longer be trusted (re-home).
POSITION_LOST_FLAGS = frozenset({"FS", "FE", "FQ", "WL", "WR"})
#: Flags cleared by ``warnings clear`` (WR only clears by homing / setting pos).
CLEARABLE_FLAGS = frozenset(FAULT_FLAGS | {"WL", "WM", "NI"})

#: Reasons a device gives in the data field of an ``RJ`` reply.
REJECT_REASONS: dict[str, str] = {
    "AGAIN": "cannot be processed right now, send it again",
    "BADAXIS": "axis number greater than the number of axes",
    "BADCOMMAND": "unknown command or setting",
    "BADDATA": "data missing, malformed or out of range",
    "BADMESSAGEID": "message id not -- or 0-99",
    "DEVICEONLY": "axis number given for a device-only command or setting",
    "FULL": "out of storage",
    "LOCKSTEP": "axis is part of a lockstep group",
    "NOACCESS": "not available at the current access level",
    "PARKED": "device is parked",
    "STATUSBUSY": "not possible while busy",
}

# Commands the transport may re-send when no (valid) reply came back: sending
# them twice leaves the device in the same state as sending them once.
#  - get / set / stop / estop / the empty status poll: obviously safe;
#  - home and move abs: the target is absolute, so a repeat ends at the same
#    place; the repeat interrupts the first one, which the device reports
#    with the NI flag -- callers ignore NI when ``Reply.attempts > 1``.
# Never re-sent: move rel / move vel (a repeat moves further) and
# "warnings clear" (the first reply listed the cleared flags; a repeat loses them).
_IDEMPOTENT_PREFIXES = ("get ", "set ", "move abs ", "move min", "move max")
_IDEMPOTENT_EXACT = frozenset({"", "stop", "estop", "home", "warnings"})

_HEX2 = re.compile(r"[0-9A-Fa-f]{2}")
_WARN = re.compile(r"[A-Z-]{2}")


# --------------------------------------------------------------------------- checksum


def checksum(body: bytes | str) -> int:
    """Zaber LRC of ``body`` (the message without start char, colon and checksum)."""
    data = body.encode("ascii") if isinstance(body, str) else body
    return (-sum(data)) & 0xFF


def with_checksum(message: str) -> str:
    """Append ``:CC`` to a message that starts with its start character."""
    return f"{message}:{checksum(message[1:]):02X}"


def split_checksum(line: str) -> tuple[str, int | None]:
    """Split ``"@01 ... data:CC"`` into (message, checksum or None). Does not verify."""
    if len(line) >= 3 and line[-3] == ":" and _HEX2.fullmatch(line[-2:]):
        return line[:-3], int(line[-2:], 16)
    return line, None


def verify_checksum(line: str) -> bool:
    """True if ``line`` carries a checksum and it matches its contents."""
    message, cc = split_checksum(line)
    return cc is not None and (sum(message[1:].encode("ascii")) + cc) & 0xFF == 0


# --------------------------------------------------------------------------- commands


@dataclass(frozen=True)
class Command:
    """A host-to-device command.

    Attributes:
        device: 0 (all devices) or 1-99.
        axis: 0 (whole device) or 1-9.
        message_id: 0-99, or None for no id.
        text: command and data, e.g. ``"move abs 10000"`` or ``""`` (status poll).
    """

    device: int
    axis: int
    message_id: int | None
    text: str

    def encode(self, *, checksum: bool = True) -> bytes:
        """Bytes on the wire, newline-terminated."""
        return format_command(
            self.device, self.axis, self.text, message_id=self.message_id, checksum=checksum
        )


def format_command(
    device: int,
    axis: int,
    text: str,
    *,
    message_id: int | None = None,
    checksum: bool = True,
) -> bytes:
    """Format ``/device axis [id] text[:CC]\\n``.

    Raises ValueError for out-of-range numbers or characters the protocol
    does not carry (control characters, ``:``, ``/`` inside the text).
    """
    if not 0 <= device <= MAX_DEVICE:
        raise ValueError(f"device number {device} outside 0-{MAX_DEVICE}")
    if not 0 <= axis <= MAX_AXIS:
        raise ValueError(f"axis number {axis} outside 0-{MAX_AXIS}")
    if message_id is not None and not 0 <= message_id <= MAX_MESSAGE_ID:
        raise ValueError(f"message id {message_id} outside 0-{MAX_MESSAGE_ID}")
    if any(not 32 <= ord(c) <= 126 for c in text) or ":" in text or "/" in text:
        raise ValueError(f"command text {text!r} has characters the protocol cannot carry")
    text = " ".join(text.split())
    parts = [f"{COMMAND_START}{device}", str(axis)]
    if message_id is not None:
        parts.append(str(message_id))
    if text:
        parts.append(text)
    message = " ".join(parts)
    if checksum:
        message = with_checksum(message)
    return (message + "\n").encode("ascii")


class CommandSyntaxError(ValueError):
    """A command line a device cannot parse; ``reason`` is the RJ reason it answers.

    ``device`` and ``axis`` are the numbers parsed before the error (0 if none).
    """

    def __init__(self, message: str, *, reason: str, device: int = 0, axis: int = 0) -> None:
        self.reason = reason
        self.device = device
        self.axis = axis
        super().__init__(message)


def parse_command(line: bytes | str) -> tuple[Command, bool]:
    """Parse a command line (as a device does).  Returns (command, had_checksum).

    Device, axis and message id are optional (``/get pos`` is ``/0 0 get pos``).
    Raises ChecksumError for a wrong checksum and CommandSyntaxError (with the
    reason a device would reject it for) for a malformed message id.
    """
    text = line.decode("ascii", "replace") if isinstance(line, bytes) else line
    text = text.strip("\r\n")
    start = text.find(COMMAND_START)
    if start < 0:
        raise CommandSyntaxError(f"no '/' in {text!r}", reason="BADCOMMAND")
    text = text[start:]
    message, cc = split_checksum(text)
    if cc is not None and (sum(message[1:].encode("ascii", "replace")) + cc) & 0xFF:
        raise ChecksumError(f"command checksum mismatch in {text!r}")
    tokens = message[1:].split()
    numbers: list[int] = []
    message_id: int | None = None
    while tokens and len(numbers) < 2 and tokens[0].isdigit():
        numbers.append(int(tokens.pop(0)))
    if len(numbers) == 2 and tokens and (tokens[0].isdigit() or tokens[0] == "--"):
        token = tokens.pop(0)
        if token != "--":
            if len(token) > 2:
                raise CommandSyntaxError(
                    f"bad message id {token!r}",
                    reason="BADMESSAGEID",
                    device=numbers[0],
                    axis=numbers[1],
                )
            message_id = int(token)
    device = numbers[0] if numbers else 0
    axis = numbers[1] if len(numbers) > 1 else 0
    return Command(device, axis, message_id, " ".join(tokens)), cc is not None


def is_idempotent(text: str) -> bool:
    """True if re-sending ``text`` after a lost reply is safe (see module notes)."""
    text = " ".join(text.split())
    return text in _IDEMPOTENT_EXACT or text.startswith(_IDEMPOTENT_PREFIXES)


# --------------------------------------------------------------------------- device messages


@dataclass(frozen=True)
class Reply:
    """A device's ``@`` reply to a command.

    Attributes:
        device, axis: who answers (axis 0 = whole device).
        message_id: echoed id, or None.
        rejected: True for ``RJ``, False for ``OK``.
        busy: True for ``BUSY``, False for ``IDLE``.
        warning: highest-precedence active flag, ``"--"`` for none.
        data: the data field (reason code when rejected).
        has_checksum: whether the line carried a (verified) checksum.
        attempts: how many times the transport sent the command (1 = first try).
    """

    device: int
    axis: int
    message_id: int | None
    rejected: bool
    busy: bool
    warning: str
    data: str
    has_checksum: bool = False
    attempts: int = 1

    @property
    def flag(self) -> str:
        """``"OK"`` or ``"RJ"``."""
        return "RJ" if self.rejected else "OK"

    @property
    def status(self) -> str:
        """``"BUSY"`` or ``"IDLE"``."""
        return "BUSY" if self.busy else "IDLE"

    @property
    def reject_reason(self) -> str | None:
        """The RJ reason (``BADDATA``...), None when accepted."""
        return self.data.split()[0] if self.rejected and self.data else None

    def data_int(self) -> int:
        """The data field as one integer (raises GarbledReply if it is not)."""
        try:
            return int(self.data.split()[0])
        except (ValueError, IndexError):
            raise GarbledReply(f"expected an integer in reply data, got {self.data!r}") from None

    def data_ints(self) -> list[int]:
        """The data field as a list of integers (one per axis for axis-0 gets)."""
        try:
            return [int(token) for token in self.data.split()]
        except ValueError:
            raise GarbledReply(f"expected integers in reply data, got {self.data!r}") from None


@dataclass(frozen=True)
class Info:
    """A ``#`` info message (extra text after some replies)."""

    device: int
    axis: int
    message_id: int | None
    text: str


@dataclass(frozen=True)
class Alert:
    """A ``!`` alert, sent unprompted (e.g. a move finished) when comm.alert is 1."""

    device: int
    axis: int
    busy: bool
    warning: str
    data: str


Message = Reply | Info | Alert


def _field_int(token: str, what: str, line: str, limit: int) -> int:
    if not token.isdigit() or int(token) > limit:
        raise GarbledReply(f"bad {what} {token!r} in {line!r}")
    return int(token)


def parse_message(line: bytes | str, *, require_checksum: bool = False) -> Message:
    """Parse one device-to-host line (``@`` reply, ``#`` info or ``!`` alert).

    Raises ChecksumError when a checksum is present but wrong (or absent while
    ``require_checksum``), GarbledReply for anything malformed.
    """
    if isinstance(line, bytes):
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            raise GarbledReply(f"non-ASCII bytes in reply {line!r}") from None
    else:
        text = line
    text = text.rstrip("\r\n")
    if not text or text[0] not in (REPLY_START, INFO_START, ALERT_START):
        raise GarbledReply(f"unexpected line {text!r}")
    if any(not 32 <= ord(c) <= 126 for c in text):
        raise GarbledReply(f"control characters in reply {text!r}")
    message, cc = split_checksum(text)
    if cc is None:
        if require_checksum:
            raise ChecksumError(f"reply without checksum {text!r} (comm.checksum is 0?)")
    elif (sum(message[1:].encode("ascii")) + cc) & 0xFF:
        raise ChecksumError(f"checksum mismatch in reply {text!r}")
    kind = message[0]
    tokens = message[1:].split(" ")
    if len(tokens) < 2:
        raise GarbledReply(f"truncated reply {text!r}")
    device = _field_int(tokens[0], "device", text, MAX_DEVICE)
    axis = _field_int(tokens[1], "axis", text, MAX_AXIS)
    rest = tokens[2:]
    has_cc = cc is not None
    if kind == ALERT_START:
        if len(rest) < 2 or rest[0] not in ("IDLE", "BUSY") or not _WARN.fullmatch(rest[1]):
            raise GarbledReply(f"malformed alert {text!r}")
        return Alert(device, axis, rest[0] == "BUSY", rest[1], " ".join(rest[2:]))
    message_id: int | None = None
    if kind == INFO_START:
        if rest and rest[0].isdigit() and len(rest[0]) <= 2:
            message_id = int(rest.pop(0))
        return Info(device, axis, message_id, " ".join(rest))
    if rest and rest[0].isdigit():
        message_id = _field_int(rest.pop(0), "message id", text, MAX_MESSAGE_ID)
    if len(rest) < 4:
        raise GarbledReply(f"truncated reply {text!r}")
    flag, status, warning = rest[0], rest[1], rest[2]
    if flag not in ("OK", "RJ") or status not in ("IDLE", "BUSY") or not _WARN.fullmatch(warning):
        raise GarbledReply(f"malformed reply {text!r}")
    data = " ".join(rest[3:])
    if not data:
        raise GarbledReply(f"reply without data field {text!r}")
    return Reply(device, axis, message_id, flag == "RJ", status == "BUSY", warning, data, has_cc)


def format_reply(
    device: int,
    axis: int,
    *,
    message_id: int | None = None,
    rejected: bool = False,
    busy: bool = False,
    warning: str = NO_WARNING,
    data: str = "0",
    checksum: bool = True,
) -> bytes:
    """Format a device reply line (``\\r\\n``-terminated), as devices send them."""
    parts = [f"{REPLY_START}{device:02d}", str(axis)]
    if message_id is not None:
        parts.append(str(message_id))
    parts += ["RJ" if rejected else "OK", "BUSY" if busy else "IDLE", warning, data]
    message = " ".join(parts)
    if checksum:
        message = with_checksum(message)
    return (message + "\r\n").encode("ascii")


def format_alert(
    device: int, axis: int, *, busy: bool = False, warning: str = NO_WARNING, checksum: bool = True
) -> bytes:
    """Format an alert line (``\\r\\n``-terminated)."""
    message = f"{ALERT_START}{device:02d} {axis} {'BUSY' if busy else 'IDLE'} {warning}"
    if checksum:
        message = with_checksum(message)
    return (message + "\r\n").encode("ascii")


# --------------------------------------------------------------------------- flags & errors


def highest_warning(flags: Iterable[str]) -> str:
    """The flag a reply shows for a set of active flags (``"--"`` if none)."""
    active = set(flags)
    for flag in WARNING_PRIORITY:
        if flag in active:
            return flag
    return NO_WARNING


def parse_warnings_data(data: str) -> frozenset[str]:
    """Parse the data of a ``warnings`` reply (``"02 FS WR"``) into a set of flags."""
    tokens = data.split()
    if not tokens or not tokens[0].isdigit() or int(tokens[0]) != len(tokens) - 1:
        raise GarbledReply(f"malformed warnings list {data!r}")
    return frozenset(tokens[1:])


def describe_flags(flags: Iterable[str]) -> str:
    """``"FS (stalled and stopped), WR (no reference position)"``, by precedence."""
    ordered = sorted(
        set(flags), key=lambda f: WARNING_PRIORITY.index(f) if f in WARNING_FLAGS else 99
    )
    return ", ".join(f"{f} ({WARNING_FLAGS.get(f, 'unknown flag')})" for f in ordered)


def error_for_flags(
    flags: Iterable[str],
    *,
    device: str,
    context: str,
    ignore: Iterable[str] = (),
) -> DeviceError | None:
    """The typed error a set of active warning flags means, or None if harmless.

    Precedence: stall, other faults, limit, lost reference, interruption.
    ``ignore`` lists flags the caller expects (e.g. NI after its own retry).
    """
    active = frozenset(flags) - frozenset(ignore)
    if not active:
        return None
    text = f"{context}: {describe_flags(active)}"
    if "FS" in active:
        return StageStalled(text, device=device, flags=active)
    if "FE" in active or "WL" in active:
        return LimitHit(text, device=device, flags=active)
    faults = active & FAULT_FLAGS
    if faults:
        return DeviceFault(text, device=device, flags=active)
    if "WR" in active:
        return NotReferenced(text, device=device, flags=active)
    if "NI" in active:
        return MoveInterrupted(text, device=device, flags=active)
    return None


def rejection_error(reply: Reply, *, command: str, device: str) -> CommandRejected:
    """The CommandRejected error for an ``RJ`` reply."""
    reason = reply.reject_reason or "UNKNOWN"
    meaning = REJECT_REASONS.get(reason, "unknown reason")
    return CommandRejected(
        f"device rejected {command!r}: {reason} ({meaning})",
        reason=reason,
        command=command,
        device=device,
    )


# --------------------------------------------------------------------------- units


def speed_to_data(usteps_per_s: float) -> int:
    """maxspeed setting value for a speed in microsteps/s."""
    return max(1, round(usteps_per_s * SPEED_DATA_PER_USTEP_S))


def data_to_speed(data: int) -> float:
    """Speed in microsteps/s for a maxspeed setting value."""
    return data / SPEED_DATA_PER_USTEP_S


def accel_to_data(usteps_per_s2: float) -> int:
    """accel setting value for an acceleration in microsteps/s^2."""
    return max(1, round(usteps_per_s2 * ACCEL_DATA_PER_USTEP_S2))


def data_to_accel(data: int) -> float:
    """Acceleration in microsteps/s^2 for an accel setting value."""
    return data / ACCEL_DATA_PER_USTEP_S2


def move_duration_s(distance: float, speed: float, accel: float) -> float:
    """Duration (s) of a trapezoidal move from rest to rest.

    ``distance`` in any length unit, ``speed`` in that unit/s, ``accel`` in
    that unit/s^2 (accel <= 0 means infinite acceleration).
    """
    distance = abs(distance)
    if distance == 0:
        return 0.0
    if speed <= 0:
        raise ValueError("speed must be positive")
    if accel <= 0:
        return distance / speed
    if distance >= speed * speed / accel:
        return distance / speed + speed / accel
    return 2.0 * (distance / accel) ** 0.5
