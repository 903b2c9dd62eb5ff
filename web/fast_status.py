"""``GET /api/v1/jobs/{id}``, the route clients poll, answered in a few tens of microseconds.

Operators' pages and scripts poll a job's status several times a second (the
benchmark: 50 pollers at 10 Hz during a sweep, ``bench/bench_web.py``), and the
answers are produced on the server's one event loop, which shares 2 cores with
the hardware worker, the archive writer, the analysis processes and the
clients. Measured on the development machine, a poll cost the event loop about
0.5 ms of CPU: a SQLite read of the job's row, building and serialising the JSON,
and mostly the framework's routing (route matching, dependency resolution,
exception wrappers). At 500 polls a second that is a quarter of a core, so on a
busy machine the loop fell behind and the status tail reached hundreds of ms.

Two pieces make a poll cheap:

- :class:`StatusBodies`: the JSON body of each job's status, serialised once per
  change of the status (:meth:`station.orchestrator.Orchestrator.status` reads
  memory only) and reused while it is unchanged; the routed handler uses it too,
  so both paths answer the same bytes.
- :class:`FastStatus`: an ASGI middleware, the innermost one (inside
  :class:`web.security.HeadAsGet`, CORS and :class:`web.security.ApiGuard`, which
  still see and check every request), that answers the plain successful case of
  ``GET /api/v1/jobs/{id}`` itself and hands everything else to the router: a
  query string, a request body, an unknown job or any error of the station
  (404, 503 ... come from the routed handler as before).
"""

from __future__ import annotations

import json
import re
from collections import OrderedDict
from typing import Any

from starlette.types import ASGIApp, Receive, Scope, Send

from station.orchestrator import JobStatus, Orchestrator
from web.schemas import MAX_ID
from web.station_api import API, job_dict

STATUS_PATH = re.compile(rf"^{re.escape(API)}/jobs/([1-9][0-9]{{0,17}})$")
"""The status route's path; the group is the job id."""

MAX_CACHED_BODIES = 256
"""Jobs whose status body is kept (least recently changed dropped first)."""


def render_json(content: Any) -> bytes:
    """JSON bytes exactly as :class:`fastapi.responses.JSONResponse` renders them."""
    return json.dumps(
        content, ensure_ascii=False, allow_nan=False, indent=None, separators=(",", ":")
    ).encode("utf-8")


class StatusBodies:
    """The serialised status of each polled job, rebuilt only when the status changes.

    Used from the event loop only (no lock). Raises what
    :meth:`station.orchestrator.Orchestrator.status` raises.
    """

    def __init__(self, station: Orchestrator, max_jobs: int = MAX_CACHED_BODIES) -> None:
        self.station = station
        self._max = max(1, int(max_jobs))
        self._bodies: OrderedDict[int, tuple[JobStatus, bytes]] = OrderedDict()

    def body(self, job_id: int) -> bytes:
        """The JSON body of ``GET /jobs/{job_id}`` (the :class:`web.schemas.JobOut` shape)."""
        status = self.station.status(job_id)
        cached = self._bodies.get(job_id)
        if cached is not None and cached[0] == status:
            return cached[1]
        body = render_json(job_dict(status))
        self._bodies[job_id] = (status, body)
        self._bodies.move_to_end(job_id)
        while len(self._bodies) > self._max:
            self._bodies.popitem(last=False)
        return body


def _has_body(scope: Scope) -> bool:
    for name, value in scope["headers"]:
        if name == b"transfer-encoding" or (name == b"content-length" and value.strip() != b"0"):
            return True
    return False


class FastStatus:
    """ASGI middleware: the successful ``GET /api/v1/jobs/{id}`` without the router
    (see the module docstring).

    Args:
        app: the wrapped application (the router side).
        bodies: the status bodies (shared with the routed handler).
    """

    def __init__(self, app: ASGIApp, *, bodies: StatusBodies) -> None:
        self.app = app
        self.bodies = bodies

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        body = self._answer(scope) if scope["type"] == "http" else None
        if body is None:
            await self.app(scope, receive, send)
            return
        await send(
            {
                "type": "http.response.start",
                "status": 200,
                "headers": [
                    (b"content-length", str(len(body)).encode("latin-1")),
                    (b"content-type", b"application/json"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})

    def _answer(self, scope: Scope) -> bytes | None:
        """The body to answer with, or None: the router answers."""
        if scope["method"] != "GET" or scope.get("query_string"):
            return None
        match = STATUS_PATH.match(scope["path"])
        if match is None or _has_body(scope):
            return None
        job_id = int(match[1])
        if job_id > MAX_ID:
            return None
        try:
            return self.bodies.body(job_id)
        except Exception:  # noqa: BLE001 - unknown job, store down ...: the router's answer
            return None


__all__ = ["STATUS_PATH", "FastStatus", "StatusBodies", "render_json"]
