"""``lfcal serve``: run the HTTP service (uvicorn, one worker) over the station.

Usage::

    lfcal serve --config FILE [--host H] [--port P]
                [--emulator-speedup K] [--sim-frame-cache DIR] [--log-level LEVEL]

Host and port default to ``[server]`` (127.0.0.1:8000). ``--port 0`` picks a
free port. The station (job store, hardware worker) is started before the
server listens, so a database held by another station process is reported at
once (exit 3). The first line on stdout is ``lfcal serve: listening on URL``.
Ctrl-C or SIGTERM stop it: open event streams end, the running job stops at its
next step boundary (``interrupted``, resumable), the devices are closed.

Exit codes: 0 stopped normally; 2 bad input (configuration, host, port in use);
3 another station process holds the job database.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import socket
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import uvicorn

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
        help="simulation: cache rendered frames in this directory",
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


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


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
    """uvicorn's server that ends the event streams on Ctrl-C/SIGTERM and returns normally
    (uvicorn would re-raise the signal after shutting down)."""

    def __init__(self, config: uvicorn.Config, on_exit: Callable[[], None]) -> None:
        super().__init__(config)
        self._on_exit = on_exit

    def handle_exit(self, sig: int, frame: Any) -> None:
        self._on_exit()
        super().handle_exit(sig, frame)

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
    from station.config import ConfigError, load_config
    from station.orchestrator import Orchestrator, StationBusy
    from web.app import create_app

    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    err = sys.stderr
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        err.write(f"lfcal serve: {args.config}: invalid configuration\n")
        for line in exc.format_problems():
            err.write(f"  {line}\n")
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
        config,
        emulator_speedup=args.emulator_speedup,
        sim_frame_cache=args.sim_frame_cache,
        analysis_workers=args.analysis_workers,
    )
    try:
        station.start()
    except StationBusy as exc:
        sock.close()
        err.write(f"lfcal serve: {exc}\n")
        return EXIT_BUSY
    try:
        app = create_app(config, station=station)
        uv_config = uvicorn.Config(
            app,
            log_level=args.log_level,
            workers=1,
            timeout_graceful_shutdown=3,
            proxy_headers=False,
            server_header=False,
        )

        def stop_streams() -> None:
            bridge = app.state.events
            if bridge is not None:
                bridge.stop_streams()

        server = _Server(uv_config, stop_streams)
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


__all__ = ["build_parser", "serve_main"]
