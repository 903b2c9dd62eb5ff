"""Fault injection at every boundary of a running sweep, over real HTTP (loopback only).

Each scenario starts a sweep on the simulated station (2000×500 px frames from
the shared frame cache, emulated stages 20× faster), injects one fault while it
runs, and asserts:

* the job ends in a truthful state with a specific reason (over HTTP, and as the
  last ``state`` event of its event stream);
* every recorded frame verifies against its checksum (the store's SHA-256 of
  each step, the manifest's and the file's agree);
* once the fault is gone, the job resumes to a complete archive and the next
  job completes;
* ``/healthz`` told the truth throughout: a watcher polls it every 50 ms, and
  every answer given while a component was known to be down says so (503 and the
  component), every answer before the fault and after its repair is 200.

Boundaries and how they are injected:

=========================== ============================================================
database write error        the store's connections come from a ``sqlite3.Connection``
                            subclass whose ``COMMIT`` fails with SQLITE_IOERR while armed
disk full from another      the server runs in its own mount namespace (``unshare -rm``)
process                     on a 64 MB tmpfs; this test process fills that tmpfs through
                            ``/proc/PID/root`` (a real ENOSPC for the server)
archive write error         ``calibration.archive_writer.atomic_write_bytes`` raises EIO for
                            frame files while armed (the writer's boundary)
camera loss                 the simulated camera is unplugged mid-sweep
serial loss                 the Zaber emulator drops the line during a rail move
analysis worker killed      SIGKILL to a live analysis worker process
SIGTERM, ``kill -9``        to a real ``python -m web.server`` process, then a restart
=========================== ============================================================
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from test_web_support import (
    FINAL,
    KEY,
    SPEEDUP,
    InProcessServer,
    ServerProcess,
    frame_cache,
    keyed,
    wait_for_state,
    wait_until,
    write_config,
)

import calibration.archive_writer as archive_module
from station.config import load_config, with_frame_cache
from station.db import SQLitePool
from station.events import JobEvent
from station.orchestrator import Orchestrator
from station.store import JobStore
from web.app import create_app

API = "/api/v1"
SHORT = {"start_mm": 30.0, "stop_mm": 55.0, "step_mm": 5.0, "calibrate": False}  # 6 frames
SLOW = {**SHORT, "settle_s": 0.5}
"""6 frames, at least 0.5 s apart: a signal sent after frame 2 lands mid-sweep."""
FULL = {"start_mm": 30.0, "stop_mm": 75.0, "step_mm": 5.0, "calibrate": True}  # 10 frames

pytestmark = pytest.mark.timeout(240)


# --------------------------------------------------------------------------- fault hooks

DB_FAULT = threading.Event()
"""While set, every COMMIT of the station's store fails with SQLITE_IOERR."""


class FaultyConnection(sqlite3.Connection):
    """A real SQLite connection whose COMMIT fails while :data:`DB_FAULT` is set."""

    def execute(self, sql: str, *args: Any) -> sqlite3.Cursor:  # type: ignore[override]
        if DB_FAULT.is_set() and sql.lstrip().upper().startswith("COMMIT"):
            exc = sqlite3.OperationalError("disk I/O error")
            exc.sqlite_errorcode = 10  # type: ignore[attr-defined]  # SQLITE_IOERR
            raise exc
        return super().execute(sql, *args)


# --------------------------------------------------------------------------- health watcher


@dataclass
class Sample:
    at: float
    status: int
    body: dict[str, Any]


@dataclass
class HealthWatch:
    """Polls ``/healthz`` every 50 ms in a thread (stop it!)."""

    url: str
    samples: list[Sample] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=10.0) as client:
            while not self._stop.is_set():
                try:
                    r = client.get(f"{API}/healthz")
                    self.samples.append(Sample(time.monotonic(), r.status_code, r.json()))
                except (httpx.HTTPError, ValueError):
                    pass
                self._stop.wait(0.05)

    def between(self, t0: float, t1: float) -> list[Sample]:
        return [s for s in list(self.samples) if t0 <= s.at <= t1]

    def fresh(self, after: float, timeout_s: float = 10.0) -> Sample:
        """The first sample taken after ``after``."""
        return wait_until(
            lambda: next((s for s in list(self.samples) if s.at > after), None),
            timeout_s,
            "a health sample",
        )

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)


# --------------------------------------------------------------------------- helpers


class EventLog:
    """The job's SSE stream, read to its end in a thread."""

    def __init__(self, url: str, job_id: int) -> None:
        self.events: list[tuple[str, dict[str, Any]]] = []
        self.ended = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(url, job_id), daemon=True)
        self._thread.start()

    def _run(self, url: str, job_id: int) -> None:
        try:
            with httpx.stream("GET", f"{url}{API}/jobs/{job_id}/events", timeout=120) as r:
                kind = "message"
                for line in r.iter_lines():
                    if line.startswith("event:"):
                        kind = line.split(":", 1)[1].strip()
                    elif line.startswith("data:"):
                        self.events.append((kind, json.loads(line.split(":", 1)[1])["data"]))
        except httpx.HTTPError:
            pass
        finally:
            self.ended.set()

    def final_state(self, timeout_s: float = 60.0) -> dict[str, Any]:
        assert self.ended.wait(timeout_s), "the event stream did not end"
        states = [data for kind, data in self.events if kind == "state"]
        assert states, self.events
        return states[-1]


def submit(client: httpx.Client, body: dict[str, Any]) -> int:
    r = client.post(f"{API}/jobs", json=body, headers=keyed())
    assert r.status_code == 202, r.text
    return int(r.json()["id"])


def replayed_steps(url: str, job_id: int) -> list[dict[str, Any]]:
    """The recorded steps of a finished job, from its event stream's replay (the store)."""
    with httpx.Client(base_url=url, timeout=30) as c:
        text = c.get(f"{API}/jobs/{job_id}/events").text
    steps = []
    for block in text.split("\n\n"):
        if "event: step" in block:
            data = next(line for line in block.splitlines() if line.startswith("data:"))
            steps.append(json.loads(data[5:])["data"])
    return steps


def verify_recorded_frames(url: str, job_id: int, job_dir: Path) -> list[int]:
    """Every recorded step's SHA-256 (store) matches its file and the manifest's entry;
    every manifest entry matches its file. Returns the recorded indices."""
    manifest = json.loads((job_dir / "sweep.json").read_text(encoding="utf-8"))
    listed = {f["index"]: f for f in manifest["frames"]}
    for entry in listed.values():
        digest = hashlib.sha256((job_dir / entry["file"]).read_bytes()).hexdigest()
        assert digest == entry["sha256"], f"frame {entry['index']} does not match its manifest"
    steps = replayed_steps(url, job_id)
    for step in steps:
        assert step["index"] in listed, f"recorded step {step['index']} is not in the manifest"
        assert listed[step["index"]]["sha256"] == step["sha256"]
    assert not list(job_dir.rglob("*.tmp"))
    return [s["index"] for s in steps]


def assert_complete(url: str, job_id: int, job_dir: Path, frames: int) -> None:
    assert verify_recorded_frames(url, job_id, job_dir) == list(range(frames))


def next_job_completes(client: httpx.Client, url: str, data_dir: Path) -> None:
    job_id = submit(client, SHORT)
    done = wait_for_state(client, job_id, FINAL, 90)
    assert done["state"] == "succeeded", done["last_error"]
    assert_complete(url, job_id, job_dir_of(data_dir, job_id), 6)


def resume_completes(
    client: httpx.Client, url: str, data_dir: Path, job_id: int, job_dir: Path
) -> None:
    """Resume the interrupted 6-frame job: it succeeds with every frame recorded once,
    and the next job runs to the end."""
    assert client.post(f"{API}/jobs/{job_id}/resume", headers=keyed()).status_code == 200
    done = wait_for_state(client, job_id, FINAL, 90)
    assert done["state"] == "succeeded", done["last_error"]
    assert_complete(url, job_id, job_dir, 6)
    next_job_completes(client, url, data_dir)


def job_dir_of(data_dir: Path, job_id: int) -> Path:
    return next(data_dir.glob(f"job-{job_id:06d}-*"))


def all_ok(samples: list[Sample]) -> bool:
    return all(s.status == 200 for s in samples)


# --------------------------------------------------------------------------- in-process rig


@dataclass
class Rig:
    station: Orchestrator
    server: InProcessServer
    watch: HealthWatch
    data_dir: Path

    @property
    def client(self) -> httpx.Client:
        return self.server.client

    @property
    def url(self) -> str:
        return self.server.url

    injected_at: float = 0.0

    def inject_at_step(self, index: int, inject: Callable[[], None]) -> Callable[[], None]:
        """Run ``inject()`` when a job newer than every existing one records step ``index``."""
        newest = max((j.id for j in self.station.store.list_jobs()), default=0)
        fired = threading.Event()
        self.injected_at = float("inf")

        def listener(event: JobEvent) -> None:
            if (
                event.type == "step"
                and event.job_id > newest
                and event.id == index
                and not fired.is_set()
            ):
                fired.set()
                self.injected_at = time.monotonic()
                inject()

        self.station.add_listener(listener)
        return lambda: self.station.remove_listener(listener)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config) -> Iterator[Rig]:
    directory = tmp_path_factory.mktemp("faults")
    path = write_config(directory)
    # a lost camera is given up after 2 s (not 30) of reconnect attempts
    path.write_text(path.read_text().replace("timeout_s = 30.0", "timeout_s = 2.0"))
    config = with_frame_cache(
        load_config(path, env={"LFCAL_API_KEYS": KEY}), frame_cache(pytestconfig)
    )
    connect = functools.partial(sqlite3.connect, factory=FaultyConnection)
    store = JobStore(SQLitePool(config.storage.database, connect=connect))
    station = Orchestrator(
        config,
        store=store,
        emulator_speedup=SPEEDUP,
        analysis_workers=1,
    ).start()
    server = InProcessServer(create_app(config, station=station))
    watch = HealthWatch(server.url)
    try:
        assert station.wait_ready(60)
        yield Rig(station, server, watch, Path(config.storage.data_dir))
    finally:
        DB_FAULT.clear()
        watch.stop()
        server.stop()
        station.close()
        store.close()


def test_database_write_error(rig: Rig) -> None:
    c = rig.client
    t0 = time.monotonic()
    remove = rig.inject_at_step(1, DB_FAULT.set)
    try:
        job_id = submit(c, SHORT)
        stream = EventLog(rig.url, job_id)
        final = stream.final_state()
        ended = time.monotonic()
        # the store refused the final state: the job is interrupted (from memory), with why
        assert final["state"] == "interrupted" and final["recorded"] is False
        status = c.get(f"{API}/jobs/{job_id}").json()
        assert status["state"] == "interrupted"
        assert "cannot be written" in status["last_error"]
        assert "disk I/O error" in status["last_error"]
        health = rig.watch.fresh(ended)
        assert health.status == 503 and health.body["components"]["store"]["state"] == "down"
        refused = c.post(f"{API}/jobs", json=SHORT, headers=keyed())
        assert refused.status_code == 503 and refused.json()["code"] == "store_unavailable"
        assert c.post(f"{API}/jobs/{job_id}/resume", headers=keyed()).status_code == 503
        cleared = time.monotonic()
    finally:
        DB_FAULT.clear()
        remove()
    # every health answer between the job's end and the repair said the store is down
    during = rig.watch.between(ended, cleared)
    assert during and all(s.status == 503 for s in during)
    assert all("job store" in " ".join(s.body["problems"]) for s in during)
    assert all_ok(rig.watch.between(t0, rig.injected_at))
    # the repair: the interrupted state is written, health recovers, resume completes
    wait_until(lambda: rig.watch.fresh(time.monotonic()).status == 200, 20, "health ok")
    transitions = rig.station.transitions(job_id)
    assert transitions[-1].to_state.value == "interrupted"
    assert "cannot record this" in transitions[-1].reason
    job_dir = job_dir_of(rig.data_dir, job_id)
    kept = verify_recorded_frames(rig.url, job_id, job_dir)
    assert 1 <= len(kept) < 6
    resume_completes(c, rig.url, rig.data_dir, job_id, job_dir)


def test_archive_write_error(rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    c = rig.client
    broken = threading.Event()
    real = archive_module.atomic_write_bytes

    def atomic_write_bytes(path: Any, data: bytes, **kwargs: Any) -> None:
        if broken.is_set() and Path(path).parent.name == "frames":
            raise OSError(errno.EIO, "Input/output error", str(path))
        real(path, data, **kwargs)

    monkeypatch.setattr(archive_module, "atomic_write_bytes", atomic_write_bytes)
    t0 = time.monotonic()
    remove = rig.inject_at_step(1, broken.set)
    try:
        job_id = submit(c, SHORT)
        final = EventLog(rig.url, job_id).final_state()
    finally:
        remove()
    assert final["state"] == "failed"
    assert "cannot write the archive" in final["last_error"]
    assert "Input/output error" in final["last_error"]
    # nothing is down: the store and the disk work, and health said so
    assert all_ok(rig.watch.between(t0, time.monotonic()))
    job_dir = job_dir_of(rig.data_dir, job_id)
    assert 2 <= len(verify_recorded_frames(rig.url, job_id, job_dir)) < 6
    broken.clear()
    resume_completes(c, rig.url, rig.data_dir, job_id, job_dir)


DEVICE_FAULTS: dict[str, tuple[Callable[[Any], None], str]] = {
    "camera loss": (lambda d: d.camera.unplug(), "unplugged"),
    "serial loss": (lambda d: d.bench.emulator.disconnect_on_next_move(1, 1), "connection"),
}


@pytest.mark.parametrize("kind", list(DEVICE_FAULTS))
def test_device_loss(rig: Rig, kind: str) -> None:
    c = rig.client
    inject, words = DEVICE_FAULTS[kind]
    devices = rig.station.devices
    assert devices is not None
    t0 = time.monotonic()
    remove = rig.inject_at_step(1, lambda: inject(devices))
    try:
        job_id = submit(c, SHORT)
        final = EventLog(rig.url, job_id).final_state()
    finally:
        remove()
    ended = time.monotonic()
    assert final["state"] == "failed" and words in final["last_error"].lower()
    assert "frames kept" in final["last_error"]
    assert all_ok(rig.watch.between(t0, rig.injected_at))
    # the station reopened the devices after the loss: health says whether they are back
    after = rig.watch.fresh(ended)
    devices_state = after.body["components"]["devices"]["state"]
    assert (after.status, devices_state) in ((200, "connected"), (200, "opening"), (503, "down"))
    wait_until(lambda: rig.watch.fresh(time.monotonic()).status == 200, 30, "devices back")
    job_dir = job_dir_of(rig.data_dir, job_id)
    assert 2 <= len(verify_recorded_frames(rig.url, job_id, job_dir)) < 6
    resume_completes(c, rig.url, rig.data_dir, job_id, job_dir)


def test_analysis_worker_killed(rig: Rig) -> None:
    c = rig.client
    pool = rig.station.analysis_pool
    assert pool is not None
    restarts = pool.restarts
    killed: list[int] = []

    def kill_worker() -> None:
        pids = pool.health()["pids"]
        assert pids, "no live analysis worker to kill"
        os.kill(pids[0], signal.SIGKILL)
        killed.append(pids[0])

    t0 = time.monotonic()
    remove = rig.inject_at_step(2, kill_worker)
    try:
        job_id = submit(c, FULL)
        final = EventLog(rig.url, job_id).final_state(120)
    finally:
        remove()
    assert killed
    assert final["state"] == "succeeded", final
    result = c.get(f"{API}/jobs/{job_id}/result").json()
    assert len(result["frames"]) == 10  # every frame analysed, none silently missing
    analysis = c.get(f"{API}/healthz").json()["components"]["analysis"]
    assert analysis["restarts"] > restarts and analysis["state"] == "ok"
    assert "died" in analysis["last_fault"] and killed[0] not in analysis["pids"]
    # the station could run jobs throughout (the analysis falls back), and said so
    samples = rig.watch.between(t0, time.monotonic())
    assert all(s.status == 200 for s in samples)
    degraded = [s for s in samples if s.body["status"] != "ok"]
    assert all("analysis" in " ".join(s.body["problems"]) for s in degraded)
    assert_complete(rig.url, job_id, job_dir_of(rig.data_dir, job_id), 10)
    next_job_completes(c, rig.url, rig.data_dir)


# --------------------------------------------------------------------------- real processes


def wait_frames(client: httpx.Client, job_id: int, count: int, timeout_s: float = 60.0) -> None:
    def probe() -> bool:
        job = client.get(f"{API}/jobs/{job_id}").json()
        assert job["state"] not in FINAL, job
        return bool(job["frames_done"] >= count)

    wait_until(probe, timeout_s, f"job {job_id} to record {count} frames", 0.02)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "kill -9"])
def test_server_process_stopped_mid_sweep(
    tmp_path: Path, pytestconfig: pytest.Config, sig: signal.Signals
) -> None:
    config = write_config(tmp_path)
    data_dir = tmp_path / "data"
    cache = frame_cache(pytestconfig)
    server = ServerProcess(config, cache=cache, analysis_workers=0)
    try:
        job_id = submit(server.client, SLOW)
        stream = EventLog(server.url, job_id)
        wait_frames(server.client, job_id, 2)
        server.proc.send_signal(sig)
        server.proc.wait(60)
        if sig == signal.SIGTERM:
            assert server.proc.returncode == 0, server.log()
            final = stream.final_state(10)  # the stream ended with the job's final state
            assert final["state"] == "interrupted"
            assert "shut down" in final["reason"]
        else:
            assert server.proc.returncode == -signal.SIGKILL
            assert stream.ended.wait(10)
    finally:
        server.stop()
    again = ServerProcess(config, cache=cache, analysis_workers=0)
    try:
        c = again.client
        health = c.get(f"{API}/healthz")
        assert health.status_code == 200 and health.json()["status"] == "ok", health.text
        job = c.get(f"{API}/jobs/{job_id}").json()
        assert job["state"] == "interrupted"
        if sig == signal.SIGKILL:
            assert "found at start-up" in job["last_error"]
            assert "verified by SHA-256" in job["last_error"]
        job_dir = job_dir_of(data_dir, job_id)
        assert len(verify_recorded_frames(again.url, job_id, job_dir)) >= 2
        resume_completes(c, again.url, data_dir, job_id, job_dir)
    finally:
        assert again.stop() == 0, again.log()


def _can_mount_tmpfs(directory: Path) -> str | None:
    if shutil.which("unshare") is None:
        return "no unshare(1)"
    probe = subprocess.run(
        ["unshare", "-rm", "sh", "-c", f'mount -t tmpfs -o size=1m tmpfs "{directory}"'],
        capture_output=True,
        text=True,
    )
    return None if probe.returncode == 0 else f"cannot mount a tmpfs: {probe.stderr.strip()}"


def test_disk_full_from_another_process(tmp_path: Path, pytestconfig: pytest.Config) -> None:
    config = write_config(tmp_path)
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    why = _can_mount_tmpfs(data_dir)
    if why is not None:
        pytest.skip(f"needs a private tmpfs (user and mount namespaces): {why}")
    mount = ["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=64m tmpfs "$0" && exec "$@"']
    server = ServerProcess(
        config, cache=frame_cache(pytestconfig), analysis_workers=0, wrap=[*mount, str(data_dir)]
    )
    watch = HealthWatch(server.url)
    try:
        c = server.client
        # the server's view of its data directory: the tmpfs in its mount namespace
        seen = Path(f"/proc/{server.proc.pid}/root") / str(data_dir).lstrip("/")
        assert c.get(f"{API}/healthz").status_code == 200
        job_id = submit(c, SLOW)
        stream = EventLog(server.url, job_id)
        wait_frames(c, job_id, 2)
        filler = seen / "filler.bin"
        with filler.open("wb") as fh:  # another process fills the disk
            chunk = b"\0" * (1 << 20)
            try:
                while True:
                    fh.write(chunk)
                    fh.flush()
            except OSError as exc:
                assert exc.errno == errno.ENOSPC
        full_at = time.monotonic()
        final = stream.final_state(60)
        assert final["state"] in ("failed", "interrupted"), final
        assert "disk" in final["last_error"] and "full" in final["last_error"]
        sample = watch.fresh(time.monotonic())
        assert sample.status == 503 and sample.body["components"]["storage"]["state"] == "full"
        refused = c.post(f"{API}/jobs", json=SHORT, headers=keyed())
        assert refused.status_code == 507 and refused.json()["code"] == "storage_full"
        assert "free space" in refused.json()["message"]
        resumed = c.post(f"{API}/jobs/{job_id}/resume", headers=keyed())
        assert resumed.status_code == 507, resumed.text
        # at least one answer well inside the full period (the steps above can take < 0.2 s)
        watch.fresh(full_at + 0.2)
        freed_at = time.monotonic()
        filler.unlink()
        # every answer while the disk was full said so (the first may predate the check)
        during = watch.between(full_at + 0.2, freed_at)
        assert during and all(
            s.status == 503 and s.body["components"]["storage"]["state"] == "full" for s in during
        )
        wait_until(lambda: watch.fresh(time.monotonic()).status == 200, 20, "health ok")
        job_dir = job_dir_of(seen, job_id)
        assert len(verify_recorded_frames(server.url, job_id, job_dir)) >= 2
        resume_completes(c, server.url, seen, job_id, job_dir)
    finally:
        watch.stop()
        assert server.stop() == 0, server.log()
