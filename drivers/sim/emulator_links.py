"""The emulators' end of a serial link: a raw pseudo-terminal or a TCP socket bound to 127.0.0.1.

The driver under test opens ``/dev/pts/N`` (pty) or ``socket://127.0.0.1:PORT`` (tcp)
with pyserial, exactly as it would a real port.
"""

from __future__ import annotations

import errno
import os
import socket
import tty
from typing import Literal

Transport = Literal["pty", "tcp"]

# --------------------------------------------------------------------------- links


class PtyLink:
    """Master side of a raw pseudo-terminal; the driver opens :attr:`path`."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation, 8-bit clean
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.alive = True

    @property
    def url(self) -> str:
        return self.path

    def read_fds(self) -> list[int]:
        return [self.master] if self.alive else []

    def on_ready(self, ready: list[int]) -> bytes:
        if not self.alive or self.master not in ready:
            return b""
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: nobody has the slave open (cannot happen: we hold it)
            if exc.errno != errno.EIO:
                raise
            return b""

    def write(self, data: bytes) -> None:
        if not self.alive:
            return
        try:
            os.write(self.master, data)
        except (BlockingIOError, OSError):
            pass  # nobody reading: bytes are lost, as on a real line

    def disconnect(self) -> None:
        """Drop the line: the driver's next read/write fails (like an unplugged adapter)."""
        if self.alive:
            self.alive = False
            for fd in (self.master, self.slave):
                try:
                    os.close(fd)
                except OSError:
                    pass

    def close(self) -> None:
        self.disconnect()


class TcpLink:
    """TCP server on 127.0.0.1 with one client at a time (like a serial line)."""

    def __init__(self, port: int) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", port))  # loopback only, never any other address
        self.listener.listen(1)
        self.listener.setblocking(False)
        self.port = self.listener.getsockname()[1]
        self.client: socket.socket | None = None

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def read_fds(self) -> list[int]:
        fds = [self.listener.fileno()]
        if self.client is not None:
            fds.append(self.client.fileno())
        return fds

    def on_ready(self, ready: list[int]) -> bytes:
        data = b""
        if self.client is not None and self.client.fileno() in ready:
            try:
                data = self.client.recv(4096)
            except OSError:
                data = b""
            if not data:
                self._drop_client()
        if self.listener.fileno() in ready:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                conn = None
            if conn is not None:
                if self.client is None:
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    conn.settimeout(1.0)
                    self.client = conn
                else:
                    conn.close()  # the line is taken
        return data

    def write(self, data: bytes) -> None:
        if self.client is None:
            return
        try:
            self.client.sendall(data)
        except OSError:
            self._drop_client()

    def _drop_client(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            except OSError:
                pass
            self.client = None

    def disconnect(self) -> None:
        """Close the current client connection; new connections are still accepted."""
        self._drop_client()

    def close(self) -> None:
        self._drop_client()
        self.listener.close()
