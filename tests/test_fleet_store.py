"""The job store on a real PostgreSQL server (and the same checks on SQLite), schema
migrations, per-station ownership, result versions, and start-up against an
unreachable database or object store.

PostgreSQL: a throw-away cluster started by the test (:mod:`tests.fleet_servers`),
on 127.0.0.1 and a socket in its temporary directory.
"""

from __future__ import annotations

import io
import json
import os
import sqlite3
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import redirect_stdout
from pathlib import Path
from typing import Any

import psycopg
import pytest
from test_station_helpers import write_config

from bench.fleet_servers import (
    PostgresServer,
    free_port,
    give_station_lock_back,
    postgres_server,
    take_station_lock,
)
from station.db import StoreUnavailable
from station.jobs_cli import jobs_main
from station.ownership import (
    OWNERSHIP_KEY,
    WATCHDOG_INTERVAL_S,
    PostgresOwnership,
    StationBusy,
    live_stations,
    station_alive,
)
from station.result_versions import add_result_version, jobs_with_software, result_versions
from station.schema import HEAD, SchemaTooNew, current_revision
from station.store import (
    DuplicateStep,
    IdempotencyConflict,
    InvalidTransition,
    JobState,
    JobStore,
    StepRecord,
)

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pg() -> Iterator[PostgresServer]:
    with postgres_server() as server:
        yield server


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh empty database of each backend."""
    if request.param == "sqlite":
        return str(tmp_path / "jobs.sqlite3")
    server: PostgresServer = request.getfixturevalue("pg")
    return server.create_database(f"t_{uuid.uuid4().hex[:12]}")


def _step(job_id: int, index: int) -> StepRecord:
    return StepRecord(job_id, index, index * 5.0, index * 5.0 + 0.001, f"frames/{index:04d}.png",
                      f"{index:064x}", 1.0, 2.0, 3.0)  # fmt: skip


def test_the_same_store_code_runs_on_both_backends(database: str, tmp_path: Path) -> None:
    with JobStore(database, station_id="st-a") as store:
        job, created = store.create_job(
            {"start_mm": 0}, archive_root=tmp_path, frames_total=3, idempotency_key="k1",
            camera_serial="CAM-1",
        )  # fmt: skip
        assert created and job.id == 1 and job.state is JobState.QUEUED
        assert (job.station_id, job.camera_serial, job.archive_url) == ("st-a", "CAM-1", None)
        again, created = store.create_job(
            {"start_mm": 0}, archive_root=tmp_path, frames_total=3, idempotency_key="k1"
        )
        assert not created and again.id == job.id
        with pytest.raises(IdempotencyConflict):
            store.create_job({"start_mm": 1}, archive_root=tmp_path, frames_total=3,
                             idempotency_key="k1")  # fmt: skip
        store.transition(job.id, JobState.RUNNING, "started")
        with pytest.raises(InvalidTransition):
            store.transition(job.id, JobState.QUEUED, "not allowed from running")
        for i in range(3):
            store.record_step(_step(job.id, i))
        with pytest.raises(DuplicateStep):
            store.record_step(_step(job.id, 1))
        store.set_step_summary(job.id, 2, {"La_mm": 1.5})
        store.transition(job.id, JobState.SUCCEEDED, "done", result={"a_mm": 10.0})
        got = store.get_job(job.id, with_result=True)
        assert got.result == {"a_mm": 10.0} and got.has_result
        assert [s.index for s in store.steps(job.id)] == [0, 1, 2]
        assert store.step(job.id, 2) is not None and store.step(job.id, 2).summary == {"La_mm": 1.5}  # type: ignore[union-attr]
        assert [(t.from_state, t.to_state) for t in store.transitions(job.id)] == [
            (None, JobState.QUEUED),
            (JobState.QUEUED, JobState.RUNNING),
            (JobState.RUNNING, JobState.SUCCEEDED),
        ]
        store.probe_write()
        assert store.health.ok
    # a second station on the same database: its own jobs, the fleet view sees both
    with JobStore(database, station_id="st-b") as other:
        b, _ = other.create_job({}, archive_root=tmp_path, frames_total=1, camera_serial="CAM-2")
        assert b.id == 2 and b.station_id == "st-b"
        assert [j.id for j in other.list_jobs()] == [1, 2]
        assert [j.id for j in other.list_jobs(station="st-a")] == [1]
        assert [j.id for j in other.list_jobs(camera_serial="CAM-2")] == [2]
        assert other.list_jobs(station="st-a", camera_serial="CAM-2") == []
        assert [j.id for j in other.list_jobs(states={JobState.QUEUED}, station="st-b")] == [2]
        assert {s["station_id"]: s["jobs"] for s in other.stations()} == {"st-a": 1, "st-b": 1}
    # lfcal jobs: the same fleet view from the command line
    for args, expected in (
        (["--station", "st-a"], [(1, "st-a", "CAM-1")]),
        (["--camera-serial", "CAM-2"], [(2, "st-b", "CAM-2")]),
        ([], [(1, "st-a", "CAM-1"), (2, "st-b", "CAM-2")]),
    ):
        out = io.StringIO()
        with redirect_stdout(out):
            assert jobs_main(["--db", database, "--json", *args]) == 0
        listed = [
            (j["id"], j["station_id"], j["camera_serial"]) for j in json.loads(out.getvalue())
        ]
        assert listed == expected


def test_result_versions_stay_side_by_side(database: str, tmp_path: Path) -> None:
    with JobStore(database, station_id="st") as store:
        job, _ = store.create_job({}, archive_root=tmp_path, frames_total=1)
        store.transition(job.id, JobState.RUNNING, "started")
        original = {"a_mm": 10.0, "software": {"version": "0.1.0"}}
        store.transition(job.id, JobState.SUCCEEDED, "done", result=original)
        v1 = add_result_version(store, job.id, {"a_mm": 10.1, "software": {"version": "0.2.0"}})
        v2 = add_result_version(store, job.id, {"a_mm": 10.2, "software": {"version": "0.3.0"}})
        assert (v1.version, v2.version) == (1, 2)
        versions = result_versions(store, job.id, with_results=True)
        assert [(v.version, v.software_version, v.source) for v in versions] == [
            (0, "0.1.0", "station"),
            (1, "0.2.0", "recalibrate"),
            (2, "0.3.0", "recalibrate"),
        ]
        assert [v.result["a_mm"] for v in versions] == [10.0, 10.1, 10.2]  # type: ignore[index]
        assert store.get_job(job.id, with_result=True).result == original  # not replaced
        only = result_versions(store, job.id, software_version="0.2.0")
        assert [v.version for v in only] == [1]
        assert jobs_with_software(store, "0.3.0") == {job.id}


LEGACY_SCHEMA = """
CREATE TABLE jobs (id INTEGER PRIMARY KEY AUTOINCREMENT, state TEXT NOT NULL,
  request TEXT NOT NULL, created_at REAL NOT NULL, updated_at REAL NOT NULL, result TEXT,
  last_error TEXT, archive_dir TEXT NOT NULL, frames_total INTEGER NOT NULL,
  idempotency_key TEXT UNIQUE);
CREATE INDEX jobs_state ON jobs(state);
CREATE TABLE transitions (seq INTEGER PRIMARY KEY AUTOINCREMENT,
  job_id INTEGER NOT NULL REFERENCES jobs(id), from_state TEXT, to_state TEXT NOT NULL,
  at REAL NOT NULL, reason TEXT NOT NULL);
CREATE TABLE steps (job_id INTEGER NOT NULL REFERENCES jobs(id), idx INTEGER NOT NULL,
  commanded_mm REAL NOT NULL, actual_mm REAL NOT NULL, file TEXT NOT NULL,
  sha256 TEXT NOT NULL, started_at REAL NOT NULL, captured_at REAL NOT NULL,
  written_at REAL NOT NULL, summary TEXT, PRIMARY KEY (job_id, idx));
INSERT INTO jobs VALUES (1, 'succeeded', '{}', 1.0, 2.0, '{"a_mm": 9.5}', NULL, '/d/job-1', 2, NULL);
INSERT INTO transitions VALUES (1, 1, NULL, 'queued', 1.0, 'submitted');
INSERT INTO steps VALUES (1, 0, 0.0, 0.0, 'frames/0000.png', 'ab', 1.0, 1.0, 1.0, NULL);
PRAGMA user_version = 1;
"""


def test_a_database_of_the_single_station_version_is_migrated_with_its_data(
    tmp_path: Path,
) -> None:
    path = tmp_path / "old.sqlite3"
    conn = sqlite3.connect(path)
    conn.executescript(LEGACY_SCHEMA)
    conn.close()
    with JobStore(path, station_id="lab-1") as store:
        assert current_revision(store.pool) == HEAD
        job = store.get_job(1, with_result=True)
        assert (job.state, job.result, job.station_id) == (
            JobState.SUCCEEDED,
            {"a_mm": 9.5},
            "lab-1",
        )
        assert [s.sha256 for s in store.steps(1)] == ["ab"]
        new, _ = store.create_job({}, archive_root=tmp_path, frames_total=1)
        assert new.id == 2


def _set_revision(database: str, revision: str) -> None:
    if database.startswith("postgresql://"):
        with psycopg.connect(database, autocommit=True) as conn:
            conn.execute("UPDATE alembic_version SET version_num = %s", (revision,))
    else:
        conn = sqlite3.connect(database)
        with conn:
            conn.execute("UPDATE alembic_version SET version_num = ?", (revision,))
        conn.close()


def test_a_schema_newer_than_the_software_is_refused_and_left_alone(
    database: str, tmp_path: Path
) -> None:
    with JobStore(database, station_id="st") as store:
        store.create_job({}, archive_root=tmp_path, frames_total=1)
    _set_revision(database, "0099")
    with pytest.raises(SchemaTooNew, match=r"schema version 0099, newer than this lfcal-station"):
        JobStore(database, station_id="st")
    # nothing was changed: still 0099, the job still there
    if database.startswith("postgresql://"):
        with psycopg.connect(database) as conn:
            assert conn.execute("SELECT version_num FROM alembic_version").fetchone() == ("0099",)
            assert conn.execute("SELECT COUNT(*) FROM jobs").fetchone() == (1,)
    else:
        conn = sqlite3.connect(database)
        assert conn.execute("SELECT version_num FROM alembic_version").fetchone() == ("0099",)
        conn.close()
    proc = subprocess.run(
        [sys.executable, "-m", "station.cli", "jobs", "--db", database],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "schema version 0099" in lines[0] and "upgrade" in lines[0]


def test_two_stations_starting_together_migrate_once(pg: PostgresServer) -> None:
    url = pg.create_database(f"t_{uuid.uuid4().hex[:12]}")
    code = (
        "import sys; from station.store import JobStore; "
        "JobStore(sys.argv[1], station_id=sys.argv[2]).close()"
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code, url, name], cwd=ROOT, stderr=subprocess.PIPE, text=True
        )  # fmt: skip
        for name in ("a", "b", "c")
    ]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    with psycopg.connect(url) as conn:
        assert conn.execute("SELECT version_num FROM alembic_version").fetchall() == [(HEAD,)]


def test_one_process_per_station_on_a_shared_database(pg: PostgresServer) -> None:
    url = pg.url()
    first = PostgresOwnership(url, "bench-7")
    try:
        with pytest.raises(StationBusy) as busy:
            PostgresOwnership(url, "bench-7")
        text = str(busy.value)
        assert "station 'bench-7' is already running" in text
        assert f"pid {os.getpid()}" in text  # the holder, from pg_stat_activity
        other = PostgresOwnership(url, "bench-8")  # another station: no conflict
        other.release()
    finally:
        first.release()
    again = PostgresOwnership(url, "bench-7")  # released: free again
    again.release()


def test_a_released_station_can_be_started_again_at_once(pg: PostgresServer) -> None:
    """release() unlocks before it returns: closing the session alone frees the lock only
    when the server's backend has exited, and on a loaded machine a station started again
    right away found itself "already running" (seen on CI; 1 of the first cycles under load
    here)."""
    url = pg.url()
    for _ in range(50):
        PostgresOwnership(url, "bench-9").release()
    held = PostgresOwnership(url, "bench-9")
    with pytest.raises(StationBusy):
        PostgresOwnership(url, "bench-9")
    held.release()


def test_an_unreachable_database_is_one_line_naming_it() -> None:
    url = f"postgresql://lfcal:secret@127.0.0.1:{free_port()}/jobs"
    with pytest.raises(StoreUnavailable) as exc:
        JobStore(url, station_id="x")
    text = str(exc.value)
    assert f"postgresql://lfcal@127.0.0.1:{url.rsplit(':', 1)[1].split('/')[0]}/jobs" in text
    assert "unreachable" in text and "secret" not in text


def _serve(config: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "station.cli", "serve", "--config", str(config), "--port", "0"],
        capture_output=True, text=True, timeout=120, cwd=ROOT,
        env=dict(os.environ, **(env or {})),
    )  # fmt: skip


def _with_storage(directory: Path, storage: str) -> Path:
    path = write_config(directory)
    text = path.read_text(encoding="utf-8")
    head = text.split("[storage]")[0]
    path.write_text(head + '[storage]\ndata_dir = "data"\n' + storage, encoding="utf-8")
    return path


@pytest.mark.parametrize("what", ["database", "object store"])
def test_serve_refuses_to_start_without_its_database_or_object_store(
    what: str, tmp_path: Path, pg: PostgresServer
) -> None:
    dead = free_port()
    if what == "database":
        storage = f'database = "postgresql://lfcal@127.0.0.1:{dead}/jobs"\nstation_id = "s1"\n'
        env: dict[str, str] = {}
    else:
        storage = (
            f'database = "{pg.url()}"\nstation_id = "s1"\narchive_url = "s3://archives/lab"\n'
            f'[storage.s3]\nendpoint_url = "http://127.0.0.1:{dead}"\nconnect_timeout_s = 1\n'
        )
        env = {"AWS_ACCESS_KEY_ID": "x", "AWS_SECRET_ACCESS_KEY": "y"}
    proc = _serve(_with_storage(tmp_path, storage), env)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.startswith("lfcal serve:")]
    assert len(lines) == 1, proc.stderr
    if what == "database":
        assert (
            f"the job database postgresql://lfcal@127.0.0.1:{dead}/jobs is unreachable" in lines[0]
        )
    else:
        assert (
            f"the object store s3://archives/lab at http://127.0.0.1:{dead} is unreachable"
            in lines[0]
        )
    # the station's ownership died with the refused start: the database is free
    PostgresOwnership(pg.url(), "s1").release()


def test_a_shared_database_splits_ownership_a_sqlite_file_does_not(
    database: str, tmp_path: Path
) -> None:
    with JobStore(database, station_id="old-name") as first:
        job, _ = first.create_job({}, archive_root=tmp_path, frames_total=1)
    with JobStore(database, station_id="new-name") as second:
        mine = second.list_jobs(station=second.own_station)
        if database.startswith("postgresql://"):
            # another station's job: never recovered, run or acted on here
            assert not second.owns(job) and mine == []
        else:  # one station per SQLite file (its lock): every job in it is this station's
            assert second.owns(job) and [j.id for j in mine] == [job.id]


def _wait(condition: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.1)


def test_live_stations_follow_their_ownership_locks_even_after_kill_9(
    pg: PostgresServer, tmp_path: Path
) -> None:
    url = pg.create_database(f"t_{uuid.uuid4().hex[:12]}")
    for station in ("bench-7", "bench-8"):
        with JobStore(url, station_id=station) as store:
            store.create_job({"start_mm": 0}, archive_root=tmp_path, frames_total=3)
    reader = JobStore(url, station_id="reader")
    holder = None
    try:
        assert live_stations(reader) == set()
        own = PostgresOwnership(url, "bench-7")
        # bench-8 runs in another process, which is then killed without a chance to clean up
        code = (
            "import sys, time; from station.ownership import PostgresOwnership; "
            f"PostgresOwnership({url!r}, 'bench-8'); print('held', flush=True); time.sleep(120)"
        )
        holder = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT,
                                  stdout=subprocess.PIPE, text=True)  # fmt: skip
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert live_stations(reader) == {"bench-7", "bench-8"}
        assert station_alive(reader, "bench-8", live_stations(reader)) is True
        holder.kill()
        holder.wait(10)
        _wait(lambda: live_stations(reader) == {"bench-7"}, 10, "bench-8's lock to go")
        assert station_alive(reader, "bench-8", live_stations(reader)) is False
        own.release()
        _wait(lambda: live_stations(reader) == set(), 10, "bench-7's lock to go")
        # the reader lists jobs with the liveness of their station
        out = io.StringIO()
        with redirect_stdout(out):
            assert jobs_main(["--db", url, "--json"]) == 0
        assert [j["station_alive"] for j in json.loads(out.getvalue())] == [False, False]
    finally:
        if holder is not None and holder.poll() is None:
            holder.kill()
        reader.close()


def test_live_stations_are_not_known_on_sqlite(tmp_path: Path) -> None:
    with JobStore(tmp_path / "jobs.sqlite3", station_id="solo") as store:
        assert live_stations(store) is None
        # a SQLite file has one station: the one in this process
        assert station_alive(store, "solo", None) is True


def test_a_station_that_loses_its_ownership_says_so_and_takes_it_back(pg: PostgresServer) -> None:
    url = pg.url()
    own = PostgresOwnership(url, "bench-9")
    try:
        with psycopg.connect(url, autocommit=True) as admin:
            # the station's session ends (a database restart) and another process takes the lock
            take_station_lock(admin, "bench-9")
            _wait(lambda: own.problem is not None, 3 * WATCHDOG_INTERVAL_S, "the loss noticed")
            assert "the ownership of station 'bench-9' is lost" in str(own.problem)
            assert "already running" in str(own.problem)
            give_station_lock_back(admin, "bench-9")
            _wait(lambda: own.problem is None, 3 * WATCHDOG_INTERVAL_S, "the lock taken back")
        reader = JobStore(url, station_id="reader")
        try:
            holders = reader.stations_holding_advisory_lock(OWNERSHIP_KEY)
        finally:
            reader.close()
        assert holders <= {"bench-9"}  # no job of bench-9 here; the query runs
    finally:
        own.release()
