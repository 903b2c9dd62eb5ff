"""The HTTP service under load: 50 status pollers and 20 event streams during a sweep.

The station of ``config/simulated.toml`` (preset ``paper``, 3000×1000 px window,
emulated Zaber stages on a pty at real speed, analysis worker processes) runs
behind the real app (:func:`web.app.create_app`) in uvicorn on 127.0.0.1, in one
process, as ``lfcal serve`` runs it. Two identical sweeps (30 steps of 1 mm,
calibrated at the end):

1. **idle**: nobody polls;
2. **loaded**: a separate process runs 50 pollers (asyncio, one keep-alive
   connection each) that each ask ``GET /api/v1/jobs/{id}`` every 100 ms (10 Hz)
   for as long as the sweep runs, and keeps 20 event streams
   (``GET /api/v1/jobs/{id}/events``) open, each read to the job's final
   ``state`` event (bounded: at most 120 s and 100 000 requests), over loopback
   only. The sweep calibrates, so the streaming analysis runs in its worker
   processes all along.

Rows: status latency p50 / p99 (target p99 ≤ 50 ms), requests and errors (target
0; a stream that ends without the final state counts as an error), and the station's own overhead per sweep step (the hardware thread's time
minus move, settle and grab, :class:`station.run_control.StepTiming`) idle and
loaded: "unchanged" is the loaded median within 5 ms of the idle one.

**What the machine was doing.** The latency tail follows the CPU time the server
gets, so the table also says how contended the CPUs were during the polled sweep:
the CPU steal of a virtual machine (time the hypervisor gave this VM's CPUs to
others), the Linux CPU pressure (PSI ``some``: the share of the time at least one
runnable task waited for a CPU), the load average, the share of the sweep the
server's event-loop thread was runnable but waiting for a CPU, and the CPU time
of the event loop and of the pollers. A machine shared with other work (other
sessions' builds and tests) shows high pressure and a long event-loop wait, and
then the tail says more about the machine than about the station.

**Isolation** (command line only): ``--pollers-nice N`` runs the pollers N nice
levels below the server, ``--pollers-cpu K`` pins them to CPU K; ``--isolate``
runs the whole benchmark in a session of its own whose scheduler weight is that
of nice -10 (Linux autogroups: the CPUs are shared between sessions first, and
nice values only count inside a session, so ``nice`` alone cannot shield the
benchmark from another session's load; it needs the permission to lower a nice
value, else it runs unisolated and says so). Inside the benchmark's session the
analysis workers keep their lower priority.

Frames are cached under ``out/bench/station-frames`` (shared with
``bench_station``); a cold cache renders each frame once (~4 s each).

Run: ``python -m bench.bench_web [--frames N] [--pollers N] [--streams N]
[--pollers-nice N] [--pollers-cpu K] [--isolate]``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
CACHE = ROOT / "out" / "bench" / "station-frames"
WIDTH, HEIGHT = 3000, 1000
POLLERS = 50
STREAMS = 20
INTERVAL_S = 0.1
MAX_POLL_S = 120.0
MAX_REQUESTS = 100_000
TARGET_P99_MS = 50.0
TARGET_OVERHEAD_CHANGE_MS = 5.0
FINAL = {"succeeded", "failed", "cancelled", "interrupted"}
ISOLATE_NICE = -10
"""Scheduler weight (as a nice value) of the benchmark's own session with ``--isolate``."""
_ISOLATED_ENV = "LFCAL_BENCH_WEB_ISOLATED"
_CONTENT_LENGTH = re.compile(rb"(?i)content-length: *(\d+)")


def _config_file(directory: Path) -> Path:
    text = (ROOT / "config" / "simulated.toml").read_text(encoding="utf-8")
    subs = {
        r"^width = \d+": f"width = {WIDTH}",
        r"^height = \d+": f"height = {HEIGHT}",
        r'^data_dir = ".*"': 'data_dir = "data"',
        r'^database = ".*"': 'database = "data/lfcal.sqlite3"',
    }
    for pattern, value in subs.items():
        text, n = re.subn(pattern, value, text, count=1, flags=re.MULTILINE)
        if n != 1:
            raise RuntimeError(f"config/simulated.toml has no line matching {pattern!r}")
    path = directory / "station.toml"
    path.write_text(text, encoding="utf-8")
    return path


# --------------------------------------------------------------------- the pollers


async def _poller(
    port: int,
    path: str,
    offset_s: float,
    interval_s: float,
    deadline: float,
    done: asyncio.Event,
    out: dict[str, Any],
) -> None:
    """One poller: a keep-alive HTTP/1.1 connection, a GET every ``interval_s``."""
    request = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAccept: application/json\r\n\r\n"
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    loop = asyncio.get_running_loop()
    next_at = loop.time() + offset_s
    try:
        while not done.is_set() and time.monotonic() < deadline:
            await asyncio.sleep(max(0.0, next_at - loop.time()))
            next_at += interval_s
            t0 = time.perf_counter()
            try:
                writer.write(request.encode())
                async with asyncio.timeout(10):
                    head = await reader.readuntil(b"\r\n\r\n")
                    status = int(head.split(b" ", 2)[1])
                    length = int(_CONTENT_LENGTH.search(head)[1])  # type: ignore[index]
                    body = await reader.readexactly(length)
            except (OSError, TimeoutError, asyncio.IncompleteReadError, ValueError) as exc:
                out["errors"].append(f"{type(exc).__name__}: {exc}")
                writer.close()
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
                continue
            took = time.perf_counter() - t0
            if status != 200:
                out["errors"].append(f"HTTP {status}")
                continue
            out["latencies_s"].append(took)
            if len(out["latencies_s"]) + len(out["errors"]) >= MAX_REQUESTS:
                done.set()
            if json.loads(body)["state"] in FINAL:
                done.set()
    finally:
        writer.close()


async def _stream(port: int, path: str, deadline: float, out: dict[str, Any]) -> None:
    """One event stream, read until the job's final ``state`` event (else an error)."""
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
    except OSError as exc:
        out["errors"].append(f"stream: {exc}")
        return
    try:
        writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
        async with asyncio.timeout(10):
            head = await reader.readuntil(b"\r\n\r\n")
        if b" 200 " not in head.split(b"\r\n", 1)[0]:
            out["errors"].append(f"stream: {head[:40]!r}")
            return
        kind = b""
        while time.monotonic() < deadline:
            async with asyncio.timeout(max(0.1, deadline - time.monotonic())):
                line = await reader.readline()
            if not line:
                break
            if line.startswith(b"event:"):
                kind = line[6:].strip()
            elif kind == b"state" and line.startswith(b"data:"):
                state = line.split(b'"state":"', 1)[1].split(b'"', 1)[0].decode()
                if state in FINAL:
                    out["streams_done"] += 1
                    return
        out["errors"].append("stream: ended without the final state")
    except (OSError, TimeoutError, asyncio.IncompleteReadError, IndexError) as exc:
        out["errors"].append(f"stream: {type(exc).__name__}: {exc}")
    finally:
        writer.close()


def poll(
    port: int, job_id: int, pollers: int, interval_s: float, max_s: float, streams: int = 0
) -> dict[str, Any]:
    """Run ``pollers`` concurrent pollers (asyncio on uvloop when installed, one thread,
    timeouts without extra tasks: the client adds as little CPU time and scheduling
    delay as it can) against ``127.0.0.1:port`` until the job is final (or ``max_s`` /
    :data:`MAX_REQUESTS`); latencies (s), errors, and the client's CPU time (s)."""
    out: dict[str, Any] = {"latencies_s": [], "errors": [], "streams_done": 0}

    async def main() -> None:
        done = asyncio.Event()
        deadline = time.monotonic() + max_s
        path = f"/api/v1/jobs/{job_id}"
        await asyncio.gather(
            *(_stream(port, f"{path}/events", deadline + 10, out) for _ in range(streams)),
            *(
                _poller(port, path, interval_s * k / pollers, interval_s, deadline, done, out)
                for k in range(pollers)
            ),
        )

    cpu0 = sum(os.times()[:2])
    try:
        import uvloop
    except ImportError:
        asyncio.run(main())
    else:
        uvloop.run(main())
    errors = out["errors"]
    return {
        "latencies_s": out["latencies_s"],
        "errors": errors[:20],
        "error_count": len(errors),
        "streams_done": out["streams_done"],
        "client_cpu_s": sum(os.times()[:2]) - cpu0,
    }


def _poller_main(argv: list[str]) -> int:
    """``--poll PORT POLLERS INTERVAL MAX_S STREAMS REPORT``: print ``ready``, read the job
    id from stdin, poll, write the JSON report to the file ``REPORT`` (not to stdout: a
    200 kB report read from the pipe came back cut at 128 KiB in 2 runs of about 12)."""
    port, pollers = int(argv[0]), int(argv[1])
    interval_s, max_s, streams = float(argv[2]), float(argv[3]), int(argv[4])
    report = Path(argv[5])
    print("ready", flush=True)
    job_id = int(sys.stdin.readline())
    result = poll(port, job_id, pollers, interval_s, max_s, streams)
    partial = report.with_suffix(".partial")
    partial.write_text(json.dumps(result), encoding="utf-8")
    partial.replace(report)
    return 0


# --------------------------------------------------------------------- the benchmark


def _row(name: str, value: float, unit: str, target: float | None = None) -> dict[str, Any]:
    ok = None if target is None else bool(value <= target)
    return {"name": name, "value": float(value), "unit": unit, "target": target, "ok": ok}


def _cpu_jiffies() -> tuple[int, int] | None:
    """(steal, total) CPU time of the whole machine from Linux ``/proc/stat`` (jiffies),
    or None elsewhere. Steal is time the hypervisor gave this VM's CPUs to others."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
    except (OSError, IndexError):
        return None
    if fields[0] != "cpu" or len(fields) < 9:
        return None
    values = [int(v) for v in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return values[7], sum(values)


def _cpu_pressure_us() -> int | None:
    """Total time (µs) some runnable task waited for a CPU (Linux PSI), or None."""
    try:
        line = Path("/proc/pressure/cpu").read_text().splitlines()[0]
    except (OSError, IndexError):
        return None
    fields = dict(f.split("=", 1) for f in line.split()[1:] if "=" in f)
    return int(fields["total"]) if "total" in fields else None


def _thread_sched(native_id: int | None) -> tuple[int, int] | None:
    """(CPU time, time runnable but waiting for a CPU) of a thread of this process (ns),
    from Linux ``/proc/self/task/TID/schedstat``; None elsewhere."""
    if native_id is None:
        return None
    try:
        run_ns, wait_ns, _ = Path(f"/proc/self/task/{native_id}/schedstat").read_text().split()
    except (OSError, ValueError):
        return None
    return int(run_ns), int(wait_ns)


@dataclasses.dataclass(frozen=True)
class PollerPlacement:
    """Where the poller process runs: ``nice`` levels below the server, pinned to
    CPU ``cpu`` (None: anywhere)."""

    nice: int = 0
    cpu: int | None = None

    def describe(self) -> str:
        parts = [f"nice +{self.nice}"] if self.nice else []
        if self.cpu is not None:
            parts.append(f"on CPU {self.cpu}")
        return f"pollers {' '.join(parts)}" if parts else ""

    def apply(self) -> None:
        """In the poller process (before it runs)."""
        if self.nice:
            os.nice(self.nice)
        if self.cpu is not None:
            os.sched_setaffinity(0, {self.cpu})


def _sweep(
    station: Any,
    request: dict[str, Any],
    port: int,
    pollers: int,
    streams: int = 0,
    placement: PollerPlacement | None = None,
) -> dict[str, Any]:
    """Run one sweep; with ``pollers`` > 0, under a poller process (and ``streams`` event
    streams). Step timings, latencies."""
    from station.store import JobState

    load: dict[str, Any] = {"latencies_s": [], "errors": [], "error_count": 0}
    if not pollers:
        job = station.submit(request)
    else:  # the pollers are up before the sweep starts
        report = Path(tempfile.mkdtemp(prefix="lfcal-bench-pollers-")) / "report.json"
        args = [str(port), str(pollers), str(INTERVAL_S), str(MAX_POLL_S), str(streams)]
        args.append(str(report))
        with subprocess.Popen(
            [sys.executable, "-m", "bench.bench_web", "--poll", *args],
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            preexec_fn=(placement or PollerPlacement()).apply,
        ) as proc:
            assert proc.stdin is not None and proc.stdout is not None
            if proc.stdout.readline().strip() != "ready":
                raise RuntimeError("the poller process did not start")
            job = station.submit(request)
            proc.communicate(f"{job.id}\n", timeout=MAX_POLL_S + 60)
        try:
            if proc.returncode != 0:
                raise RuntimeError(f"the poller process failed ({proc.returncode})")
            load = json.loads(report.read_text(encoding="utf-8"))
        finally:
            shutil.rmtree(report.parent, ignore_errors=True)
    final = {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
    done = station.wait_for(job.id, final, timeout_s=1800)
    if done.state is not JobState.SUCCEEDED:
        raise RuntimeError(f"the benchmark sweep ended {done.state.value}: {done.last_error}")
    return {"timings": station.step_timings(job.id), **load}


def run(
    frames: int = 30,
    pollers: int = POLLERS,
    streams: int = STREAMS,
    placement: PollerPlacement | None = None,
    isolation: str = "",
) -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target).

    ``placement``: where the pollers run; ``isolation``: how the benchmark's session
    is isolated (for the label; see :func:`main`)."""
    import uvicorn

    from station.config import load_config, with_frame_cache
    from station.orchestrator import Orchestrator
    from web.app import create_app
    from web.server import uvicorn_config

    request = {"start_mm": 35.0, "stop_mm": 35.0 + frames - 1, "step_mm": 1.0}
    with tempfile.TemporaryDirectory(prefix="lfcal-bench-web-") as tmp:
        config = load_config(_config_file(Path(tmp)))
        station = Orchestrator(with_frame_cache(config, CACHE)).start()
        server = uvicorn.Server(
            uvicorn_config(create_app(config, station=station), log_level="warning")
        )
        import socket

        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        port = int(sock.getsockname()[1])
        thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + 30
            while not server.started and time.monotonic() < deadline:
                time.sleep(0.05)
            station.wait_ready(60)
            _sweep(station, request, port, 0)  # warm-up: frame cache, analysis processes
            idle = _sweep(station, request, port, 0)
            before = _cpu_jiffies()
            pressure0, loop0, t0 = _cpu_pressure_us(), _thread_sched(thread.native_id), time.time()
            loaded = _sweep(station, request, port, pollers, streams, placement)
            pressure1, loop1, t1 = _cpu_pressure_us(), _thread_sched(thread.native_id), time.time()
            after = _cpu_jiffies()
        finally:
            server.should_exit = True
            thread.join(30)
            sock.close()
            station.close()

    lat_ms = sorted(x * 1000.0 for x in loaded["latencies_s"])
    if len(lat_ms) < 2:
        raise RuntimeError(f"the pollers got {len(lat_ms)} answers: {loaded['errors']}")
    p50 = statistics.median(lat_ms)
    p99 = statistics.quantiles(lat_ms, n=100, method="inclusive")[98]
    idle_ms = statistics.median(t.overhead_s * 1000.0 for t in idle["timings"])
    loaded_ms = statistics.median(t.overhead_s * 1000.0 for t in loaded["timings"])
    idle_step = statistics.median(t.total_s * 1000.0 for t in idle["timings"])
    loaded_step = statistics.median(t.total_s * 1000.0 for t in loaded["timings"])
    extra = ", ".join(x for x in ((placement or PollerPlacement()).describe(), isolation) if x)
    label = (
        f"{pollers} pollers every {INTERVAL_S * 1000:.0f} ms, {streams} event streams, "
        f"{frames}-step sweep with streaming analysis{', ' + extra if extra else ''}"
    )
    rows = [
        _row(f"web: status latency p50 ({label})", p50, "ms"),
        _row(f"web: status latency p99 ({label})", p99, "ms", TARGET_P99_MS),
        _row("web: status latency max", lat_ms[-1], "ms"),
        _row("web: status requests answered", len(lat_ms), "req"),
        _row("web: status requests and streams failed", loaded["error_count"], "req", 0),
        _row("web: event streams ended with the final state", loaded["streams_done"], "streams"),
        _row("web: station overhead per step, idle (median)", idle_ms, "ms"),
        _row("web: station overhead per step, polled (median)", loaded_ms, "ms"),
        _row(
            "web: station overhead per step, change under polling",
            loaded_ms - idle_ms,
            "ms",
            TARGET_OVERHEAD_CHANGE_MS,
        ),
        _row("web: sweep step time, idle (median)", idle_step, "ms"),
        _row("web: sweep step time, polled (median)", loaded_step, "ms"),
    ]
    rows.extend(_contention_rows(before, after, pressure0, pressure1, loop0, loop1, t1 - t0))
    rows.append(
        _row(
            "web: pollers CPU (of one core)",
            100.0 * loaded.get("client_cpu_s", 0.0) / (t1 - t0),
            "%",
        )
    )
    if loop0 is not None and loop1 is not None and lat_ms:
        rows.append(
            _row(
                "web: server event-loop CPU per status request (event streams included)",
                (loop1[0] - loop0[0]) / 1000.0 / len(lat_ms),
                "us",
            )
        )
    return rows


def _contention_rows(
    before: tuple[int, int] | None,
    after: tuple[int, int] | None,
    pressure0: int | None,
    pressure1: int | None,
    loop0: tuple[int, int] | None,
    loop1: tuple[int, int] | None,
    wall_s: float,
) -> list[dict[str, Any]]:
    """How contended the CPUs were during the polled sweep (see the module docstring)."""
    rows = []
    if before is not None and after is not None and after[1] > before[1]:
        steal = 100.0 * (after[0] - before[0]) / (after[1] - before[1])
        # on a VM, the latency tail follows the time the host takes the CPUs away
        rows.append(_row("web: CPU steal by the hypervisor during the polled sweep", steal, "%"))
    if pressure0 is not None and pressure1 is not None and wall_s > 0:
        share = (pressure1 - pressure0) / 1e6 / wall_s * 100.0
        rows.append(_row("web: CPU pressure (PSI some: a task waited for a CPU)", share, "%"))
    with contextlib.suppress(OSError, ValueError, IndexError):
        load1 = float(Path("/proc/loadavg").read_text().split()[0])
        rows.append(_row("web: load average (1 min) after the polled sweep", load1, ""))
    if loop0 is not None and loop1 is not None and wall_s > 0:
        cpu = (loop1[0] - loop0[0]) / 1e9 / wall_s * 100.0
        wait = (loop1[1] - loop0[1]) / 1e9 / wall_s * 100.0
        rows.append(_row("web: server event loop CPU (of one core)", cpu, "%"))
        rows.append(_row("web: server event loop runnable, waiting for a CPU", wait, "%"))
    return rows


def _isolate_session(nice: int) -> str:
    """In a new session (see :func:`main`): give its autogroup the weight of ``nice``;
    the label for the table (empty when not permitted)."""
    try:
        Path("/proc/self/autogroup").write_text(f"{nice}\n")
    except OSError as exc:
        print(f"bench_web: not isolated: /proc/self/autogroup: {exc}", file=sys.stderr)
        return ""
    return f"own session at autogroup nice {nice}"


def main(argv: list[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    if args_in[:1] == ["--poll"]:
        return _poller_main(args_in[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--pollers", type=int, default=POLLERS)
    parser.add_argument("--streams", type=int, default=STREAMS)
    parser.add_argument(
        "--pollers-nice", type=int, default=0, help="run the pollers N nice levels lower"
    )
    parser.add_argument("--pollers-cpu", type=int, default=None, help="pin the pollers to CPU K")
    parser.add_argument(
        "--isolate",
        action="store_true",
        help=f"run in a session of its own with the scheduler weight of nice {ISOLATE_NICE}",
    )
    args = parser.parse_args(args_in)
    if args.isolate and not os.environ.get(_ISOLATED_ENV):
        # a new session gets a new autogroup; the child sets its weight
        rest = [a for a in args_in if a != "--isolate"]
        child = [sys.executable, "-m", "bench.bench_web", *rest]
        env = dict(os.environ, **{_ISOLATED_ENV: str(ISOLATE_NICE)})
        return subprocess.run(child, cwd=ROOT, env=env, start_new_session=True).returncode
    isolation = ""
    if os.environ.get(_ISOLATED_ENV):
        isolation = _isolate_session(int(os.environ[_ISOLATED_ENV]))
    from bench.__main__ import print_table

    placement = PollerPlacement(args.pollers_nice, args.pollers_cpu)
    rows = run(args.frames, args.pollers, args.streams, placement, isolation)
    print_table(rows)
    return 0 if all(r["ok"] is not False for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
