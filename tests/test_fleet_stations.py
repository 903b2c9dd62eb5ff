"""Two station processes (``lfcal serve``) sharing one PostgreSQL database and one S3
object store, both real servers started by the test on 127.0.0.1.

Each station runs a short simulated sweep (the ``rotated`` camera, 10 frames of
2000×500 px, frames shared with the web tests' cache) to a correct result; the
fleet view filters by station and camera; a station refuses to act on another's
job; every frame reaches the object store with the SHA-256 the station recorded;
an archive whose local copy is gone is served from the object store by any
station; ``kill -9`` of one station mid-sweep leaves its job to that station alone,
which recovers and finishes it at its next start; an object-store outage
mid-sweep (moto's server stopped, then started again) loses no frame.
"""

from __future__ import annotations

import hashlib
import io
import os
import signal
import time
import uuid
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest
from test_web_support import (
    FINAL,
    ServerProcess,
    frame_cache,
    keyed,
    wait_for_state,
    wait_until,
    write_config,
)

from bench.fleet_servers import (
    S3_KEY_ID,
    S3_REGION,
    S3_SECRET,
    PostgresServer,
    S3Server,
    give_station_lock_back,
    postgres_server,
    s3_server,
    take_station_lock,
)
from station.store import JobState, JobStore

API = "/api/v1"
BUCKET = "lfcal-archives"
TRUTH_B_MM, TRUTH_A_MM, TRUTH_FOCUS_RAIL_MM = 2.45, 2.45 / 0.225, 52.37


@pytest.fixture(scope="module")
def pg() -> Iterator[PostgresServer]:
    with postgres_server() as server:
        yield server


@pytest.fixture(scope="module")
def s3() -> Iterator[S3Server]:
    with s3_server() as server:
        server.create_bucket(BUCKET)
        yield server


def fleet_entry(server: ServerProcess, job_id: int) -> dict[str, Any]:
    """``job_id`` as ``server``'s fleet view (``GET /jobs``) lists it."""
    jobs = server.client.get(f"{API}/jobs").json()["jobs"]
    return next(j for j in jobs if j["id"] == job_id)


def fresh_fleet(pytestconfig: pytest.Config, pg: PostgresServer) -> tuple[Path, str, str]:
    """The frame cache, a new database on the shared server and a new object prefix."""
    database = pg.create_database(f"fleet_{uuid.uuid4().hex[:10]}")
    return frame_cache(pytestconfig), database, f"run-{uuid.uuid4().hex[:8]}"


CAMERA_SEEDS = {"a": 1, "b": 7}
"""The two stations of the fleet tests, ``line-a`` and ``line-b``: their cameras' seeds."""


def station_config(
    tmp_path: Path,
    name: str,
    database: str,
    s3: S3Server,
    *,
    prefix: str,
    keep_local: bool = True,
) -> Path:
    """The web tests' simulated station ``line-<name>`` (in ``tmp_path/<name>``) with a
    shared database and object store (the simulated camera's serial is
    ``SIM-<scene>-<seed>``; rendered frames do not depend on the seed, so the stations
    share the frame cache)."""
    directory, station_id, camera_seed = tmp_path / name, f"line-{name}", CAMERA_SEEDS[name]
    path = write_config(directory)
    text = path.read_text(encoding="utf-8")
    text = text.replace("seed = 0\n", f"seed = {camera_seed}\n", 1)
    storage = (
        "[storage]\n"
        'data_dir = "data"\n'
        f'database = "{database}"\n'
        f'station_id = "{station_id}"\n'
        f'archive_url = "s3://{BUCKET}/{prefix}"\n'
        f"keep_local_archives = {'true' if keep_local else 'false'}\n"
        "[storage.s3]\n"
        f'endpoint_url = "{s3.endpoint}"\n'
        f'region = "{S3_REGION}"\n'
        f'access_key_id = "{S3_KEY_ID}"\n'
        f'secret_access_key = "{S3_SECRET}"\n'
        "upload_retry_s = 0.2\n"
        "connect_timeout_s = 1\n"
    )
    head, rest = text.split("[storage]\n", 1)
    tail = rest[rest.index("[server]") :]
    path.write_text(head + storage + "\n" + tail, encoding="utf-8")
    return path


def submit(server: ServerProcess) -> int:
    response = server.client.post(f"{API}/jobs", json={}, headers=keyed())
    assert response.status_code == 202, response.text
    return int(response.json()["id"])


def assert_correct(result: dict[str, Any]) -> None:
    assert result["b_mm"] == pytest.approx(TRUTH_B_MM, rel=2e-3)
    assert result["a_mm"] == pytest.approx(TRUTH_A_MM, rel=3e-3)
    assert result["focus"]["rail_mm"] == pytest.approx(TRUTH_FOCUS_RAIL_MM, abs=1.0)


def wait_uploaded(database: str, job_id: int, timeout_s: float = 90.0) -> Any:
    def probe() -> Any:
        with JobStore(database, station_id="test-reader") as store:
            job = store.get_job(job_id)
        return job if job.archive_uploaded_at is not None else None

    return wait_until(probe, timeout_s, f"job {job_id}'s archive to be uploaded", 0.2)


def assert_every_frame_in_object_store(database: str, s3: S3Server, job_id: int) -> None:
    """Every recorded step's frame is in the bucket with the SHA-256 the station
    recorded, and so are the white image and the manifest."""
    with JobStore(database, station_id="test-reader") as store:
        job = store.get_job(job_id)
        steps = store.steps(job_id)
    assert job.archive_url is not None and steps
    prefix = job.archive_url.split(f"s3://{BUCKET}/", 1)[1]
    client = s3.client()
    keys = {
        o["Key"][len(prefix) + 1 :]
        for page in client.get_paginator("list_objects_v2").paginate(
            Bucket=BUCKET, Prefix=prefix + "/"
        )
        for o in page.get("Contents", [])
    }
    assert {"sweep.json", "white.png"} <= keys
    assert {s.file for s in steps} <= keys
    for step in steps:
        head = client.head_object(Bucket=BUCKET, Key=f"{prefix}/{step.file}")
        assert head["Metadata"]["sha256"] == step.sha256, step.file
        body = client.get_object(Bucket=BUCKET, Key=f"{prefix}/{step.file}")["Body"].read()
        assert hashlib.sha256(body).hexdigest() == step.sha256


def test_two_stations_share_one_database_and_one_object_store(
    tmp_path: Path, pytestconfig: pytest.Config, pg: PostgresServer, s3: S3Server
) -> None:
    cache, database, prefix = fresh_fleet(pytestconfig, pg)
    a = ServerProcess(
        station_config(tmp_path, "a", database, s3, prefix=prefix),
        cache=cache,
    )
    try:
        b = ServerProcess(
            station_config(tmp_path, "b", database, s3, prefix=prefix, keep_local=False),
            cache=cache,
        )
        try:
            job_a, job_b = submit(a), submit(b)
            done_a = wait_for_state(a.client, job_a, FINAL, timeout_s=240)
            done_b = wait_for_state(b.client, job_b, FINAL, timeout_s=240)
            assert done_a["state"] == "succeeded", (done_a, a.log())
            assert done_b["state"] == "succeeded", (done_b, b.log())
            serial_a, serial_b = done_a["camera_serial"], done_b["camera_serial"]
            assert (done_a["station_id"], serial_a) == ("line-a", "SIM-rotated-1")
            assert (done_b["station_id"], serial_b) == ("line-b", "SIM-rotated-7")
            assert_correct(a.client.get(f"{API}/jobs/{job_a}/result").json())
            assert_correct(b.client.get(f"{API}/jobs/{job_b}/result").json())

            # the fleet view: either station lists both, filtered by station or camera
            def ids(server: ServerProcess, **params: str) -> list[int]:
                got = server.client.get(f"{API}/jobs", params=params)
                assert got.status_code == 200, got.text
                return [j["id"] for j in got.json()["jobs"]]

            assert ids(a) == ids(b) == sorted([job_a, job_b])
            assert ids(a, station="line-b") == [job_b]
            assert ids(b, camera_serial=serial_a) == [job_a]
            assert ids(a, station="line-a", camera_serial=serial_b) == []

            # a station never acts on another station's job
            refused = b.client.post(f"{API}/jobs/{job_a}/resume", headers=keyed())
            assert refused.status_code == 409
            assert "belongs to station 'line-a'" in refused.json()["message"]

            # every frame reached the object store, verified against the recorded SHA-256
            wait_uploaded(database, job_a)
            uploaded_b = wait_uploaded(database, job_b)
            assert_every_frame_in_object_store(database, s3, job_a)
            assert_every_frame_in_object_store(database, s3, job_b)
            # B keeps no local copy: B, and A too, serve its archive from the object store
            assert not Path(uploaded_b.archive_dir).exists()
            for server in (b, a):
                response = server.client.get(f"{API}/jobs/{job_b}/archive")
                assert response.status_code == 200, response.text
                names = zipfile.ZipFile(io.BytesIO(response.content)).namelist()
                assert sum(n.split("/", 1)[1].startswith("frames/") for n in names) == 10
            frame = a.client.get(f"{API}/jobs/{job_b}/frames/3?width=200")
            assert frame.status_code == 200 and frame.headers["content-type"] == "image/png"
        finally:
            assert b.stop() == 0, b.log()
    finally:
        assert a.stop() == 0, a.log()


def test_kill_9_of_one_station_mid_sweep_is_recovered_by_that_station_alone(
    tmp_path: Path, pytestconfig: pytest.Config, pg: PostgresServer, s3: S3Server
) -> None:
    cache, database, prefix = fresh_fleet(pytestconfig, pg)
    config_a = station_config(tmp_path, "a", database, s3, prefix=prefix)
    a = ServerProcess(config_a, cache=cache)
    b = ServerProcess(
        station_config(tmp_path, "b", database, s3, prefix=prefix),
        cache=cache,
    )
    try:
        job_a = submit(a)
        wait_until(
            lambda: a.client.get(f"{API}/jobs/{job_a}").json()["frames_done"] >= 3,
            120, "3 frames of station A",
        )  # fmt: skip
        # the fleet view (on B) shows A's job with A alive
        assert fleet_entry(b, job_a)["station_alive"] is True
        os.kill(a.proc.pid, signal.SIGKILL)
        a.proc.wait(30)
        assert a.stop() == -signal.SIGKILL

        # B goes on with its own work and leaves A's job alone; its fleet view says that
        # A's job is left running by a station that is down (no live worker)
        job_b = submit(b)
        wait_until(lambda: fleet_entry(b, job_a)["station_alive"] is False, 30, "A seen down")
        done_b = wait_for_state(b.client, job_b, FINAL, timeout_s=240)
        assert done_b["state"] == "succeeded", b.log()
        seen = fleet_entry(b, job_a)
        assert seen["state"] == "running" and seen["station_id"] == "line-a"
        assert seen["station_alive"] is False and fleet_entry(b, job_b)["station_alive"] is True

        # A restarts: its job is interrupted with its frames verified, then resumed
        a = ServerProcess(config_a, cache=cache)
        recovered = a.client.get(f"{API}/jobs/{job_a}").json()
        assert recovered["state"] == "interrupted", recovered
        assert fleet_entry(b, job_a)["station_alive"] is True
        assert "verified by SHA-256" in recovered["last_error"]
        assert a.client.post(f"{API}/jobs/{job_a}/resume", headers=keyed()).status_code == 200
        done_a = wait_for_state(a.client, job_a, FINAL, timeout_s=240)
        assert done_a["state"] == "succeeded", a.log()
        assert done_a["frames_done"] == 10
        assert_correct(a.client.get(f"{API}/jobs/{job_a}/result").json())
        with JobStore(database, station_id="test-reader") as store:
            moves = [(t.from_state, t.to_state) for t in store.transitions(job_a)]
        assert moves == [
            (None, JobState.QUEUED),
            (JobState.QUEUED, JobState.RUNNING),
            (JobState.RUNNING, JobState.INTERRUPTED),
            (JobState.INTERRUPTED, JobState.QUEUED),
            (JobState.QUEUED, JobState.RUNNING),
            (JobState.RUNNING, JobState.SUCCEEDED),
        ]
        wait_uploaded(database, job_a)
        assert_every_frame_in_object_store(database, s3, job_a)
    finally:
        a.stop()
        b.stop()


def test_an_object_store_outage_mid_sweep_loses_no_frame(
    tmp_path: Path, pytestconfig: pytest.Config, pg: PostgresServer, s3: S3Server
) -> None:
    cache, database, prefix = fresh_fleet(pytestconfig, pg)
    a = ServerProcess(
        station_config(tmp_path, "a", database, s3, prefix=prefix),
        cache=cache,
    )
    stopped = False
    try:
        job = submit(a)
        wait_until(
            lambda: a.client.get(f"{API}/jobs/{job}").json()["frames_done"] >= 2,
            120, "2 frames",
        )  # fmt: skip
        s3.stop()  # the object store goes away mid-sweep
        stopped = True
        done = wait_for_state(a.client, job, FINAL, timeout_s=240)
        assert done["state"] == "succeeded", a.log()  # the sweep does not wait for uploads
        with JobStore(database, station_id="test-reader") as store:
            assert store.get_job(job).archive_uploaded_at is None

        def archives_state(state: str) -> dict[str, Any] | None:
            health = a.client.get(f"{API}/healthz").json()
            return health if health["components"]["archives"]["state"] == state else None

        health = wait_until(lambda: archives_state("behind"), 30, "the upload backlog in /healthz")
        assert health["status"] == "degraded" and health["can_run_jobs"]  # jobs go on
        assert job in health["components"]["archives"]["pending_jobs"]
        assert "is unreachable" in health["components"]["archives"]["error"]
        s3.start()
        stopped = False
        wait_uploaded(database, job)
        wait_until(lambda: archives_state("ok"), 30, "/healthz to show the uploads done")
        assert_every_frame_in_object_store(database, s3, job)
        assert_correct(a.client.get(f"{API}/jobs/{job}/result").json())
    finally:
        if stopped:
            s3.start()
        assert a.stop() == 0, a.log()


def test_a_station_that_loses_its_ownership_stops_and_starts_nothing_until_it_is_back(
    tmp_path: Path, pytestconfig: pytest.Config, pg: PostgresServer, s3: S3Server
) -> None:
    cache, database, prefix = fresh_fleet(pytestconfig, pg)
    a = ServerProcess(
        station_config(tmp_path, "a", database, s3, prefix=prefix),
        cache=cache,
    )
    try:
        health = a.client.get(f"{API}/healthz")
        assert health.status_code == 200
        assert health.json()["components"]["store"]["ownership"] == "held"
        # a slow sweep (2 s settling per step): the watchdog (5 s) notices the loss mid-sweep
        response = a.client.post(f"{API}/jobs", json={"settle_s": 2.0}, headers=keyed())
        assert response.status_code == 202, response.text
        running = int(response.json()["id"])
        wait_until(
            lambda: a.client.get(f"{API}/jobs/{running}").json()["frames_done"] >= 2,
            120, "2 frames",
        )  # fmt: skip
        with psycopg.connect(database, autocommit=True) as admin:
            # the station's session ends (as in a database restart) and another process
            # takes the station's lock: it may recover and run line-a's jobs now, so
            # line-a stops its sweep and starts nothing
            take_station_lock(admin, "line-a")
            stopped = wait_for_state(a.client, running, FINAL, timeout_s=60)
            assert stopped["state"] == "interrupted", stopped
            assert "ownership of station 'line-a' is lost" in stopped["last_error"]
            wait_until(lambda: a.client.get(f"{API}/healthz").status_code == 503, 30, "503")
            lost = a.client.get(f"{API}/healthz").json()
            assert lost["components"]["store"]["ownership"] == "lost" and not lost["can_run_jobs"]
            assert any("ownership of station 'line-a' is lost" in p for p in lost["problems"])
            queued = submit(a)
            wait_until(
                lambda: any(
                    "queued jobs wait until the ownership is back" in f["message"]
                    for f in a.client.get(f"{API}/healthz").json()["components"]["worker"][
                        "recent_faults"
                    ]
                ),
                30,
                "the worker to hold the queue",
            )
            assert a.client.get(f"{API}/jobs/{queued}").json()["state"] == "queued"
            released_at = time.time()
            give_station_lock_back(admin, "line-a")
        wait_until(lambda: a.client.get(f"{API}/healthz").status_code == 200, 30, "lock back")
        assert a.client.post(f"{API}/jobs/{running}/resume", headers=keyed()).status_code == 200
        for job in (queued, running):
            done = wait_for_state(a.client, job, FINAL, timeout_s=240)
            assert done["state"] == "succeeded" and done["frames_done"] == 10, a.log()
            assert_correct(a.client.get(f"{API}/jobs/{job}/result").json())
        with JobStore(database, station_id="test-reader") as store:
            started = [t.at for t in store.transitions(queued) if t.to_state is JobState.RUNNING]
        assert started and started[0] >= released_at  # queued, not run, while the lock was lost
    finally:
        a.stop()
