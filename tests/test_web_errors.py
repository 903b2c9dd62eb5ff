"""Bad input over real HTTP: the right status, one error shape, a message that says
what to fix -- and nothing already recorded changes (the job list over the API and
the job database itself are compared before and after)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_web_support import (
    FINAL,
    OTHER_KEY,
    ServerProcess,
    frame_cache,
    keyed,
    wait_for_state,
    write_config,
)

from station.store import JobStore

API = "/api/v1"
JSON = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config
) -> Iterator[tuple[ServerProcess, Path]]:
    directory = tmp_path_factory.mktemp("web-errors")
    config = write_config(directory, max_body_bytes=4096)
    srv = ServerProcess(config, cache=frame_cache(pytestconfig), analysis_workers=0)
    yield srv, directory / "data" / "lfcal.sqlite3"
    assert srv.stop() == 0, srv.log()


def database_snapshot(db: Path) -> dict[str, Any]:
    """Every recorded job, transition and step, from the database file."""
    with JobStore(db) as store:
        jobs = store.list_jobs()
        return {
            "jobs": [(j.id, j.state, j.updated_at, j.request, j.last_error) for j in jobs],
            "transitions": [store.transitions(j.id) for j in jobs],
            "steps": [store.steps(j.id) for j in jobs],
        }


# (what, method, path, request kwargs, status, code, words the message must contain)
Case = tuple[str, str, str, dict[str, Any], int, str, tuple[str, ...]]


def cases(done: int) -> list[Case]:
    """Bad requests against a server whose job ``done`` has finished (2 frames)."""
    post = {"headers": {**keyed(), **JSON}}
    return [
        ("no key", "POST", "/jobs", {"json": {}}, 401, "api_key_required", ("X-API-Key",)),
        (
            "wrong key",
            "POST",
            "/jobs",
            {"json": {}, "headers": keyed(OTHER_KEY)},
            403,
            "api_key_rejected",
            ("not accepted",),
        ),
        (
            "no key on cancel",
            "POST",
            f"/jobs/{done}/cancel",
            {},
            401,
            "api_key_required",
            ("X-API-Key",),
        ),
        (
            "malformed JSON",
            "POST",
            "/jobs",
            {"content": b'{"start_mm": 10,', **post},
            400,
            "malformed_json",
            ("not valid JSON", "character"),
        ),
        (
            "wrong types",
            "POST",
            "/jobs",
            {"json": {"start_mm": "ten", "calibrate": "yes", "note": 5}, **post},
            422,
            "invalid_request",
            ("start_mm: must be a valid number", '"ten"', "calibrate", "note"),
        ),
        (
            "a number as text is not a number",
            "POST",
            "/jobs",
            {"json": {"step_mm": "1"}, **post},
            422,
            "invalid_request",
            ("step_mm", "valid number"),
        ),
        (
            "out of the rail's travel",
            "POST",
            "/jobs",
            {"json": {"start_mm": -5, "stop_mm": 150}, **post},
            422,
            "invalid_request",
            ("start_mm: must be ≥ 0 mm, got -5", "stop_mm: must be ≤ 100 mm, got 150"),
        ),
        (
            "stop below start",
            "POST",
            "/jobs",
            {"json": {"start_mm": 60, "stop_mm": 40}, **post},
            422,
            "invalid_request",
            ("stop_mm", "must not be below start_mm (60 mm)"),
        ),
        (
            "too many frames",
            "POST",
            "/jobs",
            {"json": {"start_mm": 0, "stop_mm": 100, "step_mm": 0.01}, **post},
            422,
            "invalid_request",
            ("step_mm", "at most 200", "step of at least"),
        ),
        (
            "zero step",
            "POST",
            "/jobs",
            {"json": {"step_mm": 0}, **post},
            422,
            "invalid_request",
            ("step_mm: must be ≥ 0.001 mm, got 0",),
        ),
        (
            "unknown field",
            "POST",
            "/jobs",
            {"json": {"start": 10}, **post},
            422,
            "invalid_request",
            ("start: unknown field", "start_mm"),
        ),
        (
            "not an object",
            "POST",
            "/jobs",
            {"json": [10, 20], **post},
            422,
            "invalid_request",
            ("must be a JSON object",),
        ),
        (
            "white image from an unknown job",
            "POST",
            "/jobs",
            {"json": {"white_from_job": 999999}, **post},
            422,
            "invalid_request",
            ("white_from_job", "no job 999999"),
        ),
        (
            "not JSON",
            "POST",
            "/jobs",
            {"content": b"start_mm=10", "headers": {**keyed(), "Content-Type": "text/plain"}},
            415,
            "unsupported_media_type",
            ("Content-Type: application/json",),
        ),
        (
            "oversize body",
            "POST",
            "/jobs",
            {"json": {"note": "x" * 5000}, **post},
            413,
            "body_too_large",
            ("4096 bytes", "max_body_bytes"),
        ),
        (
            "oversize chunked body",
            "POST",
            "/jobs",
            {"content": iter([b'{"note": "', b"y" * 3000, b"z" * 3000, b'"}']), **post},
            413,
            "body_too_large",
            ("4096 bytes",),
        ),
        (
            "bad idempotency key",
            "POST",
            "/jobs",
            {"json": {}, "headers": {**keyed(), "Idempotency-Key": "has spaces"}},
            422,
            "invalid_request",
            ("Idempotency-Key", "pattern"),
        ),
        ("unknown job", "GET", "/jobs/999999", {}, 404, "job_not_found", ("no job 999999",)),
        (
            "unknown job, pause",
            "POST",
            "/jobs/999999/pause",
            {"headers": keyed()},
            404,
            "job_not_found",
            ("no job 999999", "GET /api/v1/jobs"),
        ),
        ("unknown job, events", "GET", "/jobs/424242/events", {}, 404, "job_not_found", ()),
        ("job id 0", "GET", "/jobs/0", {}, 422, "invalid_request", ("job_id", "≥ 1")),
        ("job id text", "GET", "/jobs/abc", {}, 422, "invalid_request", ("job_id", "integer")),
        (
            "job id too large",
            "GET",
            f"/jobs/{2**64}",
            {},
            422,
            "invalid_request",
            ("job_id", "≤"),
        ),
        (
            "unknown state filter",
            "GET",
            "/jobs?state=done",
            {},
            422,
            "invalid_request",
            ("state", "succeeded"),
        ),
        (
            "frame not recorded",
            "GET",
            f"/jobs/{done}/frames/7",
            {},
            404,
            "frame_not_found",
            ("no recorded frame 7", "frames_done"),
        ),
        (
            "pause a finished job",
            "POST",
            f"/jobs/{done}/pause",
            {"headers": keyed()},
            409,
            "invalid_transition",
            ("succeeded", "cannot pause"),
        ),
        (
            "cancel a finished job",
            "POST",
            f"/jobs/{done}/cancel",
            {"headers": keyed()},
            409,
            "invalid_transition",
            ("succeeded is final",),
        ),
        (
            "result of an acquisition-only job",
            "GET",
            f"/jobs/{done}/result",
            {},
            409,
            "result_not_ready",
            ("only acquired frames",),
        ),
        (
            "plot without a result",
            "GET",
            f"/jobs/{done}/plots/focus.png",
            {},
            409,
            "result_not_ready",
            (),
        ),
        (
            "unknown patch choice",
            "GET",
            f"/jobs/{done}/render.png?p=best",
            {},
            422,
            "invalid_request",
            ("p:", "calibrated", "designed"),
        ),
        ("unknown route", "GET", "/nothing-here", {}, 404, "not_found", ("/api/v1",)),
        (
            "wrong method",
            "GET",
            f"/jobs/{done}/pause",
            {},
            405,
            "method_not_allowed",
            ("GET is not allowed",),
        ),
    ]


def test_bad_input_gets_the_right_status_and_changes_nothing(
    server: tuple[ServerProcess, Path],
) -> None:
    srv, db = server
    c = srv.client
    r = c.post(
        f"{API}/jobs",
        json={"start_mm": 50.0, "stop_mm": 55.0, "calibrate": False},
        headers=keyed(),
    )
    assert r.status_code == 202, r.text
    done = r.json()["id"]
    assert wait_for_state(c, done, FINAL, 60)["state"] == "succeeded"
    before_api = c.get(f"{API}/jobs").json()
    before_db = database_snapshot(db)

    failures = []
    for what, method, path, kwargs, status, code, words in cases(done):
        response = c.request(method, API + path, **kwargs)
        try:
            body = response.json()
        except json.JSONDecodeError:
            failures.append(f"{what}: not JSON: {response.text[:200]!r}")
            continue
        problems = []
        if response.status_code != status:
            problems.append(f"status {response.status_code} != {status}")
        if set(body) != {"status", "code", "message", "fields", "context"}:
            problems.append(f"error shape {sorted(body)}")
        elif body["code"] != code or body["status"] != response.status_code:
            problems.append(f"code {body['code']!r} != {code!r}")
        else:
            text = body["message"] + " " + json.dumps(body["fields"], ensure_ascii=False)
            problems += [f"{w!r} not in the message" for w in words if w not in text]
            if status == 422 and not body["fields"]:
                problems.append("no field-level messages")
        if problems:
            failures.append(f"{what}: {'; '.join(problems)}: {body}")
    assert not failures, "\n".join(failures)

    assert c.get(f"{API}/jobs").json() == before_api
    assert database_snapshot(db) == before_db


def test_a_body_within_the_limit_is_still_accepted(server: tuple[ServerProcess, Path]) -> None:
    srv, _ = server
    c = srv.client
    note = "n" * 400  # within [server] max_body_bytes = 4096 and the 500-character limit
    r = c.post(
        f"{API}/jobs",
        content=json.dumps({"start_mm": 70.0, "stop_mm": 70.0, "calibrate": False, "note": note}),
        headers={**keyed(), **JSON},
    )
    assert r.status_code == 202, r.text
    assert wait_for_state(c, r.json()["id"], FINAL, 60)["request"]["note"] == note
    too_long = c.post(f"{API}/jobs", json={"note": "n" * 501}, headers=keyed())
    assert too_long.status_code == 422
    assert too_long.json()["fields"][0]["field"] == "note"
    assert "at most 500 characters" in too_long.json()["fields"][0]["message"]


def test_an_empty_post_runs_the_configured_default_sweep(
    server: tuple[ServerProcess, Path],
) -> None:
    srv, _ = server
    r = srv.client.post(f"{API}/jobs", headers=keyed())
    assert r.status_code == 202, r.text
    job = r.json()
    assert (job["request"]["start_mm"], job["request"]["stop_mm"]) == (30.0, 75.0)
    cancel = srv.client.post(f"{API}/jobs/{job['id']}/cancel", headers=keyed())
    assert cancel.status_code == 200
    assert wait_for_state(srv.client, job["id"], FINAL, 60)["state"] == "cancelled"
