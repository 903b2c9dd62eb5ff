"""Bounded requests and honest answers, against real servers over real sockets (loopback).

* descriptors: a real ``python -m web.server`` answers 100 bursts of 40
  concurrent requests (new connections, the server's thread pool churning); its
  open file descriptors (``/proc/PID/fd``) stay flat and the job store never
  holds more than its pool's connections;
* request heads: an unterminated 48 MB header is refused with 431 after at most
  a few hundred kB while status polls keep being answered; too many header
  fields: 431; a head or body that stalls: 408; a silent connection is closed;
* keys: a key in the query string is refused (401) and never reaches the log;
* small items: 415 without Content-Type, ``malformed_json`` for bad UTF-8 and
  10 000-deep JSON, ``white_from_job`` without a white image (422), HEAD on GET
  routes, the API docs page served without any external host.
"""

from __future__ import annotations

import http.client
import re
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest
from test_web_support import (
    FINAL,
    KEY,
    InProcessServer,
    ServerProcess,
    frame_cache,
    keyed,
    wait_for_state,
    wait_until,
    write_config,
)

from station.config import load_config
from station.orchestrator import Orchestrator
from web.app import create_app
from web.http_limits import HttpLimits

API = "/api/v1"
JSON = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config
) -> Iterator[ServerProcess]:
    config = write_config(tmp_path_factory.mktemp("web-hardening"))
    srv = ServerProcess(config, cache=frame_cache(pytestconfig), analysis_workers=0)
    yield srv
    assert srv.stop() == 0, srv.log()


def open_fds(pid: int) -> int:
    return len(list(Path(f"/proc/{pid}/fd").iterdir()))


def test_descriptors_stay_flat_over_100_bursts_of_40_concurrent_requests(
    server: ServerProcess,
) -> None:
    c = server.client
    job = c.post(f"{API}/jobs", json={"start_mm": 30.0, "stop_mm": 30.0}, headers=keyed())
    job_id = job.json()["id"]
    wait_for_state(c, job_id, FINAL, 60)
    paths = [f"{API}/jobs", f"{API}/jobs/{job_id}", f"{API}/healthz", f"{API}/jobs/{job_id}/result"]
    pid = server.proc.pid
    errors: list[str] = []

    url = urlsplit(server.url)
    host, port = url.hostname, url.port
    assert host is not None

    def one(k: int) -> None:
        # 40 new clients per burst, one connection each (the standard library's client:
        # one httpx client shared by threads without keep-alive can close a connection
        # it has just handed to another thread, encode/httpcore#1110)
        connection = http.client.HTTPConnection(host, port, timeout=30)
        try:
            connection.request("GET", paths[k % len(paths)])
            r = connection.getresponse()
            body = r.read()
            if r.status >= 500:
                errors.append(f"{r.status} {body[:200]!r}")
        except (OSError, http.client.HTTPException) as exc:
            errors.append(repr(exc))
        finally:
            connection.close()

    def burst() -> None:
        threads = [threading.Thread(target=one, args=(k,)) for k in range(40)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)

    def settled() -> tuple[int, int]:
        """(descriptors, store connections) once the closed sockets have left the table."""
        last: list[int] = []

        def probe() -> tuple[int, int] | None:
            pooled = c.get(f"{API}/healthz").json()["components"]["store"]["open_connections"]
            now = open_fds(pid)
            same = last == [now]
            last[:] = [now]
            return (now, pooled) if same else None

        return wait_until(probe, 10, "the server's descriptor count to settle", 0.05)

    samples = []
    for _ in range(100):
        burst()
        samples.append(settled())
    assert not errors, errors[:5]
    # The store pool grows lazily up to its bound (8); a pooled SQLite connection
    # holds 1-3 descriptors (database, WAL, and the shared -shm; SQLite's unix VFS
    # also defers closing descriptors while other connections hold locks), so the
    # count may step by one as the pool grows. What must not happen is growth with
    # the bursts: the leak this guards against added ~7 descriptors per burst.
    pooled_max = max(pooled for _, pooled in samples)
    assert pooled_max <= 8, samples
    fds = [f for f, _ in samples]
    assert max(fds) - fds[0] <= 3 * (pooled_max - samples[0][1]) + 1, samples
    # flat over the last half of the bursts, but for what the pool's growth there explains
    # (how early the lazy pool reaches its size depends on scheduling: a CI run reached it
    # only in the last 3 bursts); one descriptor leaked per burst would add 50
    late = samples[len(samples) // 2 :]
    late_fds = [f for f, _ in late]
    late_growth = max(p for _, p in late) - min(p for _, p in late)
    assert max(late_fds) - min(late_fds) <= 3 * late_growth + 1, samples
    assert late_fds[-1] - late[0][0] <= 3 * (late[-1][1] - late[0][1]) + 1, samples
    print(
        f"descriptors over 100 bursts: {fds[0]}..{max(fds)} "
        f"(store connections {samples[0][1]}..{pooled_max})"
    )


def send_raw(port: int, data: bytes, *, read_timeout_s: float = 10.0) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=read_timeout_s) as s:
        s.sendall(data)
        return recv_all(s)


def recv_all(s: socket.socket) -> bytes:
    out = b""
    while True:
        try:
            chunk = s.recv(65536)
        except (ConnectionResetError, TimeoutError):
            return out
        if not chunk:
            return out
        out += chunk


def test_an_unterminated_48_mb_header_is_refused_without_stalling_the_server(
    server: ServerProcess,
) -> None:
    port = int(server.url.rsplit(":", 1)[1])
    polls: list[int] = []
    stop = threading.Event()

    def poll() -> None:
        with httpx.Client(base_url=server.url, timeout=10) as c:
            while not stop.is_set():
                polls.append(c.get(f"{API}/healthz").status_code)
                stop.wait(0.02)

    poller = threading.Thread(target=poll)
    poller.start()
    wait_until(lambda: polls, 10, "the first status poll")
    sent = 0
    answer = b""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
            s.sendall(b"GET /api/v1/healthz HTTP/1.1\r\nHost: x\r\nX-Big: ")
            chunk = b"a" * (1 << 20)
            try:
                for _ in range(48):
                    s.sendall(chunk)
                    sent += len(chunk)
            except (BrokenPipeError, ConnectionResetError):
                pass
            answer = recv_all(s)
        after = len(polls)
        wait_until(lambda: len(polls) >= after + 3, 10, "status polls after the attack")
    finally:
        stop.set()
        poller.join(30)
    assert answer.startswith(b"HTTP/1.1 431 "), answer[:200]
    assert b'"code": "header_too_large"' in answer
    # refused long before the 48 MB arrived (the kernel buffers a few MB at most)
    assert sent < 16 << 20, sent
    assert polls and set(polls) == {200}


def test_too_many_header_fields_is_431(server: ServerProcess) -> None:
    port = int(server.url.rsplit(":", 1)[1])
    fields = "".join(f"X-F{k}: {k}\r\n" for k in range(100))
    answer = send_raw(port, f"GET /api/v1/healthz HTTP/1.1\r\nHost: x\r\n{fields}\r\n".encode())
    assert answer.startswith(b"HTTP/1.1 431 ") and b"too_many_headers" in answer


@pytest.fixture
def quick(tmp_path: Path) -> Iterator[InProcessServer]:
    """A server with 1 s head and body timeouts (devices never opened)."""
    config = load_config(write_config(tmp_path), env={"LFCAL_API_KEYS": KEY})
    station = Orchestrator(config, analysis_workers=0, open_devices_at_start=False).start()
    app = create_app(config, station=station, body_timeout_s=1.0)
    srv = InProcessServer(app, limits=HttpLimits(head_timeout_s=1.0))
    try:
        yield srv
    finally:
        srv.stop()
        station.close()


def test_slow_clients_get_408_and_silent_ones_are_closed(quick: InProcessServer) -> None:
    port = quick.port
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(b"GET /api/v1/healthz HTTP/1.1\r\nHost: x\r\n")  # the head never ends
        t0 = time.monotonic()
        answer = recv_all(s)
        assert answer.startswith(b"HTTP/1.1 408 ") and b"request_timeout" in answer
        assert time.monotonic() - t0 < 8
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        assert recv_all(s) == b""  # nothing sent: closed without an answer
    head = (
        f"POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\nX-API-Key: {KEY}\r\n"
        'Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{"note": '
    )
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(head.encode())  # the body stops after 9 of 100 bytes
        answer = recv_all(s)
    assert b" 408 " in answer.split(b"\r\n", 1)[0] and b"stopped arriving" in answer
    assert quick.client.get(f"{API}/jobs").json()["jobs"] == []


def test_a_key_in_the_query_string_is_refused_and_never_logged(server: ServerProcess) -> None:
    c = server.client
    for name in ("api_key", "key", "token", "API_KEY"):
        r = c.get(f"{API}/jobs", params={name: KEY})
        assert r.status_code == 401, r.text
        body = r.json()
        assert body["code"] == "api_key_in_query" and "X-API-Key header" in body["message"]
        assert KEY not in r.text
    r = c.post(f"{API}/jobs?api_key={KEY}", json={})
    assert r.status_code == 401 and r.json()["code"] == "api_key_in_query"
    wait_until(lambda: "api_key=REDACTED" in server.log(), 10, "the access log line")
    log = server.log()
    assert re.search(r'"GET /api/v1/jobs\?key=REDACTED HTTP/1.1" 401', log), log[-2000:]
    assert KEY not in log


def test_small_request_problems_get_specific_answers(server: ServerProcess) -> None:
    c = server.client
    post = f"{API}/jobs"
    no_type = c.post(post, content=b'{"note": "x"}', headers=keyed())
    assert no_type.status_code == 415, no_type.text
    assert "Content-Type: application/json" in no_type.json()["message"]
    bad_utf8 = c.post(post, content=b'{"note": "\xff\xfe"}', headers={**keyed(), **JSON})
    assert bad_utf8.status_code == 400 and bad_utf8.json()["code"] == "malformed_json"
    assert "not UTF-8" in bad_utf8.json()["message"]
    deep = c.post(post, content=b"[" * 10000 + b"]" * 10000, headers={**keyed(), **JSON})
    assert deep.status_code == 400 and deep.json()["code"] == "malformed_json"
    assert "nested too deeply" in deep.json()["message"]
    # a job without a white image (it only queued and was cancelled)
    queued = c.post(
        post, json={"start_mm": 30.0, "stop_mm": 30.0, "settle_s": 5.0}, headers=keyed()
    )
    blocker = queued.json()["id"]
    waiting = c.post(post, json={"start_mm": 30.0, "stop_mm": 30.0}, headers=keyed()).json()["id"]
    assert c.post(f"{API}/jobs/{waiting}/cancel", headers=keyed()).status_code == 200
    no_white = c.post(post, json={"white_from_job": waiting}, headers=keyed())
    assert no_white.status_code == 422, no_white.text
    fields = no_white.json()["fields"]
    assert fields[0]["field"] == "white_from_job" and "no archive" in fields[0]["message"]
    c.post(f"{API}/jobs/{blocker}/cancel", headers=keyed())
    wait_for_state(c, blocker, FINAL, 60)


def test_head_works_on_get_routes(server: ServerProcess) -> None:
    c = server.client
    job = c.post(f"{API}/jobs", json={"start_mm": 30.0, "stop_mm": 30.0}, headers=keyed())
    job_id = job.json()["id"]
    wait_for_state(c, job_id, FINAL, 60)
    for path in (f"{API}/healthz", f"{API}/jobs", f"{API}/jobs/{job_id}", "/", "/api/docs"):
        get, head = c.get(path), c.head(path)
        assert head.status_code == get.status_code, path
        assert head.content == b"" and head.headers["content-type"] == get.headers["content-type"]
    events = c.head(f"{API}/jobs/{job_id}/events")  # a stream: headers only, at once
    assert events.status_code == 200 and events.headers["content-type"].startswith(
        "text/event-stream"
    )
    allowed = c.put(f"{API}/jobs/{job_id}", headers=keyed())
    assert allowed.status_code == 405 and "HEAD" in allowed.headers["allow"]


def test_the_api_docs_are_served_without_any_external_host(server: ServerProcess) -> None:
    c = server.client
    page = c.get("/api/docs")
    assert page.status_code == 200
    refs = re.findall(r'(?:src|href)="([^"]+)"', page.text) + re.findall(
        r"url: '([^']+)'", page.text
    )
    assert refs and all(r.startswith("/") and not r.startswith("//") for r in refs), refs
    assert not re.search(r"https?://", page.text)
    assert '"validatorUrl": null' in page.text
    for ref in refs:
        r = c.get(ref)
        assert r.status_code == 200 and r.content, ref
    bundle = c.get("/api/docs/static/swagger-ui-bundle.js")
    assert b"SwaggerUIBundle" in bundle.content
