"""API keys and request-size limits.

:class:`ApiGuard` is an ASGI middleware in front of the routes. For every
request:

0. **No key in the URL**: a query parameter named like a key (``api_key``,
   ``apikey``, ``key``, ``token``, ``access_token``, ``x-api-key``) is refused
   with 401 (``api_key_in_query``) on every path, before anything else: URLs
   end up in access logs, proxies and browser histories. (The server's access
   log also redacts such parameters: :class:`web.server.RedactKeys`.)

and for every request under ``/api/``:

1. **API key** (``X-API-Key``) on every mutating request (POST, PUT, PATCH,
   DELETE), and on read-only requests too when ``server.read_only_requires_key``
   is set (``/api/v1/healthz`` and the OpenAPI document stay open). No key: 401; a key that is not one of
   the configured ones: 403 (compared in constant time). When no key is
   configured at all, mutating requests are refused with 403 and a message
   saying how to configure one. Keys are never logged or echoed.
2. **Body size**: a body larger than ``server.max_body_bytes`` is refused with
   413, from its ``Content-Length`` before anything is read, or while it is
   read (chunked uploads); the accepted body is buffered and handed on.
   A body whose chunks stop arriving for ``body_timeout_s`` seconds: 408.
3. **Media type**: a non-empty body whose ``Content-Type`` is missing or is not
   JSON: 415.
4. **JSON**: a body that is not UTF-8 or not JSON, or is nested too deeply for
   the parser: 400 ``malformed_json`` (before FastAPI, which would answer a
   generic 400 or a 422 with the raw bytes).

The key is checked before the body is read, so a client without a key learns
nothing about its request. Routes also declare the key with :data:`api_key_header`
so that the OpenAPI document shows the security scheme.
"""

from __future__ import annotations

import asyncio
import hmac
import json
from collections.abc import Iterable
from typing import Any
from urllib.parse import parse_qsl, unquote_plus

from fastapi import Request, Security
from fastapi.security import APIKeyHeader
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from web.errors import ApiError, error_bytes

API_KEY_HEADER = "X-API-Key"
MUTATING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
OPEN_PATHS = frozenset({"/api/v1/healthz", "/api/v1/openapi.json", "/api/docs", "/api"})
"""API paths that never need a key (no station data: liveness, the API description)."""
OPEN_PREFIXES = ("/api/docs/",)
"""Path prefixes that never need a key (the API documentation's static files)."""
KEY_PARAMETERS = frozenset(
    {"api_key", "apikey", "api-key", "key", "token", "access_token", "x-api-key"}
)
"""Query parameters that look like credentials: refused, and redacted from logs."""

api_key_header = APIKeyHeader(
    name=API_KEY_HEADER,
    auto_error=False,
    scheme_name="ApiKey",
    description="an API key from [server] api_keys or $LFCAL_API_KEYS",
)


class ApiKeys:
    """The accepted API keys (never printed: ``repr`` shows only how many there are)."""

    def __init__(self, keys: Iterable[str]) -> None:
        self._keys = tuple(k.encode() for k in keys if k)

    def __repr__(self) -> str:
        return f"ApiKeys({len(self._keys)} keys)"

    def __bool__(self) -> bool:
        return bool(self._keys)

    def accepts(self, key: str) -> bool:
        """True if ``key`` is one of the keys (constant time per key)."""
        given = key.encode("utf-8", "replace")
        ok = False
        for k in self._keys:
            ok |= hmac.compare_digest(given, k)
        return ok

    def problem(self, key: str | None) -> ApiError | None:
        """The 401/403 error for ``key`` (None: accepted)."""
        if key is None or key == "":
            return ApiError(
                401,
                "api_key_required",
                f"this request needs an API key: send it in the {API_KEY_HEADER} header",
                headers={"WWW-Authenticate": f'ApiKey header="{API_KEY_HEADER}"'},
            )
        if not self._keys:
            return ApiError(
                403,
                "api_key_rejected",
                "the server has no API keys configured, so it accepts no changes: add keys to "
                "[server] api_keys or $LFCAL_API_KEYS and restart it",
            )
        if not self.accepts(key):
            return ApiError(403, "api_key_rejected", "the API key is not accepted by this server")
        return None


def needs_key(method: str, path: str, read_only_requires_key: bool) -> bool:
    """Whether a request to ``path`` with ``method`` must carry an API key."""
    if not path.startswith("/api/") or path in OPEN_PATHS or method == "OPTIONS":
        return False
    if path.startswith(OPEN_PREFIXES):
        return False
    return method in MUTATING_METHODS or read_only_requires_key


def check_key(request: Request, key: str | None = Security(api_key_header)) -> None:
    """Route dependency: the API key (declares the scheme in OpenAPI; :class:`ApiGuard`
    has normally checked it already)."""
    keys: ApiKeys = request.app.state.api_keys
    error = keys.problem(key)
    if error is not None:
        raise error


class BodyTooLarge(Exception):
    """The request body exceeds the limit."""


class BodyTooSlow(Exception):
    """The client stopped sending its body."""


def key_in_query(query_string: bytes) -> str | None:
    """The name of a credential-like query parameter (:data:`KEY_PARAMETERS`), or None."""
    if not query_string:
        return None
    text = query_string.decode("latin-1")
    for name, _ in parse_qsl(text, keep_blank_values=True):
        if name.strip().lower() in KEY_PARAMETERS:
            return name
    return None


def redact_query(text: str) -> str:
    """``text`` (a path or a log line) with the value of every credential-like query
    parameter (:data:`KEY_PARAMETERS`, also percent-encoded) replaced by ``REDACTED``."""
    if "?" not in text:
        return text
    head, _, rest = text.partition("?")
    query, space, tail = rest.partition(" ")
    parts = []
    for piece in query.split("&"):
        name, eq, _value = piece.partition("=")
        if unquote_plus(name).strip().lower() in KEY_PARAMETERS:
            piece = f"{name}{eq or '='}REDACTED"
        parts.append(piece)
    return f"{head}?{'&'.join(parts)}{space}{redact_query(tail) if tail else ''}"


def json_problem(body: bytes) -> str | None:
    """Why ``body`` is not a JSON document (None: it is one)."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        return f"it is not UTF-8: {exc.reason} at byte {exc.start}"
    try:
        json.loads(text)
    except json.JSONDecodeError as exc:
        return f"{exc.msg} at character {exc.pos}"
    except RecursionError:
        return "it is nested too deeply"
    except ValueError as exc:
        return str(exc)
    return None


class ApiGuard:
    """The ASGI middleware described in the module docstring.

    Args:
        app: the wrapped application.
        keys: the accepted API keys.
        max_body_bytes: largest accepted request body (bytes).
        read_only_requires_key: require a key on read-only API requests too.
        body_timeout_s: longest wait for the next chunk of a body (s).
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        keys: ApiKeys,
        max_body_bytes: int,
        read_only_requires_key: bool = False,
        body_timeout_s: float = 10.0,
    ) -> None:
        self.app = app
        self.keys = keys
        self.max_body_bytes = int(max_body_bytes)
        self.read_only_requires_key = read_only_requires_key
        self.body_timeout_s = float(body_timeout_s)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method = scope["method"].upper()
        path = scope["path"]
        headers = _headers(scope)
        leaked = key_in_query(scope.get("query_string", b""))
        if leaked is not None:
            await _send_error(
                send,
                ApiError(
                    401,
                    "api_key_in_query",
                    f"API keys are not accepted in the URL (query parameter {leaked!r}): URLs "
                    f"end up in logs and browser histories. Send the key in the "
                    f"{API_KEY_HEADER} header, and replace a key that was sent in a URL",
                    headers={"WWW-Authenticate": f'ApiKey header="{API_KEY_HEADER}"'},
                ),
            )
            return
        if needs_key(method, path, self.read_only_requires_key):
            error = self.keys.problem(headers.get(API_KEY_HEADER.lower()))
            if error is not None:
                await _send_error(send, error)
                return
        if method not in MUTATING_METHODS:
            await self.app(scope, receive, send)
            return
        length = headers.get("content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await _send_error(
                    send, ApiError(400, "bad_request", "the Content-Length header is not a number")
                )
                return
            if declared > self.max_body_bytes:
                await _send_error(send, self._too_large(declared))
                return
        try:
            body = await self._read_body(receive)
        except BodyTooLarge:
            await _send_error(send, self._too_large(None))
            return
        except BodyTooSlow:
            await _send_error(
                send,
                ApiError(
                    408,
                    "request_timeout",
                    f"the request body stopped arriving for {self.body_timeout_s:g} s",
                ),
            )
            return
        content_type = headers.get("content-type")
        if body.strip() and (content_type is None or not is_json_type(content_type)):
            shown = "of no type (no Content-Type header)"
            if content_type is not None:
                shown = content_type.split(";")[0].strip() or shown
            await _send_error(
                send,
                ApiError(
                    415,
                    "unsupported_media_type",
                    f"the body is {shown}: send JSON with the header "
                    "Content-Type: application/json",
                ),
            )
            return
        if body.strip():
            problem = json_problem(body)
            if problem is not None:
                await _send_error(
                    send,
                    ApiError(
                        400,
                        "malformed_json",
                        f"the request body is not valid JSON ({problem}); send a JSON object "
                        'such as {"start_mm": 0, "stop_mm": 99, "step_mm": 1}',
                    ),
                )
                return
        await self.app(scope, _replay(body, receive), send)

    def _too_large(self, size: int | None) -> ApiError:
        got = f" ({size} bytes)" if size is not None else ""
        return ApiError(
            413,
            "body_too_large",
            f"the request body{got} is larger than the {self.max_body_bytes} bytes this server "
            "accepts ([server] max_body_bytes); a sweep request is a small JSON object",
        )

    async def _read_body(self, receive: Receive) -> bytes:
        chunks: list[bytes] = []
        total = 0
        while True:
            try:
                message = await asyncio.wait_for(receive(), self.body_timeout_s)
            except TimeoutError:
                raise BodyTooSlow() from None
            if message["type"] == "http.disconnect":
                break
            chunk = message.get("body", b"")
            total += len(chunk)
            if total > self.max_body_bytes:
                raise BodyTooLarge()
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        return b"".join(chunks)


def is_json_type(content_type: str) -> bool:
    """True for ``application/json`` and ``application/*+json`` (parameters ignored)."""
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (
        media.startswith("application/") and media.endswith("+json")
    )


def _headers(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}


def _replay(body: bytes, receive: Receive) -> Receive:
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


async def _send_error(send: Send, error: ApiError) -> None:
    body = error_bytes(error.status, error.code, error.message)
    headers: list[tuple[bytes, bytes]] = [
        (b"content-type", b"application/json"),
        (b"content-length", str(len(body)).encode()),
    ]
    if error.status in (408, 413):
        headers.append((b"connection", b"close"))
    headers += [(k.lower().encode(), v.encode()) for k, v in error.headers.items()]
    start: dict[str, Any] = {"type": "http.response.start", "status": error.status}
    start["headers"] = headers
    await send(start)
    await send({"type": "http.response.body", "body": body})


class HeadAsGet:
    """ASGI middleware: ``HEAD`` on a ``GET`` route answers as ``GET`` would, without
    the body (the route runs as ``GET``; a streaming response is stopped once its
    headers are sent). The server drops any body of a ``HEAD`` answer."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return
        started = asyncio.Event()

        async def head_send(message: Message) -> None:
            if message["type"] == "http.response.start" and not started.is_set():
                await send(message)
                await send({"type": "http.response.body", "body": b"", "more_body": False})
                started.set()

        task = asyncio.ensure_future(self.app(dict(scope, method="GET"), receive, head_send))
        waiter = asyncio.ensure_future(started.wait())
        try:
            await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
            if not task.done():
                task.cancel()
            try:
                await task
            except asyncio.CancelledError:
                if not started.is_set():
                    raise


__all__ = [
    "API_KEY_HEADER",
    "HeadAsGet",
    "KEY_PARAMETERS",
    "key_in_query",
    "redact_query",
    "ApiGuard",
    "ApiKeys",
    "api_key_header",
    "check_key",
    "needs_key",
]
