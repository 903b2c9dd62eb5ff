"""The serial line under a Zaber chain: open/close, bytes out, complete lines in.

Any pyserial URL works (``serial.serial_for_url``): a device path such as
``/dev/ttyUSB0`` or ``/dev/serial/by-id/...``, a pseudo-terminal
``/dev/pts/N``, or ``socket://127.0.0.1:PORT``.  Settings are 115200 8N1,
no flow control; real ports are opened with an exclusive lock
(``exclusive=True``, a ``flock`` on POSIX) so a second program cannot talk on
the same chain.

An I/O error on an open line is a lost connection: the owner is told first
(``on_lost``, e.g. to shut its side down), then the line remembers why and raises
:class:`~drivers.errors.ConnectionLost`; later use raises it again, naming the reason,
until the line is opened again.
"""

from __future__ import annotations

import errno
import time
from collections.abc import Callable
from typing import Any

import serial

from drivers.errors import ConnectionLost, PortUnavailable

BAUDRATE = 115200
#: Granularity (s) of blocking reads; replies are picked up as soon as they arrive.
_READ_SLICE_S = 0.01
_MAX_LINE = 1024


class SerialLine:
    """One pyserial port read as lines (not thread-safe: the owner serialises calls).

    Args:
        url: pyserial port or URL.
        name: label used in error messages.
        baudrate: line speed.
        exclusive: lock the port against other programs (real ports).
        on_lost: called when an I/O error loses the connection, before the reason is
            recorded and ConnectionLost raised (default: :meth:`close`); it must close
            the line.
        on_overlong: called when more than ``_MAX_LINE`` bytes arrive without a line
            end (they are dropped).
    """

    def __init__(
        self,
        url: str,
        *,
        name: str,
        baudrate: int = BAUDRATE,
        exclusive: bool = True,
        on_lost: Callable[[], None] | None = None,
        on_overlong: Callable[[], None] | None = None,
    ) -> None:
        self._url = url
        self._name = name
        self._baudrate = baudrate
        self._exclusive = exclusive
        self._on_lost = on_lost or self.close
        self._on_overlong = on_overlong or (lambda: None)
        self._serial: Any = None
        self._buffer = bytearray()
        self._lost: str | None = None  # why the port was closed under us, if it was

    @property
    def url(self) -> str:
        """The pyserial URL or path of the port."""
        return self._url

    @property
    def name(self) -> str:
        """Label used in error messages."""
        return self._name

    @property
    def is_open(self) -> bool:
        """True while the port is open."""
        return self._serial is not None

    def open(self) -> None:
        """Open the port (8N1, exclusive) with an empty input. Raises PortUnavailable."""
        if self._serial is not None:
            return
        try:
            ser = serial.serial_for_url(
                self._url,
                baudrate=self._baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                timeout=_READ_SLICE_S,
                write_timeout=2.0,
                exclusive=self._exclusive if "://" not in self._url else None,
                do_not_open=True,
            )
            ser.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise self._open_error(exc) from exc
        self._serial = ser
        self._lost = None
        self._buffer.clear()
        try:
            ser.reset_input_buffer()  # drop bytes left over from a previous session
        except (serial.SerialException, OSError):
            pass

    def _open_error(self, exc: BaseException) -> PortUnavailable:
        code = getattr(exc, "errno", None)
        text = str(exc)
        if code in (errno.ENOENT, errno.ENODEV, errno.ENXIO) or "No such file" in text:
            hint = (
                "the port path (ls /dev/serial/by-id); is the USB-serial adapter plugged in "
                "and the stage powered?"
            )
        elif code in (errno.EACCES, errno.EPERM) or "Permission denied" in text:
            hint = "permissions: add the user to the 'dialout' group, or fix the udev rule"
        elif code in (errno.EAGAIN, errno.EBUSY) or "exclusive" in text.lower():
            hint = "another program (or another station instance) has this port open"
        elif "refused" in text.lower() or code == errno.ECONNREFUSED:
            hint = "is the server (e.g. 'lfcal emulate-stage --tcp PORT') running on that port?"
        else:
            hint = None
        return PortUnavailable(
            f"cannot open port {self._url}: {text}", device=self._name, hint=hint
        )

    def close(self) -> None:
        """Close the port (idempotent; errors while closing are ignored)."""
        ser, self._serial = self._serial, None
        if ser is not None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def write(self, data: bytes, label: str) -> None:
        """Send ``data``; ``label`` names the device in errors."""
        ser = self._port(label)
        try:
            ser.write(data)
        except (serial.SerialException, OSError) as exc:
            raise self._connection_lost(exc, label) from exc

    def read_line(self, deadline: float, label: str) -> bytes | None:
        """Next complete line (without terminator), or None at the deadline."""
        ser = self._port(label)
        buffer = self._buffer
        while True:
            newline = buffer.find(b"\n")
            if newline >= 0:
                line = bytes(buffer[:newline]).rstrip(b"\r")
                del buffer[: newline + 1]
                if line.strip():
                    return line
                continue
            if len(buffer) > _MAX_LINE:
                self._on_overlong()
                buffer.clear()
            if time.monotonic() >= deadline:
                return None
            try:
                waiting = ser.in_waiting
                chunk = ser.read(waiting if waiting > 0 else 1)
            except (serial.SerialException, OSError) as exc:
                raise self._connection_lost(exc, label) from exc
            buffer += chunk

    def _port(self, label: str) -> Any:
        if self._serial is None and self._lost is not None:
            raise ConnectionLost(
                f"port {self._url} was closed when the connection was lost ({self._lost})",
                device=label,
            )
        if self._serial is None:
            raise PortUnavailable(
                f"port {self._url} is not open", device=label, hint="call open() first"
            )
        return self._serial

    def _connection_lost(self, exc: BaseException, label: str) -> ConnectionLost:
        self._on_lost()
        self._lost = str(exc)
        return ConnectionLost(f"connection on {self._url} lost: {exc}", device=label)


__all__ = ["BAUDRATE", "SerialLine"]
