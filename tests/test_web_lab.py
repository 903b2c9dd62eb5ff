"""Lab routes over real HTTP: ``POST /render``, ``report.html``, frame corners, ``/metrics``.

``python -m web.server`` on the simulated station (:mod:`test_web_support`), one
calibrated job; uploads are the job's own raw frames (and frames and results
of other cameras). ``/metrics`` is parsed with prometheus-client's own parser.
"""

from __future__ import annotations

import base64
import copy
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from lab_support import LabData, lab_data
from prometheus_client.parser import text_string_to_metric_families
from test_web_support import (
    FINAL,
    KEY,
    ServerProcess,
    frame_cache,
    keyed,
    wait_for_state,
    write_config,
)

from calibration.export import schema_problems
from calibration.export_model import CalibratedCamera
from station.cli import main
from station.config import load_config
from station.events import JobEvent
from station.orchestrator import Orchestrator
from station.store import JobState, JobStore
from web.media import designed_patch_px
from web.metrics import StationMetrics, fault_kind

API = "/api/v1"
MAX_BODY = 8 * 1024 * 1024


@pytest.fixture(scope="module")
def config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_config(tmp_path_factory.mktemp("web-lab"), max_body_bytes=MAX_BODY)


@pytest.fixture(scope="module")
def server(config: Path, pytestconfig: pytest.Config) -> Iterator[ServerProcess]:
    srv = ServerProcess(config, cache=frame_cache(pytestconfig))
    yield srv
    assert srv.stop() == 0, srv.log()


@pytest.fixture(scope="module")
def job(server: ServerProcess) -> dict[str, Any]:
    """A calibrated job of the configured 10-frame sweep, and an acquisition-only one."""
    c = server.client
    r = c.post(f"{API}/jobs", json={"note": "lab routes"}, headers=keyed())
    assert r.status_code == 202, r.text
    done = wait_for_state(c, r.json()["id"], FINAL, 240)
    assert done["state"] == "succeeded", done["last_error"]
    r = c.post(
        f"{API}/jobs",
        json={"start_mm": 50, "stop_mm": 55, "step_mm": 5, "calibrate": False},
        headers=keyed(),
    )
    assert r.status_code == 202, r.text
    plain = wait_for_state(c, r.json()["id"], FINAL, 120)
    assert plain["state"] == "succeeded"
    result = c.get(f"{API}/jobs/{done['id']}/result").json()
    return {
        "id": done["id"],
        "plain_id": plain["id"],
        "archive": Path(done["archive_dir"]),
        "result": result,
    }


@pytest.fixture(scope="module")
def lab(pytestconfig: pytest.Config) -> LabData:
    return lab_data(pytestconfig)


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def frame_bytes(job: dict[str, Any], index: int = 4) -> bytes:
    return (job["archive"] / "frames" / f"{index:04d}.png").read_bytes()


def post_render(server: ServerProcess, body: dict[str, Any], **kw: Any) -> httpx.Response:
    return server.client.post(f"{API}/render", json=body, headers=kw.pop("headers", keyed()), **kw)


def test_a_station_result_validates_against_the_published_schema(job: dict[str, Any]) -> None:
    assert schema_problems(job["result"]) == []


def test_render_an_uploaded_frame_with_the_jobs_calibration(
    server: ServerProcess, job: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = frame_bytes(job)
    r = post_render(server, {"image_base64": b64(raw), "job_id": job["id"]})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    assert float(r.headers["X-Patch-Size-Px"]) == pytest.approx(job["result"]["patch_size_px"])
    score = float(r.headers["X-Artefact-Score"])
    image = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.dtype == np.uint8 and image.shape[0] > 20
    # the command line renders the same pixels with the same calibration
    (tmp_path / "frame.png").write_bytes(raw)
    (tmp_path / "result.json").write_text(json.dumps(job["result"]))
    out = tmp_path / "cli.png"
    assert (
        main(
            [
                "render",
                str(tmp_path / "frame.png"),
                "--result",
                str(tmp_path / "result.json"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert f"artefact score {score:.3f}" in capsys.readouterr().out
    assert out.read_bytes() == r.content

    # a result sent along instead of a job id; the designed p of the station's optics
    r = post_render(server, {"image_base64": b64(raw), "result": job["result"], "p": "designed"})
    assert r.status_code == 200, r.text
    designed = designed_patch_px(load_config(server_config(server)))
    assert float(r.headers["X-Patch-Size-Px"]) == pytest.approx(designed)
    # p at another object distance from the calibrated model, and a number
    camera = CalibratedCamera.from_result(job["result"])
    r = post_render(
        server, {"image_base64": b64(raw), "job_id": job["id"], "object_distance_mm": 400}
    )
    assert float(r.headers["X-Patch-Size-Px"]) == pytest.approx(camera.patch_at(400.0))
    r = post_render(server, {"image_base64": b64(raw), "job_id": job["id"], "p": 19.5})
    assert float(r.headers["X-Patch-Size-Px"]) == 19.5
    assert float(r.headers["X-Artefact-Score"]) > score


def server_config(server: ServerProcess) -> Path:
    return server.log_path.with_name("station.toml")


def _other_camera_result(result: dict[str, Any]) -> dict[str, Any]:
    """The job's result with the micro-image lattice of another camera of the same sensor
    (the paper preset's 100 px lenses, placed elsewhere)."""
    other = copy.deepcopy(result)
    for name in ("image_grid", "lens_grid"):
        other["mla"][name] = {
            "origin_px": [1000.3, 250.7],
            "pitch_px": 105.49,
            "rotation_deg": 0.15,
        }
    other["mla"]["image_pitch_px"] = 105.49
    return other


@pytest.mark.parametrize(
    ("case", "status", "code", "message"),
    [
        ("truncated", 422, "invalid_image", "the uploaded image is a truncated PNG file"),
        ("not-an-image", 422, "invalid_image", "is not a PNG or TIFF file"),
        ("wrong-size", 422, "frame_mismatch", "is 2000x499 px, the calibration is for 2000x500"),
        (
            "result-of-another-size",
            422,
            "frame_mismatch",
            "is 2000x500 px, the calibration is for 2000x800",
        ),
        (
            "result-of-another-camera",
            422,
            "frame_mismatch",
            "does not show the calibrated micro-image lattice",
        ),
        ("bad-base64", 422, "invalid_request", "image_base64 is not valid base64"),
        ("no-calibration", 422, "invalid_request", "exactly one of job_id"),
        ("both", 422, "invalid_request", "exactly one of job_id"),
        ("unknown-job", 404, "job_not_found", "job 999"),
        ("job-without-result", 409, "result_not_ready", "the job only acquired frames"),
        ("bad-p", 422, "cannot_render", "p must be calibrated, designed or a number"),
        ("no-key", 401, "api_key_required", "API key"),
        ("too-large", 413, "body_too_large", "larger than the 8388608 bytes"),
        ("not-json", 415, "unsupported_media_type", "send JSON"),
    ],
)
def test_render_refuses_bad_uploads_with_one_clear_message(
    server: ServerProcess,
    job: dict[str, Any],
    lab: LabData,
    case: str,
    status: int,
    code: str,
    message: str,
) -> None:
    raw = frame_bytes(job)
    body: dict[str, Any] = {"image_base64": b64(raw), "job_id": job["id"]}
    headers = keyed()
    if case == "truncated":
        body["image_base64"] = b64(raw[: len(raw) // 3])
    elif case == "not-an-image":
        body["image_base64"] = b64(b"GIF89a not a raw frame")
    elif case == "wrong-size":
        pixels = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
        body["image_base64"] = b64(cv2.imencode(".png", pixels[:499])[1].tobytes())
    elif case == "result-of-another-size":
        body = {"image_base64": body["image_base64"], "result": lab.result()}
    elif case == "result-of-another-camera":
        body = {"image_base64": body["image_base64"], "result": _other_camera_result(job["result"])}
    elif case == "bad-base64":
        body["image_base64"] = "%%% not base64 %%%"
    elif case == "no-calibration":
        del body["job_id"]
    elif case == "both":
        body["result"] = job["result"]
    elif case == "unknown-job":
        body["job_id"] = 999
    elif case == "job-without-result":
        body["job_id"] = job["plain_id"]
    elif case == "bad-p":
        body["p"] = "sharpest"
    elif case == "no-key":
        headers = {}
    elif case == "too-large":
        body["image_base64"] = "A" * (MAX_BODY + 16)
    if case == "not-json":
        r = server.client.post(
            f"{API}/render", content=raw, headers={**keyed(), "Content-Type": "image/png"}
        )
    else:
        r = post_render(server, body, headers=headers)
    assert r.status_code == status, r.text
    answer = r.json()
    assert answer["code"] == code and message in answer["message"], answer
    assert "\n" not in answer["message"]


def test_the_jobs_report_page(
    server: ServerProcess, job: dict[str, Any], config: Path, tmp_path: Path
) -> None:
    c = server.client
    r = c.get(f"{API}/jobs/{job['id']}/report.html")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/html")
    html = r.text
    assert "<script" not in html and 'src="http' not in html
    assert html.count('src="data:image/png;base64,') == 5  # 3 plots, calibrated and designed crops
    assert f"{job['result']['b_mm']:.5f}" in html and "Verdict:" in html
    assert "station job" in html and "as recorded in the manifest" in html
    again = c.get(f"{API}/jobs/{job['id']}/report.html")
    assert again.content == r.content  # made once, then served from the cache
    assert c.get(f"{API}/jobs/999/report.html").status_code == 404
    r = c.get(f"{API}/jobs/{job['plain_id']}/report.html")
    assert r.status_code == 409 and r.json()["code"] == "result_not_ready"
    # the same report from the command line, by job id through the station configuration
    out = tmp_path / "report.html"
    assert main(["report", str(job["id"]), "--config", str(config), "--out", str(out)]) == 0
    text = out.read_text()
    assert f"job {job['id']} of {config}" in text and "verified: every file re-read" in text
    assert main(["report", "999", "--config", str(config), "--out", str(out)]) == 2
    assert main(["report", str(job["plain_id"]), "--config", str(config), "--out", str(out)]) == 2


def test_frame_corners_for_the_overlay(server: ServerProcess, job: dict[str, Any]) -> None:
    c = server.client
    r = c.get(f"{API}/jobs/{job['id']}/frames/5/corners")
    assert r.status_code == 200, r.text
    data = r.json()
    assert data["analysed"] and (data["width"], data["height"]) == (2000, 500)
    assert data["rail_mm"] == pytest.approx(55.0, abs=0.01)
    assert len(data["standard"]) >= 4 and len(data["reference"]) >= 4
    # the corners are those of the stored result, frame 5
    frame = next(f for f in job["result"]["frames"] if f["index"] == 5)
    expected = np.array(sorted((row[2], row[3]) for row in frame["corners"]["standard"]))
    got = np.array(sorted(map(tuple, data["standard"])))
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, atol=1e-9)
    assert all(0 <= x < 2000 and 0 <= y < 500 for x, y in data["standard"] + data["reference"])
    assert c.get(f"{API}/jobs/{job['id']}/frames/10/corners").status_code == 404
    assert c.get(f"{API}/jobs/999/frames/0/corners").status_code == 404


def _metrics(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_metrics_in_the_prometheus_text_format(server: ServerProcess, job: dict[str, Any]) -> None:
    r = server.client.get("/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain; version=0.0.4")
    m = _metrics(r.text)
    assert m[("lfcal_jobs", (("state", "succeeded"),))] >= 2
    assert m[("lfcal_jobs", (("state", "running"),))] == 0
    assert m[("lfcal_frames_captured_total", ())] >= 12  # 10 + 2 frames
    assert m[("lfcal_step_seconds_count", ())] >= 12
    assert 0 < m[("lfcal_step_seconds_sum", ())] < 60 * m[("lfcal_step_seconds_count", ())]
    assert (
        m[("lfcal_step_seconds_bucket", (("le", "+Inf"),))] == m[("lfcal_step_seconds_count", ())]
    )
    assert m[("lfcal_analysis_backlog_frames", ())] == 0
    assert m[("lfcal_jobs_failed_total", ())] == 0
    assert any(name == "lfcal_info" for name, _ in m)
    # a second scrape does not count the steps twice
    again = _metrics(server.client.get("/metrics").text)
    assert again[("lfcal_step_seconds_count", ())] == m[("lfcal_step_seconds_count", ())]


def test_metrics_count_faults_and_failed_jobs_from_station_events(tmp_path: Path) -> None:
    """The station's event hub feeds the counters (no hardware: the orchestrator is not started)."""
    config = load_config(write_config(tmp_path))
    store = JobStore(tmp_path / "jobs.sqlite3")
    station = Orchestrator(config, store=store, analysis_workers=0, open_devices_at_start=False)
    metrics = StationMetrics(station)
    try:
        job, _ = store.create_job({"frames": 3}, archive_root=tmp_path, frames_total=3)
        store.transition(job.id, JobState.RUNNING, "started")
        for i in range(3):
            station.hub.publish(JobEvent(job.id, "step", i, {"index": i}))
        station.hub.publish(JobEvent(job.id, "step", 0, {"index": 0, "replayed": True}))
        for action in ("retry (noise on the line)", "retry (lost trigger)", "rehome (lost ref)"):
            station.hub.publish(
                JobEvent(job.id, "fault", None, {"what": "x", "error": "e", "action": action})
            )
        store.transition(job.id, JobState.FAILED, "stalled")
        station.hub.publish(JobEvent(job.id, "state", None, {"state": "failed"}))
        m = _metrics(metrics.exposition().decode())
        assert m[("lfcal_frames_captured_total", ())] == 3  # replays are not new frames
        assert m[("lfcal_faults_total", (("kind", "retry"),))] == 2
        assert m[("lfcal_faults_total", (("kind", "rehome"),))] == 1
        assert m[("lfcal_jobs_failed_total", ())] == 1
        assert m[("lfcal_jobs", (("state", "failed"),))] == 1
        assert m[("lfcal_jobs", (("state", "queued"),))] == 0
    finally:
        metrics.close()
        store.close()
    assert fault_kind({"kind": "CameraTimeout", "action": "retry"}) == "CameraTimeout"
    assert fault_kind({}) == "unknown"
    assert KEY  # the servers of this module accept the shared test key
