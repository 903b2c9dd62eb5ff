"""Server configurations over real HTTP (uvicorn in a thread on 127.0.0.1):
a device that is down (503), read-only routes that need a key, CORS off by
default and on for configured origins, a server without API keys.

The "device down" station is real: its rail is a Zaber device on
``socket://127.0.0.1:PORT`` where nothing listens, so opening it fails.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from test_web_support import (
    FINAL,
    KEY,
    InProcessServer,
    closed_port,
    keyed,
    wait_for_state,
    wait_until,
    write_config,
)

from station.config import load_config
from station.orchestrator import Orchestrator
from web.app import create_app

API = "/api/v1"
ORIGIN = "http://127.0.0.1:5173"


def serve(directory: Path, keys: str = KEY, **config_kwargs: object) -> Iterator[InProcessServer]:
    port = closed_port()
    path = write_config(directory, rail_port=f"socket://127.0.0.1:{port}", **config_kwargs)
    config = load_config(path, env={"LFCAL_API_KEYS": keys} if keys else {})
    station = Orchestrator(config, analysis_workers=0).start()
    server = InProcessServer(create_app(config, station=station))
    try:
        assert station.wait_ready(30)
        yield server
    finally:
        server.stop()
        station.close()


@pytest.fixture
def down(tmp_path: Path) -> Iterator[InProcessServer]:
    yield from serve(tmp_path)


@pytest.fixture
def guarded(tmp_path: Path) -> Iterator[InProcessServer]:
    yield from serve(tmp_path, read_only_requires_key=True, cors_origins=(ORIGIN,))


@pytest.fixture
def keyless(tmp_path: Path) -> Iterator[InProcessServer]:
    yield from serve(tmp_path, keys="")


def test_a_device_that_is_down_gives_503_and_jobs_fail_with_the_reason(
    down: InProcessServer,
) -> None:
    c = down.client
    r = c.get(f"{API}/devices")
    assert r.status_code == 503
    body = r.json()
    assert body["code"] == "device_unavailable"
    assert "a device is down" in body["message"] and "127.0.0.1" in body["message"]
    assert body["context"]["devices"]["connected"] is False
    health = c.get(f"{API}/healthz")
    assert health.status_code == 503  # a device is down: the station cannot run jobs
    report = health.json()
    assert report["devices"] == "down" and report["status"] == "degraded"
    assert not report["can_run_jobs"]
    assert any(p.startswith("devices: ") and "127.0.0.1" in p for p in report["problems"])

    job = c.post(f"{API}/jobs", json={"calibrate": False}, headers=keyed())
    assert job.status_code == 202  # the station retries opening the devices for the job
    failed = wait_for_state(c, job.json()["id"], FINAL, 30)
    assert failed["state"] == "failed"
    assert "the devices cannot be opened" in failed["last_error"]


def test_read_only_routes_can_require_the_key(guarded: InProcessServer) -> None:
    c = guarded.client
    for path in ("/jobs", "/jobs/1", "/devices", "/jobs/1/events", "/jobs/1/archive"):
        r = c.get(API + path)
        assert r.status_code == 401, path
        assert r.json()["code"] == "api_key_required"
    assert c.get(f"{API}/jobs", headers=keyed("a-wrong-key-0000000000")).status_code == 403
    assert c.get(f"{API}/jobs", headers=keyed()).json() == {"jobs": []}
    assert c.get(f"{API}/healthz").json()["read_only_requires_key"] is True
    assert c.get("/").status_code == 200  # the page itself holds no data
    schema = c.get(f"{API}/openapi.json").json()
    assert schema["paths"]["/api/v1/jobs"]["get"]["security"] == [{"ApiKey": []}]


def test_cors_answers_only_configured_origins(guarded: InProcessServer) -> None:
    c = guarded.client
    preflight = {
        "Origin": ORIGIN,
        "Access-Control-Request-Method": "POST",
        "Access-Control-Request-Headers": "X-API-Key, Content-Type",
    }
    ok = c.options(f"{API}/jobs", headers=preflight)
    assert ok.status_code == 200
    assert ok.headers["access-control-allow-origin"] == ORIGIN
    assert "x-api-key" in ok.headers["access-control-allow-headers"].lower()
    other = c.options(f"{API}/jobs", headers={**preflight, "Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in other.headers
    simple = c.get(f"{API}/jobs", headers={"Origin": ORIGIN, **keyed()})
    assert simple.headers["access-control-allow-origin"] == ORIGIN


def test_cors_is_off_by_default_and_without_keys_nothing_can_change(
    keyless: InProcessServer,
) -> None:
    c = keyless.client
    preflight = {"Origin": ORIGIN, "Access-Control-Request-Method": "POST"}
    r = c.options(f"{API}/jobs", headers=preflight)
    assert "access-control-allow-origin" not in r.headers
    r = c.get(f"{API}/jobs", headers={"Origin": ORIGIN})
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers

    refused = c.post(f"{API}/jobs", json={}, headers=keyed())
    assert refused.status_code == 403
    assert "no API keys configured" in refused.json()["message"]
    assert "LFCAL_API_KEYS" in refused.json()["message"]
    assert c.post(f"{API}/jobs", json={}).status_code == 401
    assert wait_until(lambda: c.get(f"{API}/jobs").json() == {"jobs": []}, 5, "no jobs")
