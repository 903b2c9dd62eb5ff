"""Shared helpers of the web tests (imported by the other ``test_web_*`` modules; no tests).

The simulated station here: preset ``rotated`` on a 2000×500 px sensor, wide
enough that both the standard and the reference corner stay in view, so La(u)
is measured; the emulated Zaber rail and XY stage on a real pty behind the real
driver; a 10-frame sweep 30..75 mm around the focus plane (rail 52.4 mm).
Rendered frames are cached in pytest's cache directory (shared with the
station tests, :mod:`drivers.sim.frame_cache`): the first run renders them (~2 s
each), later runs read them, and a sweep takes a few seconds.

Servers run for real: :class:`ServerProcess` is ``python -m web.server`` (what
``lfcal serve`` runs) on a free port of 127.0.0.1; :class:`InProcessServer` is
uvicorn in a thread for apps built in the test (other configurations).
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import httpx
import pytest
import uvicorn

REPO = Path(__file__).resolve().parents[1]
KEY = "web-test-key-0123456789abcdef"
"""The API key every test server accepts."""
OTHER_KEY = "not-the-key-fedcba9876543210"
FINAL = {"succeeded", "failed", "cancelled", "interrupted"}
SPEEDUP = 20.0

STATION_TOML = """
[camera]
backend = "simulated"
preset = "rotated"
width = {width}
height = {height}
timeout_s = 30.0
seed = 0

[rail]
driver = "{rail_driver}"
{rail_port}
microstep_um = 0.047625
max_speed_mm_s = 20.0
accel_mm_s2 = 100.0
min_mm = 0.0
max_mm = 100.0
position_tolerance_um = 2.0
settle_s = 0.0
zero_object_distance_mm = 380.0
direction = 1

[xy_stage]
driver = "{rail_driver}"
microstep_um = 0.09921875
max_speed_mm_s = 50.0
accel_mm_s2 = 200.0
position_tolerance_um = 2.0
x = {{ device = 2, axis = 1, min_mm = 0.0, max_mm = 300.0 }}
y = {{ device = 2, axis = 2, min_mm = 0.0, max_mm = 300.0 }}
alignment = {{ x_mm = 100.0, y_mm = 100.0 }}
white = {{ x_mm = 300.0, y_mm = 100.0 }}

[optics]
main_focal_mm = 50.0
mla_focal_mm = 2.0
mla_pitch_mm = 0.2
pixel_pitch_mm = 0.0025
designed_b_mm = 2.45

[sweep]
start_mm = 30.0
stop_mm = 75.0
step_mm = 5.0
max_frames = 200

[storage]
data_dir = "data"
database = "data/lfcal.sqlite3"

[server]
host = "127.0.0.1"
port = 8000
read_only_requires_key = {read_key}
cors_origins = [{cors}]
max_body_bytes = {max_body}
"""

T = TypeVar("T")


def write_config(
    directory: Path,
    *,
    width: int = 2000,
    height: int = 500,
    read_only_requires_key: bool = False,
    cors_origins: tuple[str, ...] = (),
    max_body_bytes: int = 65536,
    rail_port: str | None = None,
) -> Path:
    """A station configuration in ``directory`` (storage under ``directory/data``).

    ``rail_port``: a real Zaber port (``socket://...``) instead of the emulated chain.
    """
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "station.toml"
    path.write_text(
        STATION_TOML.format(
            width=width,
            height=height,
            rail_driver="zaber" if rail_port else "emulated",
            rail_port=f'port = "{rail_port}"' if rail_port else "",
            read_key="true" if read_only_requires_key else "false",
            cors=", ".join(f'"{o}"' for o in cors_origins),
            max_body=max_body_bytes,
        ),
        encoding="utf-8",
    )
    return path


def frame_cache(pytestconfig: pytest.Config) -> Path:
    """The rendered-frame cache shared with the station tests (and later runs)."""
    return Path(pytestconfig.cache.mkdir("lfcal-station-frames"))


def closed_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on (just released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(
    probe: Callable[[], T | None], timeout_s: float, what: str, interval_s: float = 0.05
) -> T:
    """Call ``probe`` until it returns something truthy; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last: T | None = None
    while time.monotonic() < deadline:
        last = probe()
        if last:
            return last
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what} (last: {last!r})")


def keyed(key: str = KEY) -> dict[str, str]:
    """Headers with the API key."""
    return {"X-API-Key": key}


def wait_for_state(
    client: httpx.Client, job_id: int, states: set[str], timeout_s: float = 120.0
) -> dict[str, Any]:
    """Poll ``GET /jobs/{id}`` until the job is in one of ``states``; its status."""

    def probe() -> dict[str, Any] | None:
        job = client.get(f"/api/v1/jobs/{job_id}").json()
        return job if job["state"] in states else None

    return wait_until(probe, timeout_s, f"job {job_id} to reach {sorted(states)}", 0.1)


class ServerProcess:
    """``python -m web.server --config FILE --port 0 ...`` on 127.0.0.1 (stop it!).

    stdout and stderr go to ``log_path``; :attr:`url` is read from the
    ``listening on`` line.
    """

    def __init__(
        self,
        config: Path,
        *,
        cache: Path | None,
        keys: str = KEY,
        analysis_workers: int | None = 1,
        start_timeout_s: float = 60.0,
        wrap: list[str] | None = None,
    ) -> None:
        self.log_path = config.with_name("server.log")
        if self.log_path.exists():  # a restart on the same configuration: keep both logs
            self.log_path = config.with_name(f"server-{time.time_ns()}.log")
        args = list(wrap or []) + [
            sys.executable,
            "-m",
            "web.server",
            "--config",
            str(config),
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--emulator-speedup",
            str(SPEEDUP),
        ]
        if cache is not None:
            args += ["--sim-frame-cache", str(cache)]
        if analysis_workers is not None:
            args += ["--analysis-workers", str(analysis_workers)]
        env = dict(os.environ, LFCAL_API_KEYS=keys, PYTHONUNBUFFERED="1")
        self._log = self.log_path.open("w", encoding="utf-8")
        self.proc = subprocess.Popen(
            args,
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
        )
        lines: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._pump, args=(lines,), daemon=True).start()
        deadline = time.monotonic() + start_timeout_s
        self.url = ""
        while not self.url:
            left = deadline - time.monotonic()
            if left <= 0 or self.proc.poll() is not None:
                self.stop()
                raise AssertionError(f"the server did not start: {self.log()}")
            try:
                line = lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if "listening on " in line:
                self.url = line.split("listening on ", 1)[1].strip()
        self.client = httpx.Client(base_url=self.url, timeout=30.0)
        wait_until(self._healthy, start_timeout_s, "the server's devices to be ready", 0.1)

    def _pump(self, lines: queue.Queue[str]) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._log.write(line)
            self._log.flush()
            lines.put(line)

    def _healthy(self) -> bool:
        try:
            return self.client.get("/api/v1/healthz").json()["devices"] != "opening"
        except httpx.HTTPError:
            return False

    def log(self) -> str:
        """Everything the server printed so far."""
        self._log.flush()
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def stop(self, timeout_s: float = 60.0) -> int:
        """SIGTERM, then wait (SIGKILL after ``timeout_s``); the exit code."""
        if hasattr(self, "client"):
            self.client.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._log.close()
        return int(self.proc.returncode)


class InProcessServer:
    """uvicorn serving ``app`` from a thread on a free port of 127.0.0.1 (stop it!)."""

    def __init__(self, app: Any, start_timeout_s: float = 30.0, limits: Any = None) -> None:
        from web.http_limits import DEFAULT_LIMITS
        from web.server import uvicorn_config

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.port = int(self.sock.getsockname()[1])
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn_config(
            app,
            log_level="warning",
            limits=limits or DEFAULT_LIMITS,
            timeout_graceful_shutdown=2,
        )
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(
            target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True
        )
        self.thread.start()
        wait_until(lambda: self.server.started, start_timeout_s, "uvicorn to start")
        self.client = httpx.Client(base_url=self.url, timeout=30.0)

    def stop(self) -> None:
        self.client.close()
        self.server.should_exit = True
        self.thread.join(30)
        self.sock.close()


def read_events(response: httpx.Response) -> list[tuple[str | None, str, dict[str, Any]]]:
    """Parse a whole SSE body into ``(id, event, data)`` triples."""
    import json

    out = []
    for block in response.text.split("\n\n"):
        ev_id, ev_type, data = None, "message", []
        for line in block.splitlines():
            if line.startswith(":") or not line:
                continue
            field, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if field == "id":
                ev_id = value
            elif field == "event":
                ev_type = value
            elif field == "data":
                data.append(value)
        if data:
            out.append((ev_id, ev_type, json.loads("\n".join(data))))
    return out
