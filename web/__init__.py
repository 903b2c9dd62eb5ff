"""The HTTP service of the station: REST API, Server-Sent Events and the operator page.

- :mod:`web.app` -- :func:`~web.app.create_app`, the FastAPI app over a station
- :mod:`web.server` -- ``lfcal serve`` (:func:`~web.server.serve_main`), uvicorn
- :mod:`web.routes_jobs`, :mod:`web.routes_media`, :mod:`web.routes_system`,
  :mod:`web.sse` -- the routes under ``/api/v1``
- :mod:`web.station_api` -- the station's errors and statuses as HTTP answers
- :mod:`web.security` -- API keys, body-size limit; :mod:`web.errors` -- one error shape
- :mod:`web.media` -- previews, rendering, the archive zip
- ``web/static/`` -- the operator page (plain HTML, CSS, JavaScript)
"""
