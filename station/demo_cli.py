"""``lfcal demo``: start the HTTP station on the simulated devices (``lfcal serve`` in a
child process, on 127.0.0.1 only), run a calibration over its HTTP API, print it.

The demo works under ``--out`` (default ``out/demo``): a copy of the configuration whose
database and archives live there (``station.toml``, ``data/``), the server's log
(``server.log``) and the result (``result.json``). The server listens on a free port
(or ``--port``) and takes one API key made for the run. Times are seconds; the server
must listen and answer ``/api/v1/healthz`` within 120 s of starting.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import secrets
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from station.cli_common import (
    EXIT_CALIBRATION_FAILED,
    EXIT_OK,
    UserError,
    progress_bar,
    write_json,
)
from station.summary_table import summary_table


def _http(
    method: str,
    url: str,
    *,
    key: str | None = None,
    body: dict[str, Any] | None = None,
    timeout_s: float = 10.0,
) -> tuple[int, dict[str, Any], dict[str, str]]:
    """A small JSON HTTP client on the standard library (the demo talks to 127.0.0.1 only)."""
    import urllib.error
    import urllib.request

    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method)
    req.add_header("Accept", "application/json")
    if data is not None:
        req.add_header("Content-Type", "application/json")
    if key:
        req.add_header("X-API-Key", key)
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:  # noqa: S310 (loopback)
            return resp.status, json.loads(resp.read() or b"{}"), dict(resp.headers)
    except urllib.error.HTTPError as exc:
        payload = exc.read()
        try:
            parsed = json.loads(payload or b"{}")
        except ValueError:
            parsed = {"detail": payload.decode(errors="replace")}
        return exc.code, parsed, dict(exc.headers)


def _demo_config(config_path: Path, out: Path) -> Path:
    """A copy of the station configuration whose database and archives live under ``out``."""
    import re

    text = config_path.read_text(encoding="utf-8")
    text = re.sub(r"(?m)^data_dir\s*=.*$", f'data_dir = "{(out / "data").resolve()}"', text)
    text = re.sub(
        r"(?m)^database\s*=.*$", f'database = "{(out / "data" / "lfcal.sqlite3").resolve()}"', text
    )
    out.mkdir(parents=True, exist_ok=True)
    copy = out / "station.toml"
    copy.write_text(text, encoding="utf-8")
    # relative paths (a .cti, a white image) keep pointing next to the original
    return copy


def _preset_truth(config_path: Path) -> dict[str, Any] | None:
    """Ground truth of the simulated station's preset (None for real hardware)."""
    from calibration.presets import get_preset
    from station.config import load_config

    cfg = load_config(config_path)
    if cfg.camera.backend != "simulated":
        return None
    o = get_preset(cfg.camera.preset).camera.optics
    u0 = o.u0
    return {
        "a_mm": o.a_f,
        "b_mm": o.b,
        "Q": o.Q_focus,
        "patch_size_px": float(o.patch_px(u0)),
        "focus": {
            "object_distance_mm": u0,
            "rail_mm": (u0 - cfg.rail.zero_object_distance_mm) / cfg.rail.direction,
        },
    }


# ------------------------------------------------------------------------------ server


def _start_server(
    args: argparse.Namespace, demo_config: Path, key: str, log: IO[str]
) -> subprocess.Popen[str]:
    """``lfcal serve`` on 127.0.0.1 for ``demo_config`` in a child process that takes
    ``key`` as its one API key (stderr to ``log`` unless ``--verbose``)."""
    env = dict(os.environ, LFCAL_API_KEYS=key)
    return subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from station.cli import main; sys.exit(main())",
            "serve",
            "--config",
            str(demo_config),
            "--host",
            "127.0.0.1",
            "--port",
            str(args.port or 0),
            "--emulator-speedup",
            str(args.emulator_speedup),
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=None if args.verbose else log,
        text=True,
    )


def _pump_stdout(server: subprocess.Popen[str], verbose: bool) -> queue.Queue[str]:
    """The server's stdout lines, read by a daemon thread (echoed when ``verbose``)."""
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:  # the server's stdout: its first line says where it listens
        assert server.stdout is not None
        for line in server.stdout:
            lines.put(line)
            if verbose:
                print(line, end="")

    threading.Thread(target=pump, daemon=True).start()
    return lines


def _wait_until_listening(
    server: subprocess.Popen[str], lines: queue.Queue[str], log: IO[str], out: Path, deadline: float
) -> str:
    """The server's base URL from its ``listening on`` line (``UserError`` when it exits
    first, with the end of ``out/server.log``, or when ``deadline`` passes)."""
    base = ""
    while not base:
        try:
            line = lines.get(timeout=0.5)
        except queue.Empty:
            line = ""
        if "listening on" in line:
            base = line.split("listening on", 1)[1].strip().rstrip("/")
        elif server.poll() is not None:
            log.flush()
            detail = (out / "server.log").read_text()[-2000:]
            raise UserError(f"the server exited with code {server.returncode}: {detail}")
        elif time.monotonic() > deadline:
            raise UserError("the server did not start listening within 120 s")
    return base


def _wait_until_healthy(base: str, deadline: float) -> None:
    """Poll ``/api/v1/healthz`` every 0.25 s until it answers 200 (``UserError`` at
    ``deadline``, a ``time.monotonic()`` time)."""
    while True:
        try:
            status, _, _ = _http("GET", f"{base}/api/v1/healthz", timeout_s=2.0)
            if status == 200:
                break
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise UserError("the server did not answer /api/v1/healthz within 120 s")
        time.sleep(0.25)


def _stop_server(server: subprocess.Popen[str]) -> None:
    """Stop the server as Ctrl-C would (SIGINT), killing it after 30 s."""
    if server.poll() is None:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()


# --------------------------------------------------------------------------------- job


def _submit_job(base: str, key: str, frames: int | None) -> str:
    """POST a calibration job (``frames`` over the rail's 0..99 mm, or the configuration's
    sweep when None) and return its URL."""
    body: dict[str, Any] = {}
    if frames:
        body = {"start_mm": 0.0, "stop_mm": 99.0, "step_mm": 99.0 / (frames - 1)}
    status, job, headers = _http("POST", f"{base}/api/v1/jobs", key=key, body=body)
    if status != 202:
        raise UserError(f"POST /api/v1/jobs answered {status}: {job}")
    location = headers.get("Location") or headers.get("location") or f"/api/v1/jobs/{job['id']}"
    return location if location.startswith("http") else base + location


def _follow_job(url: str) -> dict[str, Any]:
    """Poll the job every second, drawing its frames on a progress bar, until it ends."""
    report = progress_bar("sweep")
    shown = -1
    while True:
        status, job, _ = _http("GET", url)
        if status != 200:
            raise UserError(f"GET {url} answered {status}: {job}")
        done = int(job.get("frames_done") or 0)
        if job.get("frames_total") and done != shown:
            report(done, int(job["frames_total"]))
            shown = done
        if job["state"] in ("succeeded", "failed", "cancelled", "interrupted"):
            return job
        time.sleep(1.0)


def cmd_demo(args: argparse.Namespace) -> int:
    """Start the HTTP station on the simulated devices, run a calibration over HTTP, print it."""
    from station.config import ConfigError, load_config

    config_path = Path(args.config)
    try:
        load_config(config_path)
    except ConfigError as exc:
        raise UserError(f"{config_path}: " + "; ".join(exc.format_problems())) from None
    out = Path(args.out)
    demo_config = _demo_config(config_path, out)
    key = secrets.token_hex(16)
    log = (out / "server.log").open("w")
    server = _start_server(args, demo_config, key, log)
    lines = _pump_stdout(server, args.verbose)
    try:
        deadline = time.monotonic() + 120.0
        base = _wait_until_listening(server, lines, log, out, deadline)
        _wait_until_healthy(base, deadline)
        print(f"server up at {base}/ (operator page); starting a calibration over HTTP")
        url = _submit_job(base, key, args.frames)
        job = _follow_job(url)
        if job["state"] != "succeeded":
            print(f"the job ended {job['state']}: {job.get('last_error')}", file=sys.stderr)
            return EXIT_CALIBRATION_FAILED
        status, result, _ = _http("GET", f"{url}/result")
        if status != 200:
            raise UserError(f"GET {url}/result answered {status}: {result}")
        print(summary_table(result, _preset_truth(config_path)))
        write_json(out / "result.json", result)
        print(f"result written to {out / 'result.json'}; archive in {job.get('archive_dir')}")
        if args.keep_serving:
            print(f"operator page: {base}/  (API key for this run: {key}); Ctrl-C stops the server")
            server.wait()
        return EXIT_OK
    finally:
        _stop_server(server)
        log.close()


# ------------------------------------------------------------------------------ parser


def add_demo_command(sub: Any) -> None:
    """Add ``demo`` to the ``lfcal`` sub-command parser."""
    p = sub.add_parser(
        "demo",
        help="start the HTTP station on the simulated devices, calibrate over HTTP, print it",
    )
    p.add_argument("--config", default="config/simulated.toml", help="station configuration")
    p.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames over the rail's 0..99 mm (default: the configuration's sweep)",
    )
    p.add_argument("--port", type=int, default=None, help="port (default: a free one)")
    p.add_argument(
        "--emulator-speedup",
        type=float,
        default=1.0,
        help="run the emulated stages K times faster than real time",
    )
    p.add_argument(
        "--keep-serving",
        action="store_true",
        help="leave the server (and the operator page) up until Ctrl-C",
    )
    p.add_argument("--verbose", action="store_true", help="show the server's log")
    p.set_defaults(func=cmd_demo)


__all__ = ["add_demo_command", "cmd_demo"]
