"""``[storage]`` for a fleet: PostgreSQL URL, station id, object storage, ``[storage.s3]``;
and the archive uploader's journal against a moto S3 server on 127.0.0.1."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from bench.fleet_servers import S3_KEY_ID, S3_SECRET, s3_server
from station.archive_source import fetch_archive
from station.archive_sync import ArchiveUploader, archive_files
from station.config import ConfigError, load_config
from station.objectstore import ObjectStore, ObjectStoreUnavailable, split_s3_url
from station.store import JobState, JobStore

MINIMAL = "[rail]\nzero_object_distance_mm = 250.0\n"


def _load(tmp_path: Path, storage: str) -> object:
    path = tmp_path / "station.toml"
    path.write_text(MINIMAL + "[storage]\n" + storage, encoding="utf-8")
    return load_config(path, env={})


def _problems(tmp_path: Path, storage: str) -> list[str]:
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, storage)
    return err.value.format_problems()


def test_a_postgresql_url_and_the_object_store_are_configured(tmp_path: Path) -> None:
    cfg = _load(
        tmp_path,
        'data_dir = "data"\ndatabase = "postgresql://lfcal:pw@db.lab:5432/lfcal"\n'
        'station_id = "line-2"\n'
        'archive_url = "s3://calib-archives/lab/a"\nkeep_local_archives = false\n'
        '[storage.s3]\nendpoint_url = "http://minio.lab:9000"\nupload_retry_s = 5\n',
    )
    storage = cfg.storage  # type: ignore[attr-defined]
    assert storage.database == "postgresql://lfcal:pw@db.lab:5432/lfcal"
    assert storage.postgres and storage.database_path is None
    assert (storage.station_id, storage.archive_url) == ("line-2", "s3://calib-archives/lab/a")
    assert storage.s3.endpoint_url == "http://minio.lab:9000" and storage.s3.upload_retry_s == 5
    assert storage.cache_dir == tmp_path / "data" / "archive-cache"
    sqlite = _load(tmp_path, 'database = "db/jobs.sqlite3"\n').storage  # type: ignore[attr-defined]
    assert sqlite.database == tmp_path / "db" / "jobs.sqlite3" and not sqlite.postgres


@pytest.mark.parametrize(
    ("storage", "key", "reason"),
    [
        ('database = "mysql://x@h/db"\n', "storage.database", "mysql:// URL"),
        ('station_id = "line 1"\n', "storage.station_id", "should match pattern"),
        ('archive_url = "http://bucket/x"\n', "storage.archive_url", "should match pattern"),
        ('[storage.s3]\nendpont_url = "http://h"\n', "storage.s3.endpont_url", "unknown key"),
        ("[storage.s3]\nupload_retry_s = 0\n", "storage.s3.upload_retry_s", "greater than 0"),
    ],
)
def test_bad_storage_keys_are_named(tmp_path: Path, storage: str, key: str, reason: str) -> None:
    lines = _problems(tmp_path, storage)
    assert any(f": {key}: " in line and reason in line for line in lines), lines


def test_the_uploader_resumes_from_its_journal_and_verifies_every_file(tmp_path: Path) -> None:
    with s3_server() as s3:
        s3.create_bucket("journal-test")
        settings = {"endpoint_url": s3.endpoint, "access_key_id": S3_KEY_ID,
                    "secret_access_key": S3_SECRET, "region": "us-east-1"}  # fmt: skip
        objects = ObjectStore("s3://journal-test/pre", settings)
        store = JobStore(tmp_path / "db.sqlite3", station_id="s", archive_url=objects.url)
        job, _ = store.create_job({}, archive_root=tmp_path / "data", frames_total=3)
        (job.archive_dir / "frames").mkdir(parents=True)
        for i in range(3):
            (job.archive_dir / "frames" / f"{i:04d}.png").write_bytes(bytes([i]) * 1000)
        (job.archive_dir / "sweep.json").write_text("{}")
        (job.archive_dir / "frames" / ".0003.png.tmp").write_bytes(b"half")  # never uploaded
        uploader = ArchiveUploader(store, objects, tmp_path / "data")
        store.transition(job.id, JobState.RUNNING, "started")
        assert uploader.sync_once() == 1  # running: uploaded, not complete
        assert uploader.status()["files_uploaded"] == 4
        # a restart that lost part of the journal uploads only what is not in it
        journal = uploader.journal(job.id)
        del journal["frames/0001.png"]
        uploader._save_journal(job.id, journal)
        again = ArchiveUploader(store, objects, tmp_path / "data")
        store.transition(job.id, JobState.SUCCEEDED, "done")
        assert again.sync_once() == 0
        assert again.status()["files_uploaded"] == 1
        done = store.get_job(job.id)
        assert done.archive_uploaded_at is not None
        _, prefix = split_s3_url(done.archive_url or "")
        keys = {o.key for o in objects.list(prefix)}
        assert keys == {f"{prefix}/{rel}" for rel in archive_files(job.archive_dir)}
        assert f"{prefix}/frames/.0003.png.tmp" not in keys
        for rel in archive_files(job.archive_dir):
            head = objects.head(f"{prefix}/{rel}")
            assert head is not None
            assert head.sha256 == hashlib.sha256((job.archive_dir / rel).read_bytes()).hexdigest()
        # read back through the cache: same bytes, checked against the stored SHA-256
        copy = fetch_archive(done.archive_url or "", tmp_path / "cache", settings=settings)
        assert (copy / "frames" / "0002.png").read_bytes() == bytes([2]) * 1000
        assert json.loads((copy / "sweep.json").read_text()) == {}
        store.close()
        s3.stop()
        with pytest.raises(ObjectStoreUnavailable, match="is unreachable"):
            objects.check()
        s3.start()


def test_a_job_resumed_during_an_upload_pass_is_not_marked_uploaded(tmp_path: Path) -> None:
    """The pass that began with the job interrupted must not mark it uploaded once
    it has been resumed meanwhile: the resumed sweep writes frames it never saw."""
    store = JobStore(tmp_path / "db.sqlite3", station_id="s", archive_url="s3://b/p")
    job, _ = store.create_job({}, archive_root=tmp_path / "data", frames_total=3)
    store.transition(job.id, JobState.RUNNING, "started")
    interrupted = store.transition(job.id, JobState.INTERRUPTED, "killed")
    assert [j.id for j in store.jobs_to_upload()] == [job.id]
    store.transition(job.id, JobState.QUEUED, "resumed")  # during the pass
    assert store.mark_archive_uploaded(job.id, as_of=interrupted) is False
    assert [j.id for j in store.jobs_to_upload()] == [job.id]
    store.transition(job.id, JobState.RUNNING, "started")
    done = store.transition(job.id, JobState.SUCCEEDED, "done")
    assert store.mark_archive_uploaded(job.id, as_of=done) is True
    assert store.jobs_to_upload() == []
    store.close()
