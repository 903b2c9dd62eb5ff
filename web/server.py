"""``lfcal serve``: run the HTTP service (uvicorn, one worker) over the station.

Usage::

    lfcal serve --config FILE [--host H] [--port P]
                [--emulator-speedup K] [--sim-frame-cache DIR] [--log-level LEVEL]

Host and port default to ``[server]`` (127.0.0.1:8000). ``--port 0`` picks a
free port. The station (job store, hardware worker) is started before the
server listens, so a database held by another station process is reported at
once (exit 3). The first line on stdout is ``lfcal serve: listening on URL``.
Ctrl-C or SIGTERM stop it: new jobs are refused (503), the running job stops at
its next step boundary (``interrupted``, resumable; waited for up to 30 s), then
every open event stream ends with the job's final ``state`` event, the server
stops and the devices are closed.

:func:`uvicorn_config` is the server's configuration (also for tests and
benchmarks): request-head limits and slow-client timeouts
(:mod:`web.http_limits`), at most :data:`MAX_CONNECTIONS` connections and
tasks, and access logs without credentials (:class:`RedactKeys`).

Exit codes: 0 stopped normally; 2 bad input (configuration, host, port in use);
3 another station process holds the job database.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import logging
import signal
import socket
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import uvicorn
from uvicorn.config import LOGGING_CONFIG

from web.http_limits import DEFAULT_LIMITS, HttpLimits, protocol_with
from web.security import redact_query

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_BUSY = 3


def build_parser() -> argparse.ArgumentParser:
    """The ``lfcal serve`` argument parser."""
    p = argparse.ArgumentParser(
        prog="lfcal serve",
        description="run the HTTP API and the operator page over the station",
    )
    p.add_argument("--config", required=True, help="station configuration (TOML)")
    p.add_argument("--host", help="address to listen on (default: [server] host, 127.0.0.1)")
    p.add_argument(
        "--port", type=int, help="TCP port (default: [server] port, 8000; 0: any free port)"
    )
    p.add_argument(
        "--emulator-speedup",
        type=float,
        default=1.0,
        help="simulation: emulated stages move this many times faster (default 1)",
    )
    p.add_argument(
        "--sim-frame-cache",
        type=Path,
        help="simulation: cache rendered frames in this directory (sets [camera] frame_cache)",
    )
    p.add_argument(
        "--analysis-workers",
        type=int,
        default=None,
        help="frame-analysis processes (default: one per core, at most 4)",
    )
    p.add_argument(
        "--log-level",
        default="info",
        choices=["critical", "error", "warning", "info", "debug"],
        help="server log level (default info)",
    )
    return p


MAX_CONNECTIONS = 500
"""Connections plus running requests beyond which uvicorn answers 503."""
STOP_JOBS_TIMEOUT_S = 30.0
"""How long a SIGTERM waits for the running job to reach its step boundary (s)."""


class RedactKeys(logging.Filter):
    """Replaces credential-like query parameters (``api_key``, ``key``, ``token`` ...)
    in log records by ``REDACTED`` (see :func:`web.security.redact_query`)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact_query(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact_query(a) if isinstance(a, str) else a for a in record.args)
        return True


def log_config() -> dict[str, Any]:
    """uvicorn's logging configuration with :class:`RedactKeys` on every handler."""
    config = copy.deepcopy(LOGGING_CONFIG)
    config["filters"] = {"redact_keys": {"()": RedactKeys}}
    for handler in config["handlers"].values():
        handler["filters"] = ["redact_keys"]
    return config


def uvicorn_config(
    app: Any,
    *,
    log_level: str = "info",
    limits: HttpLimits = DEFAULT_LIMITS,
    timeout_graceful_shutdown: int = 3,
) -> uvicorn.Config:
    """The server configuration of ``lfcal serve`` for ``app`` (see the module docstring)."""
    return uvicorn.Config(
        app,
        http=protocol_with(limits),
        log_level=log_level,
        log_config=log_config(),
        workers=1,
        timeout_graceful_shutdown=timeout_graceful_shutdown,
        timeout_keep_alive=5,
        limit_concurrency=MAX_CONNECTIONS,
        proxy_headers=False,
        server_header=False,
    )


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (IPv4 or IPv6); ``OSError`` if it cannot bind."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, kind, proto, _, address = infos[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
        sock.set_inheritable(True)
    except OSError:
        sock.close()
        raise
    return sock


class _Server(uvicorn.Server):
    """uvicorn's server that, on Ctrl-C/SIGTERM, first runs ``on_exit`` (stop the running
    job, end the event streams) in a thread while it keeps serving, then stops, and
    returns normally (uvicorn would re-raise the signal after shutting down). A second
    signal stops at once."""

    def __init__(self, config: uvicorn.Config, on_exit: Callable[[], None]) -> None:
        super().__init__(config)
        self._on_exit = on_exit
        self._exiting: threading.Thread | None = None

    def handle_exit(self, sig: int, frame: Any) -> None:
        if self._exiting is not None:
            super().handle_exit(sig, frame)
            return

        def graceful() -> None:
            try:
                self._on_exit()
            finally:
                super(_Server, self).handle_exit(sig, frame)

        self._exiting = threading.Thread(target=graceful, name="graceful-stop", daemon=True)
        self._exiting.start()

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        signals = (signal.SIGINT, signal.SIGTERM)
        originals = {sig: signal.signal(sig, self.handle_exit) for sig in signals}
        try:
            yield
        finally:
            for sig, handler in originals.items():
                signal.signal(sig, handler)


def serve_main(argv: Sequence[str] | None = None) -> int:
    """``lfcal serve``: run the server until Ctrl-C/SIGTERM; returns the exit code."""
    from station.config import load_config_or_report, with_frame_cache
    from station.config_checks import is_loopback
    from station.orchestrator import Orchestrator, StationBusy
    from station.store import StoreError
    from web.app import create_app

    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    err = sys.stderr
    config = load_config_or_report(args.config, "lfcal serve", err)
    if config is None:
        return EXIT_BAD_INPUT
    host = args.host or config.server.host
    port = config.server.port if args.port is None else args.port
    if not 0 <= port <= 65535:
        err.write(f"lfcal serve: --port must be 0..65535, got {port}\n")
        return EXIT_BAD_INPUT
    if not args.emulator_speedup > 0:
        err.write("lfcal serve: --emulator-speedup must be positive\n")
        return EXIT_BAD_INPUT
    if not is_loopback(host) and not config.server.api_keys:
        err.write(
            f"lfcal serve: --host {host} is not a loopback address: configure API keys first "
            "([server] api_keys or $LFCAL_API_KEYS)\n"
        )
        return EXIT_BAD_INPUT
    try:
        sock = bind_socket(host, port)
    except OSError as exc:
        err.write(f"lfcal serve: cannot listen on {host}:{port}: {exc.strerror or exc}\n")
        return EXIT_BAD_INPUT

    station = Orchestrator(
        with_frame_cache(config, args.sim_frame_cache),
        emulator_speedup=args.emulator_speedup,
        analysis_workers=args.analysis_workers,
    )
    try:
        station.start()
    except StationBusy as exc:
        sock.close()
        err.write(f"lfcal serve: {exc}\n")
        return EXIT_BUSY
    except StoreError as exc:
        sock.close()
        err.write(f"lfcal serve: {exc}\n")  # names the job database or the object store
        return EXIT_BAD_INPUT
    try:
        app = create_app(config, station=station)
        uv_config = uvicorn_config(app, log_level=args.log_level)

        def stop_gracefully() -> None:
            station.stop_jobs(STOP_JOBS_TIMEOUT_S)  # the job's final state reaches the streams
            bridge = app.state.events
            if bridge is not None:
                bridge.stop_streams()

        server = _Server(uv_config, stop_gracefully)
        bound_host, bound_port = sock.getsockname()[:2]
        shown = f"[{bound_host}]" if ":" in bound_host else bound_host
        url = f"http://{shown}:{bound_port}"
        print(f"lfcal serve: listening on {url}", flush=True)
        print(
            f"lfcal serve: operator page {url}/ , API {url}/api/v1 , docs {url}/api/docs",
            flush=True,
        )
        if not config.server.api_keys:
            err.write(
                "lfcal serve: no API keys configured: the API is read-only (set "
                "$LFCAL_API_KEYS or [server] api_keys to start runs)\n"
            )
        server.run(sockets=[sock])
    finally:
        sock.close()
        station.close()
    return EXIT_OK


def main() -> None:
    """``python -m web.server``."""
    sys.exit(serve_main())


if __name__ == "__main__":
    main()


__all__ = [
    "MAX_CONNECTIONS",
    "RedactKeys",
    "build_parser",
    "log_config",
    "serve_main",
    "uvicorn_config",
]
