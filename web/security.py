"""API keys and request-size limits.

:class:`ApiGuard` is an ASGI middleware in front of the routes. For every
request under ``/api/``:

1. **API key** (``X-API-Key``) on every mutating request (POST, PUT, PATCH,
   DELETE), and on read-only requests too when ``server.read_only_requires_key``
   is set (``/api/v1/healthz`` and the OpenAPI document stay open). No key: 401; a key that is not one of
   the configured ones: 403 (compared in constant time). When no key is
   configured at all, mutating requests are refused with 403 and a message
   saying how to configure one. Keys are never logged or echoed.
2. **Body size**: a body larger than ``server.max_body_bytes`` is refused with
   413, from its ``Content-Length`` before anything is read, or while it is
   read (chunked uploads); the accepted body is buffered and handed on.
3. **Media type**: a non-empty body whose ``Content-Type`` is not JSON: 415.

The key is checked before the body is read, so a client without a key learns
nothing about its request. Routes also declare the key with :data:`api_key_header`
so that the OpenAPI document shows the security scheme.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterable
from typing import Any

from fastapi import Request, Security
from fastapi.security import APIKeyHeader
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from web.errors import ApiError, error_bytes

API_KEY_HEADER = "X-API-Key"
MUTATING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
OPEN_PATHS = frozenset({"/api/v1/healthz", "/api/v1/openapi.json", "/api/docs", "/api"})
"""API paths that never need a key (no station data: liveness, the API description)."""

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


class ApiGuard:
    """The ASGI middleware described in the module docstring.

    Args:
        app: the wrapped application.
        keys: the accepted API keys.
        max_body_bytes: largest accepted request body (bytes).
        read_only_requires_key: require a key on read-only API requests too.
    """

    def __init__(
        self,
        app: ASGIApp,
        *,
        keys: ApiKeys,
        max_body_bytes: int,
        read_only_requires_key: bool = False,
    ) -> None:
        self.app = app
        self.keys = keys
        self.max_body_bytes = int(max_body_bytes)
        self.read_only_requires_key = read_only_requires_key

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method = scope["method"].upper()
        path = scope["path"]
        headers = _headers(scope)
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
        content_type = headers.get("content-type")
        if body.strip() and content_type is not None and not is_json_type(content_type):
            await _send_error(
                send,
                ApiError(
                    415,
                    "unsupported_media_type",
                    f"the body is {content_type.split(';')[0].strip() or 'of no type'}: send "
                    "JSON with the header Content-Type: application/json",
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
            message = await receive()
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
    if error.status == 413:
        headers.append((b"connection", b"close"))
    headers += [(k.lower().encode(), v.encode()) for k, v in error.headers.items()]
    start: dict[str, Any] = {"type": "http.response.start", "status": error.status}
    start["headers"] = headers
    await send(start)
    await send({"type": "http.response.body", "body": body})


__all__ = [
    "API_KEY_HEADER",
    "ApiGuard",
    "ApiKeys",
    "api_key_header",
    "check_key",
    "needs_key",
]
