"""Serial transport for Zaber ASCII devices: one chain of devices on one port.

The port speaks the ASCII protocol over a :class:`~drivers.zaber.serial_line.SerialLine`
(any pyserial URL: ``/dev/ttyUSB0``, ``/dev/pts/N``, ``socket://127.0.0.1:PORT``;
115200 8N1, opened with an exclusive lock).

Every command goes out with a message id (1-99, cycling) and a checksum (devices
check a command's checksum whatever their ``comm.checksum`` setting).
A reply is accepted only when its device, axis and id match the command and,
once :meth:`ZaberPort.enable_checksums` ran for that device, its checksum is
present and right.  ``comm.checksum`` is a setting the device stores: when the
port had to turn it on, :meth:`ZaberPort.close` turns it off again, so the lab's
stored configuration is left as it was found.  Anything else on the line -- alerts, info messages, late
replies to earlier attempts, other devices' replies, corrupted lines -- is
discarded and counted in :attr:`ZaberPort.stats`.

Retries: when no valid reply arrives within ``reply_timeout_s``, a command is
sent again (up to ``retries`` more times) only if re-sending it is harmless
(:func:`drivers.zaber.protocol.is_idempotent`: get, set, stop, estop, home,
move abs, the status poll).  ``move rel`` and ``warnings clear`` are never
repeated; their failure raises at once with a hint that the command may have
been executed.  ``Reply.attempts`` tells callers a command was repeated (a
repeated move makes the device raise the NI flag, which is then expected).

The port is thread-safe: one request (write + matching reply) at a time.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from dataclasses import dataclass
from types import TracebackType

from drivers.errors import (
    ChecksumError,
    ConnectionLost,
    GarbledReply,
    NoReply,
    PortUnavailable,
)
from drivers.zaber import protocol
from drivers.zaber.protocol import Alert, Reply
from drivers.zaber.serial_line import BAUDRATE, SerialLine


@dataclass
class PortStats:
    """Counters of what the transport saw (for diagnostics and tests)."""

    requests: int = 0
    retries: int = 0
    garbled: int = 0
    stale: int = 0
    alerts: int = 0
    other: int = 0


class ZaberPort:
    """One serial chain of Zaber devices.

    Args:
        url: pyserial port or URL (``/dev/ttyUSB0``, ``/dev/pts/3``, ``socket://127.0.0.1:9000``).
        name: label used in error messages (defaults to the URL).
        reply_timeout_s: seconds to wait for each reply.
        retries: extra attempts for idempotent commands.
        baudrate: line speed (Zaber default 115200).
        exclusive: lock the port against other programs (real ports).
    """

    def __init__(
        self,
        url: str,
        *,
        name: str | None = None,
        reply_timeout_s: float = 0.5,
        retries: int = 2,
        baudrate: int = BAUDRATE,
        exclusive: bool = True,
    ) -> None:
        if reply_timeout_s <= 0:
            raise ValueError("reply_timeout_s must be positive")
        if retries < 0:
            raise ValueError("retries must be >= 0")
        self.reply_timeout_s = reply_timeout_s
        self.retries = retries
        #: a connection lost on the line closes the port first (restoring settings, best effort)
        self._line = SerialLine(
            url,
            name=name or url,
            baudrate=baudrate,
            exclusive=exclusive,
            on_lost=self.close,
            on_overlong=self._count_overlong_line,
        )
        self._lock = threading.RLock()
        self._next_id = 0
        self._checksummed: set[int] = set()
        #: devices whose comm.checksum this port switched on (switched off at close)
        self._checksum_restore: set[int] = set()
        self.stats = PortStats()
        #: Last alerts received (they are not needed for operation; kept for diagnostics).
        self.alerts: deque[Alert] = deque(maxlen=32)

    # ------------------------------------------------------------------ lifecycle

    @property
    def url(self) -> str:
        """The pyserial URL or path of the port."""
        return self._line.url

    @property
    def name(self) -> str:
        """Label used in error messages."""
        return self._line.name

    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._line.is_open

    def open(self) -> ZaberPort:
        """Open the port (115200 8N1, exclusive). Raises PortUnavailable."""
        with self._lock:
            if not self._line.is_open:
                self._line.open()
                self._checksummed.clear()
            return self

    def close(self) -> None:
        """Restore ``comm.checksum`` where this port changed it; close the port (idempotent)."""
        with self._lock:
            self.restore_settings()
            self._line.close()

    def __enter__(self) -> ZaberPort:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ requests

    def request(
        self,
        device: int,
        axis: int,
        text: str,
        *,
        label: str | None = None,
        timeout_s: float | None = None,
        retry: bool | None = None,
        require_checksum: bool | None = None,
    ) -> Reply:
        """Send one command and return the device's matching reply.

        Args:
            device: device number 1-99 (use :meth:`broadcast` for 0).
            axis: 0 (device) or 1-9.
            text: command and data, e.g. ``"get pos"``.
            label: device name for error messages (default: port name + numbers).
            timeout_s: seconds to wait for each attempt's reply.
            retry: allow re-sending; default: only if the command is idempotent.
            require_checksum: default: True once checksums were enabled on ``device``.

        ``RJ`` replies are returned, not raised: the caller knows what they mean.
        Raises NoReply, GarbledReply/ChecksumError, ConnectionLost, PortUnavailable.
        """
        if not 1 <= device <= protocol.MAX_DEVICE:
            raise ValueError(f"device number {device} outside 1-{protocol.MAX_DEVICE}")
        label = label or f"{self.name} device {device} axis {axis}"
        if retry is None:
            retry = protocol.is_idempotent(text)
        if require_checksum is None:
            require_checksum = device in self._checksummed
        timeout = self.reply_timeout_s if timeout_s is None else timeout_s
        attempts = 1 + (self.retries if retry else 0)
        failure: NoReply | GarbledReply | None = None
        with self._lock:
            for attempt in range(1, attempts + 1):
                if attempt > 1:
                    self.stats.retries += 1
                try:
                    reply = self._transact(device, axis, text, timeout, require_checksum, label)
                except (NoReply, GarbledReply) as exc:
                    failure = exc
                    continue
                return dataclasses.replace(reply, attempts=attempt) if attempt > 1 else reply
        assert failure is not None
        tries = f"{attempts} attempt{'s' if attempts > 1 else ''}"
        extra = "" if retry else "; it was not re-sent and may or may not have been executed"
        failure.message = f"{failure.message} ({tries}{extra})"
        raise failure

    def enable_checksums(self, device: int, *, label: str | None = None) -> bool:
        """Make ``device`` append checksums to its replies; True if it does.

        Reads ``comm.checksum`` first; only when it is 0 is it set to 1 (and set back
        to 0 by :meth:`close`).  From then on replies from ``device`` without a valid
        checksum are rejected.  A device that rejects the setting keeps answering
        without checksums (False; replies are still parsed strictly).
        """
        label = label or f"{self.name} device {device}"
        if device in self._checksummed:
            return True
        current = self.request(device, 0, "get comm.checksum", label=label, require_checksum=False)
        if current.rejected:
            return False
        if current.data.strip() != "1":
            reply = self.request(
                device, 0, "set comm.checksum 1", label=label, require_checksum=False
            )
            if reply.rejected:
                return False
            with self._lock:
                self._checksum_restore.add(device)
        with self._lock:
            self._checksummed.add(device)
        return True

    def restore_settings(self) -> None:
        """Set ``comm.checksum`` back to 0 on the devices where this port switched it on
        (best effort: a device that does not answer keeps it)."""
        with self._lock:
            devices, self._checksum_restore = sorted(self._checksum_restore), set()
            if not self._line.is_open:
                return
            for device in devices:
                try:
                    self.request(
                        device,
                        0,
                        "set comm.checksum 0",
                        timeout_s=0.3,
                        retry=False,
                        require_checksum=False,
                    )
                except (NoReply, GarbledReply, ConnectionLost, PortUnavailable):
                    pass
                self._checksummed.discard(device)

    def broadcast(self, text: str, *, listen_s: float = 0.2) -> list[Reply]:
        """Send ``text`` to every device (device 0) and collect replies for ``listen_s`` seconds."""
        with self._lock:
            message_id = self._take_id()
            self._line.write(protocol.format_command(0, 0, text, message_id=message_id), self.name)
            deadline = time.monotonic() + listen_s
            replies: list[Reply] = []
            while True:
                line = self._line.read_line(deadline, self.name)
                if line is None:
                    return sorted(replies, key=lambda r: r.device)
                try:
                    message = protocol.parse_message(line)
                except GarbledReply:
                    self.stats.garbled += 1
                    continue
                if isinstance(message, Reply) and message.message_id == message_id:
                    replies.append(message)
                else:
                    self._count_discarded(message)

    def discover(self, *, listen_s: float = 0.2) -> dict[int, str]:
        """Device numbers on the chain mapped to their device ids.

        Asks with both names (firmware 7 ``device.id``, firmware 6 ``deviceid``): each
        device answers one of them and rejects the other.
        """
        found: dict[int, str] = {}
        for setting in ("device.id", "deviceid"):
            for reply in self.broadcast(f"get {setting}", listen_s=listen_s):
                if not reply.rejected:
                    found.setdefault(reply.device, reply.data)
        return dict(sorted(found.items()))

    # ------------------------------------------------------------------ internals

    def _take_id(self) -> int:
        self._next_id = self._next_id % protocol.MAX_MESSAGE_ID + 1
        return self._next_id

    def _transact(
        self,
        device: int,
        axis: int,
        text: str,
        timeout_s: float,
        require_checksum: bool,
        label: str,
    ) -> Reply:
        message_id = self._take_id()
        self.stats.requests += 1
        self._line.write(protocol.format_command(device, axis, text, message_id=message_id), label)
        deadline = time.monotonic() + timeout_s
        bad: GarbledReply | None = None
        while True:
            line = self._line.read_line(deadline, label)
            if line is None:
                if bad is not None:
                    raise type(bad)(
                        f"no valid reply to {text!r}; last bad line: {bad.message}", device=label
                    )
                raise NoReply(f"no reply to {text!r} within {timeout_s:.2f} s", device=label)
            try:
                message = protocol.parse_message(line, require_checksum=require_checksum)
            except GarbledReply as exc:
                self.stats.garbled += 1
                bad = exc
                continue
            if (
                isinstance(message, Reply)
                and message.message_id == message_id
                and message.device == device
                and message.axis == axis
            ):
                return message
            self._count_discarded(message)

    def _count_discarded(self, message: protocol.Message) -> None:
        if isinstance(message, Alert):
            self.stats.alerts += 1
            self.alerts.append(message)
        elif isinstance(message, Reply):
            self.stats.stale += 1
        else:
            self.stats.other += 1

    def _count_overlong_line(self) -> None:
        self.stats.garbled += 1


__all__ = ["BAUDRATE", "ChecksumError", "PortStats", "ZaberPort"]
