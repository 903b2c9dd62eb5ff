"""End to end over real HTTP: ``python -m web.server`` on the simulated station.

A calibration is started with ``POST /api/v1/jobs``, polled to the end and its
result, frame previews, plots, rendered images and archive fetched; the events
stream replays from ``Last-Event-ID``; pause, resume and cancel act at step
boundaries; an ``Idempotency-Key`` makes a POST repeatable.
"""

from __future__ import annotations

import io
import json
import threading
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from test_web_support import (
    FINAL,
    KEY,
    OTHER_KEY,
    ServerProcess,
    frame_cache,
    keyed,
    read_events,
    wait_for_state,
    wait_until,
    write_config,
)

from calibration.archive import SweepArchive

API = "/api/v1"


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config
) -> Iterator[ServerProcess]:
    config = write_config(tmp_path_factory.mktemp("web-api"))
    srv = ServerProcess(config, cache=frame_cache(pytestconfig))
    yield srv
    assert srv.stop() == 0, srv.log()


@pytest.fixture(scope="module")
def finished_job(server: ServerProcess) -> dict[str, Any]:
    """A job of the configured 10-frame sweep, run to its end."""
    c = server.client
    r = c.post(f"{API}/jobs", json={"note": "end-to-end"}, headers=keyed())
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    assert r.headers["Location"] == f"{API}/jobs/{job_id}"
    seen: list[int] = []

    def done() -> dict[str, Any] | None:
        job = c.get(r.headers["Location"]).json()
        seen.append(job["frames_done"])
        return job if job["state"] in FINAL else None

    job = wait_until(done, 180, f"job {job_id} to finish", 0.05)
    assert job["state"] == "succeeded", job["last_error"]
    assert seen == sorted(seen) and job["frames_done"] == job["frames_total"] == 10
    return job


def png(response: httpx.Response) -> np.ndarray:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(response.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None
    return image


def test_a_calibration_started_over_http_ends_with_its_result(
    server: ServerProcess, finished_job: dict[str, Any]
) -> None:
    c = server.client
    job_id = finished_job["id"]
    assert finished_job["request"]["frames"] == 10 and finished_job["request"]["note"]
    result = c.get(f"{API}/jobs/{job_id}/result").json()
    # the simulator's camera "rotated": b = 2.45 mm, focus plane at rail 52.37 mm
    assert result["b_mm"] == pytest.approx(2.45, rel=2e-3)
    assert result["Q"] == pytest.approx(result["b_mm"] / result["a_mm"], rel=1e-9)
    assert result["focus"]["rail_mm"] == pytest.approx(52.37, abs=1.0)
    assert result["uncertainty"]["a_mm"] > 0 and result["patch_size_px"] > 0
    assert len(result["frames"]) == 10
    assert sum(f["La_mm"] is not None for f in result["frames"]) >= 8  # both corners in view
    on_disk = json.loads((Path(finished_job["archive_dir"]) / "result.json").read_text())
    assert on_disk["a_mm"] == result["a_mm"]

    listed = c.get(f"{API}/jobs", params={"state": "succeeded"}).json()["jobs"]
    assert job_id in [j["id"] for j in listed]
    assert job_id not in [j["id"] for j in c.get(f"{API}/jobs?state=queued").json()["jobs"]]


def test_frames_plots_and_rendered_images_are_pngs(
    server: ServerProcess, finished_job: dict[str, Any]
) -> None:
    c = server.client
    base = f"{API}/jobs/{finished_job['id']}"
    preview = png(c.get(f"{base}/frames/3"))
    assert preview.shape == (160, 640)  # 2000×500 scaled to 640 px wide
    assert png(c.get(f"{base}/frames/9", params={"width": 100})).shape == (25, 100)
    assert preview.std() > 10  # a picture, not a flat field
    for name in ("focus", "disparity"):
        assert png(c.get(f"{base}/plots/{name}.png")).shape[1] >= 400
    calibrated = png(c.get(f"{base}/render.png", params={"p": "calibrated"}))
    designed = png(c.get(f"{base}/render.png?p=designed"))
    assert calibrated.shape[0] > 20 and designed.shape[0] > 20
    # the checkerboard: both dark and light squares in the rendered image
    assert (calibrated < 60).mean() > 0.2 and (calibrated > 190).mean() > 0.2
    assert png(c.get(f"{base}/render.png?p=calibrated&frame=0")).size > 0
    bad = c.get(f"{base}/render.png?p=sharpest")
    assert bad.status_code == 422 and "calibrated" in bad.json()["message"]


def test_the_archive_streams_as_a_zip_that_verifies(
    server: ServerProcess, finished_job: dict[str, Any], tmp_path: Path
) -> None:
    with server.client.stream("GET", f"{API}/jobs/{finished_job['id']}/archive") as r:
        assert r.status_code == 200
        assert r.headers["content-type"] == "application/zip"
        assert "content-length" not in r.headers  # streamed
        data = b"".join(r.iter_bytes())
    name = Path(finished_job["archive_dir"]).name
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        names = set(zf.namelist())
        assert {f"{name}/sweep.json", f"{name}/white.png", f"{name}/frames/0009.png"} <= names
        zf.extractall(tmp_path)
    archive = SweepArchive.open(tmp_path / name)
    check = archive.check(decode=True)
    assert check.ok, check.problems()
    assert archive.indices == list(range(10))


def test_events_replay_from_last_event_id(
    server: ServerProcess, finished_job: dict[str, Any]
) -> None:
    c = server.client
    url = f"{API}/jobs/{finished_job['id']}/events"
    every = read_events(c.get(url))
    steps = [e for e in every if e[1] == "step"]
    assert [e[0] for e in steps] == [str(i) for i in range(10)]
    assert all(e[2]["data"]["summary"]["La_mm"] is not None for e in steps[2:8])
    assert every[-1][1] == "state" and every[-1][2]["data"]["state"] == "succeeded"

    later = read_events(c.get(url, headers={"Last-Event-ID": "6"}))
    assert [e[0] for e in later if e[1] == "step"] == ["7", "8", "9"]
    assert later[-1][2]["data"]["state"] == "succeeded"
    assert [e[0] for e in read_events(c.get(url, params={"after": 8})) if e[0]] == ["9"]


class EventCollector:
    """Reads a job's SSE stream in a thread until the server ends it."""

    def __init__(self, url: str) -> None:
        self.events: list[tuple[str | None, str, dict[str, Any]]] = []
        self.started = threading.Event()
        self.ended = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(url,), daemon=True)
        self._thread.start()

    def _run(self, url: str) -> None:
        try:
            with httpx.stream("GET", url, timeout=60) as r:
                self.started.set()
                block: list[str] = []
                for line in r.iter_lines():
                    if line:
                        block.append(line)
                        continue
                    text = "\n".join(block) + "\n\n"
                    block = []
                    self.events += read_events(httpx.Response(200, text=text))
        finally:
            self.ended.set()

    def states(self) -> list[str]:
        return [e[2]["data"]["state"] for e in self.events if e[1] == "state"]


def test_pause_resume_cancel_over_http_with_live_events(server: ServerProcess) -> None:
    c = server.client
    r = c.post(f"{API}/jobs", json={"settle_s": 0.3, "calibrate": False}, headers=keyed())
    assert r.status_code == 202
    job_id = r.json()["id"]
    live = EventCollector(f"{server.url}{API}/jobs/{job_id}/events")
    running = wait_until(
        lambda: (j := c.get(f"{API}/jobs/{job_id}").json())["frames_done"] >= 2 and j,
        60,
        "two frames",
    )
    assert running["state"] == "running" and running["rail_mm"] is not None
    assert running["eta_s"] is not None
    assert c.get(f"{API}/jobs/{job_id}/result").status_code == 409
    busy = c.get(f"{API}/devices").json()
    assert busy["busy"] is True and busy["connected"] is True

    assert c.post(f"{API}/jobs/{job_id}/pause", headers=keyed()).status_code == 200
    paused = wait_for_state(c, job_id, {"paused", *FINAL}, 60)
    assert paused["state"] == "paused" and 2 <= paused["frames_done"] < 10
    again = c.post(f"{API}/jobs/{job_id}/pause", headers=keyed())
    assert again.status_code == 200 and again.json()["state"] == "paused"

    assert c.post(f"{API}/jobs/{job_id}/resume", headers=keyed()).status_code == 200
    wait_for_state(c, job_id, {"running", *FINAL}, 60)
    assert c.post(f"{API}/jobs/{job_id}/cancel", headers=keyed()).status_code == 200
    cancelled = wait_for_state(c, job_id, FINAL, 60)
    assert cancelled["state"] == "cancelled"

    for action in ("pause", "resume", "cancel"):
        refused = c.post(f"{API}/jobs/{job_id}/{action}", headers=keyed())
        assert refused.status_code == 409, action
        body = refused.json()
        assert body["code"] == "invalid_transition" and "cancelled" in body["message"]
    assert c.get(f"{API}/jobs/{job_id}/result").json()["code"] == "result_not_ready"

    assert live.ended.wait(30), "the event stream did not end with the job"
    ids = [int(e[0]) for e in live.events if e[1] == "step"]
    assert ids == list(range(len(ids))) and len(ids) == cancelled["frames_done"]
    assert live.states()[-1] == "cancelled" and "paused" in live.states()
    assert any(e[1] == "phase" for e in live.events)


def test_an_idempotency_key_returns_the_same_job(server: ServerProcess) -> None:
    c = server.client
    body = {"start_mm": 40.0, "stop_mm": 45.0, "calibrate": False}
    headers = {**keyed(), "Idempotency-Key": "operator-42-run-1"}
    first = c.post(f"{API}/jobs", json=body, headers=headers)
    assert first.status_code == 202
    count = len(c.get(f"{API}/jobs").json()["jobs"])
    second = c.post(f"{API}/jobs", json=body, headers=headers)
    assert second.status_code == 202 and second.json()["id"] == first.json()["id"]
    conflict = c.post(f"{API}/jobs", json={**body, "stop_mm": 50.0}, headers=headers)
    assert conflict.status_code == 409 and "Idempotency-Key" in conflict.json()["message"]
    assert len(c.get(f"{API}/jobs").json()["jobs"]) == count
    wait_for_state(c, first.json()["id"], FINAL, 60)


def test_devices_health_and_the_operator_page(server: ServerProcess) -> None:
    c = server.client
    health = c.get(f"{API}/healthz").json()
    assert health["status"] == "ok" and health["devices"] in ("connected", "busy")
    devices = wait_until(
        lambda: (r := c.get(f"{API}/devices")).status_code == 200 and r.json(), 60, "devices"
    )
    assert devices["rail"]["homed"] is True and devices["camera"]["sensor_px"] == [2000, 500]
    page = c.get("/")
    assert page.status_code == 200 and "run-form" in page.text
    assert c.get("/static/app.js").status_code == 200
    schema = c.get(f"{API}/openapi.json").json()
    assert "ApiKey" in schema["components"]["securitySchemes"]


def test_api_keys_are_checked_and_never_logged(server: ServerProcess) -> None:
    c = server.client
    body = {"start_mm": 60.0, "stop_mm": 60.0, "calibrate": False}
    assert c.post(f"{API}/jobs", json=body).status_code == 401
    wrong = c.post(f"{API}/jobs", json=body, headers=keyed(OTHER_KEY))
    assert wrong.status_code == 403 and OTHER_KEY not in wrong.text
    ok = c.post(f"{API}/jobs", json=body, headers=keyed())
    assert ok.status_code == 202 and KEY not in ok.text
    wait_for_state(c, ok.json()["id"], FINAL, 60)
    log = server.log()
    assert "POST /api/v1/jobs" in log  # the access log is there ...
    assert KEY not in log and OTHER_KEY not in log  # ... without the keys
