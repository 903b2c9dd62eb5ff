"""The FastAPI application: REST under ``/api/v1``, SSE, and the operator page at ``/``.

:func:`create_app` builds the app over a station (:class:`station.orchestrator.Orchestrator`).
Routes stay thin: the station validates, queues and runs the sweeps; the app
maps its answers to HTTP (:mod:`web.station_api`), checks API keys and body sizes
(:mod:`web.security`), and serves images, the archive and the events.

Middleware, outermost first: :class:`web.security.HeadAsGet` (``HEAD`` on every
``GET`` route), CORS (only when ``server.cors_origins`` is set),
:class:`web.security.ApiGuard` (no key in the URL, API keys, body size, media
type, JSON), then :class:`web.fast_status.FastStatus` (the polled status route
without the router). Request heads are limited before any of them, in the HTTP
protocol (:mod:`web.http_limits`).

The API documentation (``/api/docs``, Swagger UI) is served from the
``swagger-ui-bundle-v2`` distribution installed with the package: it works on a
lab network without internet access.
"""

from __future__ import annotations

import gc
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import swagger_ui_bundle
from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from station.config import StationConfig
from station.orchestrator import Orchestrator
from web.errors import install_error_handlers
from web.fast_status import FastStatus, StatusBodies
from web.media import BytesCache
from web.metrics import StationMetrics, build_metrics_router
from web.routes_jobs import build_jobs_router
from web.routes_lab import build_lab_router
from web.routes_media import build_media_router
from web.routes_system import build_system_router
from web.schemas import SWEEP_FIELDS, sweep_body_model
from web.security import API_KEY_HEADER, ApiGuard, ApiKeys, HeadAsGet
from web.sse import EventBridge, build_events_router

STATIC_DIR = Path(__file__).with_name("static")
SWAGGER_DIR = Path(str(swagger_ui_bundle.swagger_ui_path))
"""Swagger UI's files, from the installed ``swagger-ui-bundle-v2`` distribution."""
DOCS_STATIC = "/api/docs/static"

DESCRIPTION = """\
Calibration station for focused plenoptic cameras: start a calibration sweep,
follow it, and fetch the result (a, b, Q, p, the focus plane), plots, rendered
images and the sweep archive.

Mutating requests need an API key in the `X-API-Key` header (401 without one,
403 for a key the server does not know). Every error is one JSON shape:
`{"status", "code", "message", "fields": [{"field", "message"}], "context"}`.
"""


def create_app(
    config: StationConfig,
    *,
    station: Orchestrator | None = None,
    body_timeout_s: float = 10.0,
    **station_options: Any,
) -> FastAPI:
    """The HTTP app over ``station``.

    Args:
        config: the station configuration (``[server]``: API keys, CORS, body limit).
        station: a started orchestrator; the caller keeps ownership (starts and
            closes it). None: the app makes one from ``config`` with
            ``station_options`` (see :class:`~station.orchestrator.Orchestrator`),
            starts it at startup and closes it at shutdown.
        body_timeout_s: a request body whose next chunk takes longer is refused (408).
    """
    server = config.server
    read_key = server.read_only_requires_key
    owned = station is None
    orchestrator = station if station is not None else Orchestrator(config, **station_options)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if owned:
            orchestrator.start()
        bridge = EventBridge(orchestrator)
        app.state.events = bridge
        # everything built so far (modules, the app, the station) lives as long as
        # the server: out of the collector's sight, a full collection scans only
        # what requests and jobs allocate later (~10 ms instead of ~100 ms stalls
        # of the event loop, see bench/bench_web.py)
        gc.freeze()
        try:
            yield
        finally:
            bridge.close()
            if owned:
                orchestrator.close()

    app = FastAPI(
        title="lfcal-station",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
        openapi_url="/api/v1/openapi.json",
        # no OpenTelemetry here (metrics: GET /metrics): FastAPI's native telemetry
        # would look up three global providers, and the environment, on every
        # request -- about 8 % of the event loop's time under 50 pollers
        telemetry={"tracing": False, "metrics": False, "logs": False},
    )
    app.state.config = config
    app.state.station = orchestrator
    app.state.api_keys = ApiKeys(server.api_keys)
    app.state.media_cache = BytesCache()
    app.state.status_bodies = StatusBodies(orchestrator)
    # the bridge also exists before startup (tests that skip the lifespan)
    app.state.events = None

    install_error_handlers(app, body_fields=SWEEP_FIELDS)
    app.include_router(build_jobs_router(sweep_body_model(config), read_key=read_key))
    app.include_router(build_events_router(read_key=read_key))
    app.include_router(build_media_router(read_key=read_key))
    app.include_router(build_system_router(read_key=read_key))
    app.include_router(build_lab_router(read_key=read_key))
    app.state.metrics = StationMetrics(orchestrator)
    app.include_router(build_metrics_router(app.state.metrics, read_key=read_key))

    @app.get("/", include_in_schema=False)
    def operator_page() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})

    @app.get("/api", include_in_schema=False)
    def api_root() -> RedirectResponse:
        return RedirectResponse("/api/docs")

    @app.get("/api/docs", include_in_schema=False)
    def api_docs() -> HTMLResponse:
        """Swagger UI from this server only (no CDN, no validator badge)."""
        return get_swagger_ui_html(
            openapi_url="/api/v1/openapi.json",
            title="lfcal-station API",
            swagger_js_url=f"{DOCS_STATIC}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_STATIC}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_STATIC}/favicon-32x32.png",
            swagger_ui_parameters={"validatorUrl": None},
        )

    app.mount(DOCS_STATIC, StaticFiles(directory=SWAGGER_DIR), name="api-docs-static")
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    # innermost: every request has passed the guard (and CORS, HEAD) before it
    app.add_middleware(FastStatus, bodies=app.state.status_bodies)
    app.add_middleware(
        ApiGuard,
        keys=app.state.api_keys,
        max_body_bytes=server.max_body_bytes,
        read_only_requires_key=read_key,
        body_timeout_s=body_timeout_s,
    )
    if server.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=list(server.cors_origins),
            allow_methods=["GET", "POST"],
            allow_headers=[API_KEY_HEADER, "Content-Type", "Idempotency-Key", "Last-Event-ID"],
            expose_headers=["Location"],
        )
    app.add_middleware(HeadAsGet)
    return app


__all__ = ["create_app"]
