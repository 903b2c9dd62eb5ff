"""One JSON error shape for every failed request, and the exception handlers that produce it.

Every 4xx/5xx answer of the API is an :class:`ErrorBody`::

    {"status": 422, "code": "invalid_request",
     "message": "the sweep request is invalid: start_mm: must be ≤ 100 mm, got 150",
     "fields": [{"field": "start_mm", "message": "must be ≤ 100 mm, got 150"}],
     "context": null}

``code`` is a stable machine-readable word, ``message`` says what went wrong and
what to do about it, ``fields`` names each offending request field (422), and
``context`` carries extra data (e.g. the device description of a 503).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from station.db import StorageFull, StoreUnavailable

log = logging.getLogger("lfcal.web")


class FieldError(BaseModel):
    """One problem of one request field."""

    field: str = Field(description="the field: a body key (start_mm), a query or path parameter")
    message: str = Field(description="what is wrong and what would be accepted")


class ErrorBody(BaseModel):
    """The body of every error response."""

    status: int = Field(description="the HTTP status code")
    code: str = Field(description="machine-readable error code, e.g. invalid_request")
    message: str = Field(description="what went wrong and how to fix it")
    fields: list[FieldError] = Field(default_factory=list, description="field-level problems")
    context: dict[str, Any] | None = Field(default=None, description="extra data")


class ApiError(Exception):
    """An error answered with :class:`ErrorBody` (raise it from a route)."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        fields: Sequence[tuple[str, str]] = (),
        context: Mapping[str, Any] | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.fields = list(fields)
        self.context = dict(context) if context is not None else None
        self.headers = dict(headers or {})

    def body(self) -> dict[str, Any]:
        """The JSON body."""
        return ErrorBody(
            status=self.status,
            code=self.code,
            message=self.message,
            fields=[FieldError(field=f, message=m) for f, m in self.fields],
            context=self.context,
        ).model_dump()

    def response(self) -> JSONResponse:
        """The JSON response."""
        return JSONResponse(self.body(), status_code=self.status, headers=self.headers)


def error_response(
    status: int, code: str, message: str, headers: Mapping[str, str] | None = None
) -> JSONResponse:
    """A JSON error response without field problems."""
    return ApiError(status, code, message, headers=headers).response()


def error_bytes(status: int, code: str, message: str) -> bytes:
    """The encoded JSON error body (for the ASGI middleware, which has no Response)."""
    return json.dumps(ApiError(status, code, message).body()).encode()


# ----------------------------------------------------------------- validation messages

_REWRITES = (
    ("Input should be greater than or equal to", "must be ≥"),
    ("Input should be less than or equal to", "must be ≤"),
    ("Input should be greater than", "must be >"),
    ("Input should be less than", "must be <"),
    ("Input should be a valid", "must be a valid"),
    ("Input should be", "must be"),
    ("String should have at most", "must have at most"),
    ("String should have at least", "must have at least"),
    ("String should match pattern", "must match the pattern"),
    ("List should have at most", "must have at most"),
)


def _show(value: Any) -> str:
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return "a list"
    text = json.dumps(value) if isinstance(value, str | int | float | bool | None) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _field_name(loc: Sequence[Any]) -> str:
    parts = list(loc)
    if parts and parts[0] in ("body", "query", "path", "header"):
        where = parts.pop(0)
        if not parts:
            return "body" if where == "body" else where
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else ("." if out else "") + str(p)
    return out or "request"


def field_message(err: Mapping[str, Any], allowed_fields: Sequence[str] = ()) -> str:
    """A readable message for one pydantic error: what is expected and what was sent."""
    kind = err.get("type", "")
    if kind == "extra_forbidden":
        allowed = ", ".join(allowed_fields)
        return f"unknown field; the allowed fields are {allowed}" if allowed else "unknown field"
    if kind == "missing":
        return "field required"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        fields = ", ".join(allowed_fields)
        return f"must be a JSON object ({fields}), got {_show(err.get('input'))}"
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    for old, new in _REWRITES:
        if msg.startswith(old):
            msg = new + msg[len(old) :]
            break
    if kind == "enum" or kind == "literal_error":
        return f"{msg}, got {_show(err.get('input'))}"
    if "input" in err:
        msg += f", got {_show(err.get('input'))}"
    return msg


_UNITS = (("_mm", "mm"), ("_us", "µs"), ("_s", "s"), ("_px", "px"))
_BOUND = re.compile(r"^(must be [≤≥<>]) (-?[0-9.e+]+)(,|$)")


def _with_unit(field: str, message: str) -> str:
    """``must be ≤ 100, got 150`` -> ``must be ≤ 100 mm, got 150`` for ``stop_mm``."""
    unit = next((u for suffix, u in _UNITS if field.endswith(suffix)), None)
    if unit is None:
        return message
    return _BOUND.sub(lambda m: f"{m[1]} {m[2]} {unit}{m[3]}", message, count=1)


def validation_fields(
    errors: Sequence[Mapping[str, Any]], allowed_fields: Sequence[str] = ()
) -> list[tuple[str, str]]:
    """``(field, message)`` for every pydantic error (locations ``('body', 'start_mm')``...)."""
    out = []
    for e in errors:
        field = _field_name(e.get("loc", ()))
        out.append((field, _with_unit(field, field_message(e, allowed_fields))))
    return out


def _json_problem(errors: Sequence[Mapping[str, Any]]) -> str | None:
    for e in errors:
        if e.get("type") == "json_invalid":
            ctx = e.get("ctx") or {}
            loc = list(e.get("loc", ()))
            where = f" at character {loc[-1]}" if loc and isinstance(loc[-1], int) else ""
            return f"{ctx.get('error', 'invalid JSON')}{where}"
    return None


# ----------------------------------------------------------------- handlers


def allowed_methods(request: Request) -> list[str]:
    """Every method some route accepts for the request's path (for ``Allow`` on 405)."""
    methods: set[str] = set()
    for method in ("GET", "POST", "PUT", "PATCH", "DELETE"):
        scope = dict(request.scope, method=method)
        for route in request.app.router.routes:
            if route.matches(scope)[0] is Match.FULL:
                methods.add(method)
                break
    if "GET" in methods:
        methods.add("HEAD")  # web.security.HeadAsGet
    return sorted(methods)


def storage_error(exc: StoreUnavailable) -> ApiError:
    """507 ``storage_full`` for a full disk, 503 ``store_unavailable`` otherwise."""
    if isinstance(exc, StorageFull):
        return ApiError(
            507,
            "storage_full",
            str(exc),
            context={"free_bytes": exc.free_bytes, "path": exc.path},
        )
    return ApiError(
        503,
        "store_unavailable",
        str(exc),
        context={"path": exc.path},
        headers={"Retry-After": "5"},
    )


def install_error_handlers(app: FastAPI, *, body_fields: Sequence[str] = ()) -> None:
    """Answer every error with :class:`ErrorBody` (validation, HTTP, ApiError, crashes)."""

    async def on_api_error(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ApiError)
        return exc.response()

    async def on_validation(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        errors = list(exc.errors())
        problem = _json_problem(errors)
        if problem is not None:
            return error_response(
                400,
                "malformed_json",
                f"the request body is not valid JSON ({problem}); send a JSON object such as "
                '{"start_mm": 0, "stop_mm": 99, "step_mm": 1}',
            )
        fields = validation_fields(errors, body_fields)
        summary = "; ".join(f"{f}: {m}" for f, m in fields)
        return ApiError(
            422, "invalid_request", f"the request is invalid: {summary}", fields=fields
        ).response()

    async def on_http(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StarletteHTTPException)
        status = exc.status_code
        if status == 404:
            message = f"no such resource: {request.url.path} (the API is under /api/v1)"
            code = "not_found"
        elif status == 405:
            allowed = allowed_methods(request)
            message = f"{request.method} is not allowed on {request.url.path}"
            if allowed:
                message += f" (use {', '.join(m for m in allowed if m != 'HEAD')})"
            code = "method_not_allowed"
            headers = dict(exc.headers or {})
            headers["Allow"] = ", ".join(allowed)
            return error_response(status, code, message, headers=headers)
        else:
            message = str(exc.detail)
            code = "http_error"
        return error_response(status, code, message, headers=exc.headers)

    async def on_store(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StoreUnavailable)
        log.warning("%s %s: %s", request.method, request.url.path, exc)
        return storage_error(exc).response()

    async def on_crash(request: Request, exc: Exception) -> JSONResponse:
        log.error("internal error on %s %s", request.method, request.url.path, exc_info=exc)
        return error_response(
            500,
            "internal_error",
            f"internal error ({type(exc).__name__}); the station log has the details",
        )

    app.add_exception_handler(ApiError, on_api_error)
    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(StoreUnavailable, on_store)
    app.add_exception_handler(Exception, on_crash)


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for the given error statuses (all :class:`ErrorBody`)."""
    descriptions = {
        400: "malformed JSON (not UTF-8, not JSON, nested too deeply)",
        401: "no API key (send X-API-Key)",
        403: "API key not accepted",
        404: "unknown job, frame or resource",
        409: "not allowed in the job's current state",
        413: "request body too large",
        415: "the body is not JSON",
        422: "invalid request: see fields",
        408: "the request head or body did not arrive in time",
        431: "request line and headers too large, or too many header fields",
        503: "a device is down, the job store cannot be written, or the station is stopping",
        507: "the disk holding the job database or the archives is full (storage_full)",
    }
    return {s: {"model": ErrorBody, "description": descriptions.get(s, "error")} for s in statuses}


__all__ = [
    "ApiError",
    "ErrorBody",
    "FieldError",
    "error_bytes",
    "error_response",
    "error_responses",
    "field_message",
    "install_error_handlers",
    "storage_error",
    "validation_fields",
]
