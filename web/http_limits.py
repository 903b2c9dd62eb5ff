"""Request-head limits and slow-client timeouts where the bytes arrive: in the HTTP protocol.

uvicorn's HTTP protocol (httptools) accumulates a request's line and headers
before any ASGI middleware sees the request, without a limit: an unterminated
48 MB header was buffered (and re-copied at every read) for seconds on the event
loop. :class:`LimitedHttpToolsProtocol` counts the bytes of every request head
as they are read and answers, without waiting for the rest:

* **431** ``Request Header Fields Too Large`` when the head (request line and
  headers) exceeds :attr:`HttpLimits.max_head_bytes`, or it has more than
  :attr:`HttpLimits.max_headers` header fields; the connection is closed, so at
  most one read (256 KiB) past the limit is ever held;
* **408** ``Request Timeout`` when a request head is not complete
  :attr:`HttpLimits.head_timeout_s` seconds after its first byte (a slow or
  stalled client), and a connection that sends nothing at all is closed after
  the same time.

Request bodies are limited by :class:`web.security.ApiGuard` (size, and a
timeout between body chunks). The answers are JSON in the API's error shape.

**One write per small answer.** uvicorn writes a response's status line and
headers as soon as the application starts the response, and the body in a second
write: two TCP segments, and a client waiting for the body wakes up twice. Under
50 pollers on a busy 2-core machine every wake-up of a client is a chance for the
scheduler to preempt the event loop in the middle of a request.
:class:`_CoalescedWrites`, the transport that each request-response cycle writes
to, holds what is written until the end of the current event-loop step (or the
next write, or a close), so a small answer leaves in one write.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from web.errors import error_bytes


@dataclass(frozen=True)
class HttpLimits:
    """Limits of a request head (see the module docstring).

    Attributes:
        max_head_bytes: request line plus headers (bytes).
        max_headers: header fields.
        head_timeout_s: from the first byte of a request head to its end (s); also the
            longest a new connection may stay silent.
    """

    max_head_bytes: int = 16 * 1024
    max_headers: int = 64
    head_timeout_s: float = 10.0


DEFAULT_LIMITS = HttpLimits()


def _answer(status: int, reason: str, code: str, message: str) -> bytes:
    body = error_bytes(status, code, message)
    head = (
        f"HTTP/1.1 {status} {reason}\r\n"
        "content-type: application/json\r\n"
        f"content-length: {len(body)}\r\n"
        "connection: close\r\n\r\n"
    )
    return head.encode("latin-1") + body


class _CoalescedWrites:
    """A transport that joins the writes of one event-loop step into one (see the
    module docstring); everything else goes to the real transport, and ``close`` /
    ``write_eof`` / ``abort`` send (or drop, for ``abort``) what is held first."""

    def __init__(self, transport: asyncio.Transport, loop: asyncio.AbstractEventLoop) -> None:
        self._transport = transport
        self._loop = loop
        self._held: list[bytes] = []

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if not self._held:
            self._loop.call_soon(self.flush)
        self._held.append(data if isinstance(data, bytes) else bytes(data))

    def flush(self) -> None:
        """Write what is held (now)."""
        if not self._held:
            return
        data = b"".join(self._held) if len(self._held) > 1 else self._held[0]
        self._held.clear()
        if not self._transport.is_closing():
            self._transport.write(data)

    def close(self) -> None:
        self.flush()
        self._transport.close()

    def write_eof(self) -> None:
        self.flush()
        self._transport.write_eof()

    def abort(self) -> None:
        self._held.clear()
        self._transport.abort()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)


class LimitedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with the limits of :class:`HttpLimits`
    (class attribute ``limits``; :func:`protocol_with` makes a subclass with others)."""

    limits: HttpLimits = DEFAULT_LIMITS

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._in_head = True  # waiting for (or reading) a request head
        self._head_bytes = 0
        self._header_count = 0
        self._refused = False
        self._head_timer: asyncio.TimerHandle | None = None

    # ------------------------------------------------------------------ the timer

    def _arm(self) -> None:
        if self._head_timer is None:
            self._head_timer = self.loop.call_later(self.limits.head_timeout_s, self._head_late)

    def _disarm(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_late(self) -> None:
        self._head_timer = None
        if self.transport.is_closing() or not self._in_head:
            return
        if self._head_bytes == 0:
            self.transport.close()  # an idle connection: nothing to answer
            return
        self._refuse(
            408,
            "Request Timeout",
            "request_timeout",
            f"the request head was not complete within {self.limits.head_timeout_s:g} s",
        )

    # ------------------------------------------------------------------ the protocol

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        if self._in_head:
            self._head_bytes += len(data)
            self._arm()
        super().data_received(data)
        if self._refused or self.transport.is_closing():
            return
        if self._in_head and self._head_bytes > self.limits.max_head_bytes:
            self._refuse(
                431,
                "Request Header Fields Too Large",
                "header_too_large",
                f"the request line and headers exceed {self.limits.max_head_bytes} bytes",
            )

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_head = True
        self._header_count = 0

    def on_header(self, name: bytes, value: bytes) -> None:
        self._header_count += 1
        if self._header_count > self.limits.max_headers:
            if not self._refused:
                self._refuse(
                    431,
                    "Request Header Fields Too Large",
                    "too_many_headers",
                    f"the request has more than {self.limits.max_headers} header fields",
                )
            return
        super().on_header(name, value)

    def on_headers_complete(self) -> None:
        if self._refused:
            return
        self._in_head = False
        self._head_bytes = 0
        self._disarm()
        super().on_headers_complete()
        cycle = self.cycle
        if cycle is not None and cycle.transport is self.transport:
            cycle.transport = _CoalescedWrites(self.transport, self.loop)  # type: ignore[assignment]

    def on_message_complete(self) -> None:
        super().on_message_complete()
        # the next bytes are the next request's head: counted (and timed) from its
        # first byte; an idle keep-alive connection is closed by uvicorn's timer
        self._in_head = True
        self._head_bytes = 0

    def _refuse(self, status: int, reason: str, code: str, message: str) -> None:
        self._refused = True
        self._disarm()
        self._flush_cycle()  # an answer still held for the previous request goes first
        self.logger.warning("%s: %s", self.client and f"{self.client[0]}:{self.client[1]}", message)
        self.transport.write(_answer(status, reason, code, message))
        self.transport.close()

    def _flush_cycle(self) -> None:
        writes = getattr(self.cycle, "transport", None)
        if isinstance(writes, _CoalescedWrites):
            writes.flush()

    def send_400_response(self, msg: str) -> None:
        self._flush_cycle()  # an answer still held for the previous request goes first
        super().send_400_response(msg)

    def shutdown(self) -> None:
        self._flush_cycle()
        super().shutdown()


def protocol_with(limits: HttpLimits) -> type[LimitedHttpToolsProtocol]:
    """A protocol class (for ``uvicorn.Config(http=...)``) with these limits."""
    return type("LimitedHttpToolsProtocol", (LimitedHttpToolsProtocol,), {"limits": limits})


__all__ = [
    "DEFAULT_LIMITS",
    "HttpLimits",
    "LimitedHttpToolsProtocol",
    "protocol_with",
]
