"""A calibration over HTTP from start to finish (what the README's main command runs).

Usage::

    python -m web.demo --config config/simulated.toml [--start MM --stop MM --step MM]
                       [--port P] [--keep-serving] [--emulator-speedup K]
                       [--sim-frame-cache DIR]

It starts ``lfcal serve`` (:mod:`web.server`) on 127.0.0.1, submits a sweep with
``POST /api/v1/jobs``, polls ``GET /api/v1/jobs/{id}`` to the end (a progress
line on stderr), fetches ``GET /api/v1/jobs/{id}/result`` and prints a, b, Q, p
and the focus plane with their uncertainties. Without ``$LFCAL_API_KEYS`` it
makes a one-time API key for the server and this client. With
``--keep-serving`` the server stays up afterwards for the operator page (its URL
and the key are printed) until Ctrl-C; otherwise it is stopped.

Only the standard library talks HTTP here (``urllib``), on loopback.
Exit codes: 0 calibrated; 1 the job did not succeed; 2 bad input or the server
did not start.
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
import urllib.error
import urllib.request
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

FINAL = {"succeeded", "failed", "cancelled", "interrupted"}


def build_parser() -> argparse.ArgumentParser:
    """The demo's argument parser."""
    p = argparse.ArgumentParser(prog="python -m web.demo", description=__doc__.splitlines()[0])
    p.add_argument("--config", required=True, help="station configuration (TOML)")
    p.add_argument("--start", type=float, help="first rail position (mm)")
    p.add_argument("--stop", type=float, help="last rail position (mm)")
    p.add_argument("--step", type=float, help="rail step (mm)")
    p.add_argument("--port", type=int, default=0, help="server port (default: any free port)")
    p.add_argument("--keep-serving", action="store_true", help="leave the server running")
    p.add_argument("--emulator-speedup", type=float, default=1.0, help="simulation only")
    p.add_argument("--sim-frame-cache", type=Path, help="simulation only: frame cache directory")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many s")
    return p


class Client:
    """A tiny JSON client for the API (urllib, loopback)."""

    def __init__(self, url: str, key: str) -> None:
        self.url = url.rstrip("/")
        self.key = key

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """``method path`` with an optional JSON body; the decoded answer.

        Raises ``RuntimeError`` with the API's message on an error status.
        """
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method=method)
        request.add_header("Accept", "application/json")
        request.add_header("X-API-Key", self.key)
        if data is not None:
            request.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(request, timeout=60) as response:
                return json.loads(response.read())
        except urllib.error.HTTPError as exc:
            try:
                message = json.loads(exc.read())["message"]
            except (ValueError, KeyError):
                message = str(exc)
            raise RuntimeError(f"{method} {path}: {exc.code}: {message}") from None


def start_server(args: argparse.Namespace, key: str) -> tuple[subprocess.Popen[str], str]:
    """Start ``python -m web.server``; the process and its URL (RuntimeError if it fails)."""
    cmd = [
        sys.executable,
        "-m",
        "web.server",
        "--config",
        str(args.config),
        "--host",
        "127.0.0.1",
        "--port",
        str(args.port),
        "--emulator-speedup",
        str(args.emulator_speedup),
        "--log-level",
        "warning",
    ]
    if args.sim_frame_cache is not None:
        cmd += ["--sim-frame-cache", str(args.sim_frame_cache)]
    env = dict(os.environ, LFCAL_API_KEYS=key, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)  # stderr: ours
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the server exited with code {proc.returncode}")
        try:
            line = lines.get(timeout=0.5)
        except queue.Empty:
            continue
        if "listening on " in line:
            return proc, line.split("listening on ", 1)[1].strip()
    proc.terminate()
    raise RuntimeError("the server did not start within 120 s")


def stop_server(proc: subprocess.Popen[str]) -> None:
    """SIGTERM and wait (the running job stops at a step boundary)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def _fmt(value: Any, digits: int) -> str:
    return f"{value:.{digits}f}" if isinstance(value, int | float) else "n/a"


def result_table(result: dict[str, Any]) -> str:
    """a, b, Q, p and the focus plane with uncertainties, one per line."""
    u = result.get("uncertainty") or {}
    focus = result.get("focus") or {}
    rows = [
        ("a (mm)", result.get("a_mm"), u.get("a_mm"), 5),
        ("b (mm)", result.get("b_mm"), u.get("b_mm"), 5),
        ("Q = b/a", result.get("Q"), u.get("Q"), 6),
        ("p (px)", result.get("patch_size_px"), u.get("patch_size_px"), 4),
        ("focus plane u (mm)", focus.get("object_distance_mm"), focus.get("uncertainty_mm"), 3),
        ("focus plane rail (mm)", focus.get("rail_mm"), focus.get("uncertainty_mm"), 3),
    ]
    return "\n".join(
        f"  {name:22s} {_fmt(value, d):>12s} ± {_fmt(se, d)}" for name, value, se, d in rows
    )


def run_calibration(
    client: Client, request: dict[str, Any], timeout_s: float, out: TextIO, err: TextIO
) -> int:
    """Submit, poll to the end, print the result; the exit code."""
    job = client.call("POST", "/api/v1/jobs", request)
    job_id = job["id"]
    err.write(f"job {job_id}: {job['frames_total']} frames, archive {job['archive_dir']}\n")
    deadline = time.monotonic() + timeout_s
    while job["state"] not in FINAL:
        if time.monotonic() > deadline:
            err.write(f"\njob {job_id}: still {job['state']} after {timeout_s:g} s\n")
            return 1
        time.sleep(0.5)
        job = client.call("GET", f"/api/v1/jobs/{job_id}")
        eta = f", ETA {job['eta_s']:.0f} s" if job.get("eta_s") is not None else ""
        phase = f" ({job['phase']})" if job.get("phase") else ""
        err.write(
            f"\rjob {job_id}: {job['state']}{phase} {job['frames_done']}/{job['frames_total']} "
            f"frames{eta}          "
        )
        err.flush()
    err.write("\n")
    if job["state"] != "succeeded":
        err.write(f"job {job_id} {job['state']}: {job.get('last_error')}\n")
        return 1
    result = client.call("GET", f"/api/v1/jobs/{job_id}/result")
    out.write(f"job {job_id}: calibrated over HTTP\n{result_table(result)}\n")
    for warning in result.get("warnings", []):
        out.write(f"  warning: {warning}\n")
    return 0


def demo_main(argv: Sequence[str] | None = None) -> int:
    """Run the demo (see the module docstring); the exit code."""
    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    out, err = sys.stdout, sys.stderr
    keys = [k for k in os.environ.get("LFCAL_API_KEYS", "").replace(",", " ").split() if k]
    key = keys[0] if keys else secrets.token_urlsafe(24)
    request = {
        k: v
        for k, v in (("start_mm", args.start), ("stop_mm", args.stop), ("step_mm", args.step))
        if v is not None
    }
    try:
        proc, url = start_server(args, ",".join(keys) if keys else key)
    except RuntimeError as exc:
        err.write(f"web.demo: {exc}\n")
        return 2
    code = 2
    try:
        try:
            code = run_calibration(Client(url, key), request, args.timeout, out, err)
        except RuntimeError as exc:
            err.write(f"web.demo: {exc}\n")
            return 2
        if args.keep_serving:
            out.write(f"operator page: {url}/  (API key: {key})  -- Ctrl-C stops the server\n")
            out.flush()
            try:
                proc.wait()
            except KeyboardInterrupt:
                pass
        return code
    finally:
        stop_server(proc)


if __name__ == "__main__":
    sys.exit(demo_main())


__all__ = ["demo_main", "result_table", "run_calibration"]
