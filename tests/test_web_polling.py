"""The polled routes stay cheap without changing what clients get.

``GET /api/v1/jobs/{id}`` is answered by :class:`web.fast_status.FastStatus` from
memory, before the router (``bench/bench_web.py`` measures the latency): its
answers are the routed handler's byte for byte, it follows every state change at
once, it reads no database row once a job is known, and everything but the plain
successful case (unknown job, bad id, key required, a query string) gets the
router's answer. HTTP answers leave in one write (:mod:`web.http_limits`), and
every SSE event is serialised once whatever the number of clients (:mod:`web.sse`).
"""

from __future__ import annotations

import asyncio
import socket
import threading
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from test_web_support import (
    KEY,
    SPEEDUP,
    InProcessServer,
    frame_cache,
    keyed,
    wait_until,
    write_config,
)

import web.sse as sse
from station.config import load_config, with_frame_cache
from station.events import JobEvent
from station.orchestrator import Orchestrator
from station.store import JobState
from web.app import create_app
from web.fast_status import FastStatus
from web.http_limits import _CoalescedWrites
from web.schemas import JobOut
from web.station_api import job_dict

API = "/api/v1"
SHORT = {"start_mm": 30.0, "stop_mm": 35.0, "step_mm": 5.0, "calibrate": False}
ORDER = ["queued", "running", "paused", "succeeded", "failed", "cancelled", "interrupted"]


class Rig:
    def __init__(self, station: Orchestrator, server: InProcessServer) -> None:
        self.station = station
        self.server = server
        self.client = server.client


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config) -> Iterator[Rig]:
    path = write_config(tmp_path_factory.mktemp("polling"))
    config = with_frame_cache(
        load_config(path, env={"LFCAL_API_KEYS": KEY}), frame_cache(pytestconfig)
    )
    station = Orchestrator(config, analysis_workers=0, emulator_speedup=SPEEDUP).start()
    server = InProcessServer(create_app(config, station=station))
    try:
        assert station.wait_ready(60)
        yield Rig(station, server)
    finally:
        server.stop()
        station.close()


def run_job(rig: Rig) -> int:
    r = rig.client.post(f"{API}/jobs", json=SHORT, headers=keyed())
    assert r.status_code == 202, r.text
    job_id = int(r.json()["id"])
    final = {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
    done = rig.station.wait_for(job_id, final, timeout_s=120)
    assert done.state is JobState.SUCCEEDED, done.last_error
    return job_id


def test_the_polled_status_is_the_routed_answer_byte_for_byte(rig: Rig) -> None:
    job_id = run_job(rig)
    fast = rig.client.get(f"{API}/jobs/{job_id}")
    routed = rig.client.get(f"{API}/jobs/{job_id}", params={"via": "router"})  # a query: routed
    assert fast.status_code == routed.status_code == 200
    assert fast.content == routed.content
    for header in ("content-type", "content-length"):
        assert fast.headers[header] == routed.headers[header]
    assert fast.headers["content-type"] == "application/json"
    job = JobOut.model_validate(fast.json())  # the documented shape
    assert job.state == "succeeded" and job.frames_done == job.frames_total == 2
    assert fast.json() == job_dict(rig.station.status(job_id))
    head = rig.client.head(f"{API}/jobs/{job_id}")
    assert head.status_code == 200 and head.content == b""
    assert head.headers["content-length"] == fast.headers["content-length"]


def test_a_known_job_is_polled_without_reading_the_database(
    rig: Rig, monkeypatch: pytest.MonkeyPatch
) -> None:
    job_id = run_job(rig)
    rig.client.get(f"{API}/jobs/{job_id}")
    store = rig.station.store
    reads: list[str] = []
    for name in ("get_job", "step_count", "steps", "list_jobs"):
        method = getattr(store, name)

        def counted(*args: Any, _name: str = name, _method: Any = method, **kw: Any) -> Any:
            reads.append(_name)
            return _method(*args, **kw)

        monkeypatch.setattr(store, name, counted)
    for _ in range(20):
        assert rig.client.get(f"{API}/jobs/{job_id}").json()["state"] == "succeeded"
    assert reads == []


def test_the_status_follows_every_state_change_at_once(rig: Rig) -> None:
    """Right after each ``state`` event, the polled status shows that state (or a later one):
    the cached row is replaced before the change is announced."""
    seen: list[tuple[str, str, int]] = []
    by_job: dict[int, list[str]] = {}
    newest = max((j.id for j in rig.station.store.list_jobs()), default=0)

    stepped: list[tuple[float, float]] = []

    def poll_on_event(event: JobEvent) -> None:
        if event.type == "step" and event.job_id > newest:
            # a recorded step moves the row's updated_at: the status shows it at once
            body = httpx.get(f"{rig.server.url}{API}/jobs/{event.job_id}", timeout=10).json()
            step = rig.station.store.step(event.job_id, int(event.id or 0))
            assert step is not None
            stepped.append((body["updated_at"], step.written_at))
        if event.type == "state" and event.job_id > newest:
            # a client polls as soon as the event is out (here: in the publishing thread)
            body = httpx.get(f"{rig.server.url}{API}/jobs/{event.job_id}", timeout=10).json()
            assert body["id"] == event.job_id
            seen.append((event.data["state"], body["state"], body["frames_done"]))
            by_job.setdefault(event.job_id, []).append(event.data["state"])

    rig.station.add_listener(poll_on_event)
    try:
        first = rig.client.post(f"{API}/jobs", json=SHORT, headers=keyed()).json()["id"]
        second = rig.client.post(f"{API}/jobs", json=SHORT, headers=keyed()).json()["id"]
        # the second waits in the queue: cancelled at once, and polled as such at once
        assert rig.client.post(f"{API}/jobs/{second}/cancel", headers=keyed()).is_success
        assert rig.client.get(f"{API}/jobs/{second}").json()["state"] == "cancelled"
        final = wait_until(
            lambda: (
                (s := rig.client.get(f"{API}/jobs/{first}").json())["state"]
                in ("succeeded", "failed")
                and s
            ),
            120,
            "the job to finish",
            0.05,
        )
        # the listener polls from the worker's thread: wait for its last answer
        wait_until(lambda: seen and seen[-1][0] == "succeeded", 30, "the last poll", 0.05)
    finally:
        rig.station.remove_listener(poll_on_event)
    assert final["state"] == "succeeded" and final["frames_done"] == 2
    for event_state, polled, _ in seen:
        assert ORDER.index(polled) >= ORDER.index(event_state), seen
    assert by_job == {first: ["queued", "running", "succeeded"], second: ["queued", "cancelled"]}
    assert len(stepped) == 2 and all(updated >= written for updated, written in stepped)
    assert seen[-1] == ("succeeded", "succeeded", 2), seen


@pytest.mark.parametrize(
    ("path", "status", "code"),
    [
        ("/jobs/987654", 404, "job_not_found"),
        ("/jobs/0", 422, "invalid_request"),
        ("/jobs/abc", 422, "invalid_request"),
        ("/jobs/99999999999999999999", 422, "invalid_request"),
        ("/jobs/1/", 404, "not_found"),
    ],
)
def test_everything_but_a_known_job_gets_the_routers_answer(
    rig: Rig, path: str, status: int, code: str
) -> None:
    r = rig.client.get(f"{API}{path}", follow_redirects=False)
    if path.endswith("/") and r.status_code in (307, 308):
        return  # the router's trailing-slash redirect
    assert r.status_code == status, r.text
    assert r.json()["code"] == code


def test_a_read_key_is_still_required_when_configured(
    rig: Rig, tmp_path_factory: pytest.TempPathFactory
) -> None:
    job_id = run_job(rig)
    guarded = load_config(
        write_config(tmp_path_factory.mktemp("read-key"), read_only_requires_key=True),
        env={"LFCAL_API_KEYS": KEY},
    )
    server = InProcessServer(create_app(guarded, station=rig.station))
    try:
        anonymous = server.client.get(f"{API}/jobs/{job_id}")
        assert anonymous.status_code == 401 and anonymous.json()["code"] == "api_key_required"
        wrong = server.client.get(f"{API}/jobs/{job_id}", headers={"X-API-Key": "x" * 20})
        assert wrong.status_code == 403
        allowed = server.client.get(f"{API}/jobs/{job_id}", headers=keyed())
        assert allowed.status_code == 200
        assert allowed.content == rig.client.get(f"{API}/jobs/{job_id}").content
    finally:
        server.stop()


def read_response(stream: socket.socket, buffer: bytearray) -> tuple[bytes, bytes]:
    """One HTTP/1.1 response (head, body) with a Content-Length from ``stream``."""
    while b"\r\n\r\n" not in buffer:
        chunk = stream.recv(65536)
        assert chunk, "connection closed before a whole response"
        buffer += chunk
    head, _, rest = bytes(buffer).partition(b"\r\n\r\n")
    length = next(
        int(line.split(b":", 1)[1])
        for line in head.split(b"\r\n")
        if line.lower().startswith(b"content-length:")
    )
    buffer[:] = rest
    while len(buffer) < length:
        chunk = stream.recv(65536)
        assert chunk, "connection closed in a body"
        buffer += chunk
    body = bytes(buffer[:length])
    del buffer[:length]
    return head, body


def test_pipelined_requests_get_whole_answers_in_order(rig: Rig) -> None:
    job_id = run_job(rig)
    expected = rig.client.get(f"{API}/jobs/{job_id}").content
    requests = b"".join(
        f"{method} {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode()
        for method, path in [
            ("GET", f"{API}/jobs/{job_id}"),
            ("HEAD", f"{API}/jobs/{job_id}"),
            ("GET", f"{API}/jobs/987654"),
            ("GET", f"{API}/jobs/{job_id}"),
        ]
    )
    with socket.create_connection(("127.0.0.1", rig.server.port), timeout=10) as stream:
        stream.sendall(requests)
        buffer = bytearray()
        head, body = read_response(stream, buffer)
        assert head.startswith(b"HTTP/1.1 200 ") and body == expected
        head = bytes(buffer)  # HEAD: a head, no body
        while b"\r\n\r\n" not in head:
            head += stream.recv(65536)
        head, _, rest = head.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 200 ") and f"{len(expected)}".encode() in head
        buffer[:] = rest
        head, body = read_response(stream, buffer)
        assert head.startswith(b"HTTP/1.1 404 ") and b"job_not_found" in body
        head, body = read_response(stream, buffer)
        assert head.startswith(b"HTTP/1.1 200 ") and body == expected


# --------------------------------------------------------------------------- units


class Recorder:
    """The router side of :class:`FastStatus`: records that it was asked."""

    def __init__(self) -> None:
        self.calls = 0

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        self.calls += 1
        await send({"type": "http.response.start", "status": 299, "headers": []})
        await send({"type": "http.response.body", "body": b"routed"})


class Bodies:
    def body(self, job_id: int) -> bytes:
        if job_id != 7:
            raise KeyError(job_id)
        return b'{"id":7}'


def call(app: Any, method: str, path: str, query: bytes = b"", headers: Any = ()) -> list[Any]:
    sent: list[Any] = []

    async def receive() -> Any:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: Any) -> None:
        sent.append(message)

    scope = {
        "type": "http",
        "method": method,
        "path": path,
        "query_string": query,
        "headers": list(headers),
    }
    asyncio.run(app(scope, receive, send))
    return sent


def test_the_fast_path_answers_only_the_plain_successful_poll() -> None:
    router = Recorder()
    app = FastStatus(router, bodies=Bodies())  # type: ignore[arg-type]
    sent = call(app, "GET", f"{API}/jobs/7")
    assert router.calls == 0
    assert sent[0]["status"] == 200
    assert dict(sent[0]["headers"]) == {
        b"content-length": b"8",
        b"content-type": b"application/json",
    }
    assert sent[1]["body"] == b'{"id":7}'
    handed_over = [
        ("GET", f"{API}/jobs/8", b"", ()),  # unknown job
        ("GET", f"{API}/jobs/7", b"x=1", ()),  # a query string
        ("GET", f"{API}/jobs/7", b"", [(b"content-length", b"3")]),  # a body
        ("GET", f"{API}/jobs/7", b"", [(b"transfer-encoding", b"chunked")]),
        ("POST", f"{API}/jobs/7", b"", ()),
        ("GET", f"{API}/jobs/07", b"", ()),
        ("GET", f"{API}/jobs/7/events", b"", ()),
        ("GET", f"{API}/jobs/{2**53 + 1}", b"", ()),
    ]
    for method, path, query, headers in handed_over:
        before = router.calls
        sent = call(app, method, path, query, headers)
        assert router.calls == before + 1 and sent[0]["status"] == 299, (method, path, query)


class Transport:
    def __init__(self) -> None:
        self.writes: list[bytes] = []
        self.closed = False
        self.aborted = False

    def write(self, data: bytes) -> None:
        assert not self.closed
        self.writes.append(bytes(data))

    def is_closing(self) -> bool:
        return self.closed

    def close(self) -> None:
        self.closed = True

    def abort(self) -> None:
        self.aborted = self.closed = True

    def get_extra_info(self, name: str) -> str:
        return f"info:{name}"


def test_writes_of_one_loop_step_leave_as_one() -> None:
    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        raw = Transport()
        writes = _CoalescedWrites(raw, loop)  # type: ignore[arg-type]
        writes.write(b"HTTP/1.1 200 OK\r\n\r\n")
        writes.write(memoryview(b"body"))
        assert raw.writes == []  # held until the end of this step
        await asyncio.sleep(0)
        assert raw.writes == [b"HTTP/1.1 200 OK\r\n\r\nbody"]
        writes.write(b"chunk")  # alone (a streamed chunk): out at the next step
        await asyncio.sleep(0)
        assert raw.writes[-1] == b"chunk"
        writes.write(b"last")
        writes.close()  # sent before the close
        assert raw.writes[-1] == b"last" and raw.closed
        await asyncio.sleep(0)
        assert len(raw.writes) == 3
        assert writes.get_extra_info("peername") == "info:peername"
        dropped = Transport()
        other = _CoalescedWrites(dropped, loop)  # type: ignore[arg-type]
        other.write(b"never")
        other.abort()
        await asyncio.sleep(0)
        assert dropped.writes == [] and dropped.aborted

    asyncio.run(scenario())


class Hub:
    def __init__(self) -> None:
        self.listeners: list[Any] = []

    def add_listener(self, callback: Any) -> None:
        self.listeners.append(callback)

    def remove_listener(self, callback: Any) -> None:
        self.listeners.remove(callback)


def test_each_event_is_serialised_once_for_every_client(monkeypatch: pytest.MonkeyPatch) -> None:
    formatted: list[JobEvent] = []
    original = sse.format_event

    def counting(event: JobEvent) -> str:
        formatted.append(event)
        return original(event)

    monkeypatch.setattr(sse, "format_event", counting)

    async def scenario() -> None:
        bridge = sse.EventBridge(Hub())  # type: ignore[arg-type]
        watchers = [bridge.open(1) for _ in range(20)]
        other_job = bridge.open(2)
        event = JobEvent(1, "step", 3, {"index": 3, "frames_done": 4})
        publisher = threading.Thread(target=bridge._on_event, args=(event,))
        publisher.start()  # the station's thread
        publisher.join()
        late = bridge.open(1)  # connected after the event was published: not for it
        await asyncio.sleep(0)
        items = [w.queue.get_nowait() for w in watchers]
        assert all(item == (event, original(event)) for item in items)
        assert len({id(item) for item in items}) == 1  # one object for all
        assert other_job.queue.empty() and late.queue.empty()
        bridge.close()  # the end of every stream
        await asyncio.sleep(0)
        assert all(w.queue.get_nowait() is None for w in [*watchers, other_job, late])

    asyncio.run(scenario())
    assert formatted == [JobEvent(1, "step", 3, {"index": 3, "frames_done": 4}, formatted[0].at)]
