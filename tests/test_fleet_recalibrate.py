"""``lfcal recalibrate`` on a Dask LocalCluster over stored archives, local and in S3.

The archive is a small sweep made with ``lfcal simulate`` (``rotated`` camera,
12 frames of 640×400 px, its ``truth.json``), cached between runs. Three
succeeded jobs of two stations carry an old result of software ``0.0.1``; one
job's archive exists only in a moto S3 server on 127.0.0.1, so a Dask worker has
to download it (checked against the stored SHA-256). Each job gets a new result
version beside the old one, close to the simulator's truth; a second run skips
what this software version already did, ``--all`` redoes it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.fleet_servers import S3Server, s3_server
from calibration.version import software_version
from station.archive_sync import archive_files
from station.objectstore import ObjectStore
from station.result_versions import result_versions
from station.store import JobState, JobStore

ROOT = Path(__file__).resolve().parents[1]
OLD = {"a_mm": 10.5, "b_mm": 2.40, "Q": 0.2286, "focus": {"object_distance_mm": 430.0},
       "software": {"name": "lfcal-station", "version": "0.0.1"}}  # fmt: skip


def lfcal(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> Any:
    return subprocess.run(
        [sys.executable, "-m", "station.cli", *args],
        capture_output=True, text=True, timeout=timeout, cwd=ROOT,
        env=dict(os.environ, **(env or {})),
    )  # fmt: skip


@pytest.fixture(scope="module")
def sweep(pytestconfig: pytest.Config) -> Path:
    """A small simulated sweep archive (rendered once, kept in pytest's cache)."""
    cache = Path(pytestconfig.cache.mkdir("lfcal-fleet-sweeps"))
    path = cache / "rotated-640x400-12"
    if not (path / "sweep.json").is_file():
        proc = lfcal("simulate", str(path), "--preset", "rotated", "--frames", "12",
                     "--step-mm", "8", "--width", "640", "--height", "400", "--seed", "3",
                     "--overwrite")  # fmt: skip
        assert proc.returncode == 0, proc.stderr
    return path


@pytest.fixture(scope="module")
def s3() -> Iterator[S3Server]:
    with s3_server() as server:
        server.create_bucket("recal")
        yield server


def _succeeded_job(store: JobStore, archive: Path) -> int:
    job, _ = store.create_job({}, archive_root=archive.parent, frames_total=12)
    store.transition(job.id, JobState.RUNNING, "started")
    store.transition(job.id, JobState.SUCCEEDED, "done", result=OLD)
    return job.id


def test_recalibrate_stores_new_versions_and_shows_what_changed(
    tmp_path: Path, sweep: Path, s3: S3Server
) -> None:
    db = tmp_path / "fleet.sqlite3"
    truth = json.loads((sweep / "truth.json").read_text())
    with JobStore(db, station_id="st-a") as store:
        local_ids = [_succeeded_job(store, tmp_path / "a") for _ in range(2)]
        for job_id in local_ids:
            shutil.copytree(sweep, store.get_job(job_id).archive_dir)
    # station B's archive is only in the object store
    with JobStore(db, station_id="st-b", archive_url="s3://recal/fleet") as store:
        remote_id = _succeeded_job(store, tmp_path / "b")
        job = store.get_job(remote_id)
    assert job.archive_url == f"s3://recal/fleet/st-b/{job.archive_dir.name}"
    objects = ObjectStore("s3://recal", {"endpoint_url": s3.endpoint, "region": "us-east-1",
                                         "access_key_id": "testing-key-id",
                                         "secret_access_key": "testing-secret-key"})  # fmt: skip
    for rel in archive_files(sweep):
        objects.put_file(f"fleet/st-b/{job.archive_dir.name}/{rel}", sweep / rel)
    assert not job.archive_dir.exists()

    env = {**s3.env(), "HOME": str(tmp_path / "home")}  # the archive cache goes under HOME
    proc = lfcal("recalibrate", "--database", str(db), "--workers", "2", env=env)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "3 archives on a LocalCluster of 2 workers on 127.0.0.1" in proc.stderr
    version = software_version()
    table = proc.stdout.splitlines()
    assert table[0].split()[:5] == ["job", "station", "camera", "software", "version"]
    rows = {int(line.split()[0]): line for line in table[1:4]}
    assert set(rows) == {*local_ids, remote_id}
    for job_id, line in rows.items():
        assert f"0.0.1 -> {version}" in line
        assert ("st-b" if job_id == remote_id else "st-a") in line
        assert "10.50000 -> " in line  # the old a, then the new one with the change
    assert "3 of 3 recalibrated" in proc.stdout

    with JobStore(db, station_id="") as store:
        for job_id in [*local_ids, remote_id]:
            versions = result_versions(store, job_id, with_results=True)
            assert [(v.version, v.software_version) for v in versions] == [
                (0, "0.0.1"),
                (1, version),
            ]
            assert versions[0].result == OLD  # the old result is kept as it was
            new = versions[1].result
            assert new is not None
            # a new calibration of that archive: near the truth by its own uncertainty
            # (this window has no reference corner, so F comes from the data sheet and
            # a and b carry its tolerance, σ about 1.5 %), and far nearer than the old one
            for key in ("a_mm", "b_mm"):
                error = abs(new[key] - truth[key])
                assert error <= 2.0 * new["uncertainty"][key], (key, new[key], truth[key])
                assert error < abs(OLD[key] - truth[key]) / 3.0, (key, new[key])
            assert new["focus"]["object_distance_mm"] == pytest.approx(
                truth["focus"]["object_distance_mm"], abs=2.0 * new["focus"]["uncertainty_mm"]
            )
    # the worker fetched B's archive into the cache, checked against the stored SHA-256
    cached = tmp_path / "home" / ".cache" / "lfcal" / "archives" / "recal" / "fleet" / "st-b"
    assert (cached / job.archive_dir.name / "sweep.json").is_file()

    again = lfcal("recalibrate", "--database", str(db), env=env)
    assert again.returncode == 0 and "nothing to recalibrate" in again.stdout
    later = lfcal("recalibrate", "--database", str(db), "--since", "2999-01-01", "--all", env=env)
    assert later.returncode == 0 and "nothing to recalibrate" in later.stdout
    redo = lfcal("recalibrate", "--database", str(db), "--all", "--station", "st-b",
                 "--workers", "1", "--json", env=env)  # fmt: skip
    assert redo.returncode == 0, redo.stderr
    payload = json.loads(redo.stdout)
    assert [(p["job_id"], p["version"], p["previous_software_version"]) for p in payload] == [
        (remote_id, 2, version)
    ]
    listing = lfcal("jobs", "--db", str(db), str(remote_id), "--results")
    assert listing.returncode == 0
    assert [ln.split()[:2] for ln in listing.stdout.splitlines()] == [
        ["version", "0"],
        ["version", "1"],
        ["version", "2"],
    ]


def test_recalibrate_bad_input_is_one_line(tmp_path: Path) -> None:
    bad_date = lfcal("recalibrate", "--database", str(tmp_path / "x.sqlite3"), "--since", "May")
    assert bad_date.returncode == 2 and "--since: not a date" in bad_date.stderr
    no_db = lfcal("recalibrate", "--database", "postgresql://lfcal@127.0.0.1:1/none")
    assert no_db.returncode == 2
    lines = no_db.stderr.strip().splitlines()
    assert len(lines) == 1 and "postgresql://lfcal@127.0.0.1:1/none is unreachable" in lines[0]


def test_calibrate_report_and_render_read_archives_from_the_object_store(
    tmp_path: Path, sweep: Path, s3: S3Server
) -> None:
    objects = ObjectStore("s3://recal", {"endpoint_url": s3.endpoint, "region": "us-east-1",
                                         "access_key_id": "testing-key-id",
                                         "secret_access_key": "testing-secret-key"})  # fmt: skip
    env = {**s3.env(), "HOME": str(tmp_path / "home")}
    local = tmp_path / "local"
    shutil.copytree(sweep, local)
    made = lfcal("calibrate", str(local), "--out", str(local / "result.json"), env=env)
    assert made.returncode == 0, made.stderr
    for rel in archive_files(local):
        objects.put_file(f"cli/job-000009/{rel}", local / rel)
    url = "s3://recal/cli/job-000009"

    calibrated = lfcal("calibrate", url, "--out", str(tmp_path / "r.json"), env=env)
    assert calibrated.returncode == 0, calibrated.stderr
    assert "b (mm)" in calibrated.stdout and "truth" in calibrated.stdout  # truth.json came too
    again = json.loads((tmp_path / "r.json").read_text())
    first = json.loads((local / "result.json").read_text())
    assert again["b_mm"] == pytest.approx(first["b_mm"], rel=1e-9)

    report = lfcal("report", url, "--out", str(tmp_path / "report.html"), env=env)
    assert report.returncode == 0, report.stderr
    assert "archive was not found" not in report.stdout
    assert (tmp_path / "report.html").stat().st_size > 10_000

    rendered = lfcal("render", f"{url}/frames/0005.png", "--result", f"{url}/result.json",
                     "--out", str(tmp_path / "r.png"), env=env)  # fmt: skip
    assert rendered.returncode == 0, rendered.stderr
    assert (tmp_path / "r.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    missing = lfcal("calibrate", "s3://recal/cli/no-such-job", env=env)
    assert missing.returncode == 2
    assert "has no archive at s3://recal/cli/no-such-job" in missing.stderr
