"""Where an archive is read from: the local directory, or object storage through a cache.

The calibration core reads ``lfcal-sweep/1`` archives from a local directory and
knows nothing of networks (``calibration/`` imports no boto3). This module is the
station's archive reader: it turns an archive *location* into a local directory.

- A local path (``/data/job-000012-...``) is returned as it is.
- ``s3://bucket/prefix/station/job-...`` is downloaded into a cache directory
  (``cache_dir/bucket/prefix/station/job-...``), every object checked against the
  SHA-256 stored with it; files already in the cache with the same size and
  SHA-256 are not downloaded again. The archive is assembled in a hidden staging
  directory and renamed into place, so a half-downloaded archive is never seen.
- :class:`ArchiveReader` does this for a job: its local archive if it is there
  (complete: ``sweep.json`` present), else its ``archive_url`` through the cache.

``lfcal calibrate s3://...``, ``lfcal recalibrate`` (on every Dask worker) and the
station's HTTP routes (archive zip, frames, plots, renders) read through here.
"""

from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path
from typing import Any

from calibration.archive import file_sha256
from station.objectstore import ObjectStore, split_s3_url

MANIFEST = "sweep.json"
_FETCH_LOCK = threading.Lock()


def is_remote(location: str | Path) -> bool:
    """The location is an object-storage URL (else a local path)."""
    return str(location).startswith("s3://")


def cache_path(url: str, cache_dir: Path) -> Path:
    """Where the archive at ``url`` is kept in ``cache_dir``."""
    bucket, key = split_s3_url(url)
    return Path(cache_dir) / bucket / key


def fetch_archive(
    url: str, cache_dir: Path, *, objects: ObjectStore | None = None, settings: Any = None
) -> Path:
    """Download the archive at ``url`` into the cache (see the module docstring) and
    return its local directory. Raises :class:`station.objectstore.ObjectStoreUnavailable`
    (unreachable, no such archive) or :class:`station.objectstore.UploadMismatch`."""
    bucket, prefix = split_s3_url(url)
    store = objects or ObjectStore(f"s3://{bucket}", settings)
    target = cache_path(url, cache_dir)
    with _FETCH_LOCK:
        listing = store.list(prefix)
        if not listing:
            from station.objectstore import ObjectStoreUnavailable

            raise ObjectStoreUnavailable(
                f"the object store has no archive at {url} (nothing under that prefix)",
                path=url,
            )
        index_path = target / ".fetched.json"
        try:
            index: dict[str, list[Any]] = json.loads(index_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            index = {}
        staging = target.with_name(f".{target.name}.staging")
        shutil.rmtree(staging, ignore_errors=True)
        if target.is_dir():
            shutil.copytree(target, staging)
        fresh: dict[str, list[Any]] = {}
        for item in listing:
            rel = item.key[len(prefix) + 1 :]
            local = staging / rel
            known = index.get(rel)
            if known is not None and known[0] == item.size and known[1] == item.etag:
                if local.is_file() and local.stat().st_size == item.size:
                    fresh[rel] = known
                    continue
            sha = store.get_file(item.key, local)
            fresh[rel] = [item.size, item.etag, sha]
        for path in list(staging.rglob("*")):  # files no longer in the object store
            rel = str(path.relative_to(staging))
            if path.is_file() and rel not in fresh and rel != ".fetched.json":
                path.unlink()
        (staging / ".fetched.json").write_text(json.dumps(fresh), encoding="utf-8")
        if target.exists():
            old = target.with_name(f".{target.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            target.rename(old)
            staging.rename(target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            staging.rename(target)
    return target


def default_cache_dir() -> Path:
    """The command line's archive cache: ``~/.cache/lfcal/archives``."""
    return Path.home() / ".cache" / "lfcal" / "archives"


def local_file(
    location: str | Path, cache_dir: Path | None = None, *, settings: Any = None
) -> Path:
    """A local copy of one file: the path itself, or an ``s3://bucket/key`` object
    downloaded into the cache (checked against its stored SHA-256)."""
    if not is_remote(location):
        return Path(location)
    bucket, key = split_s3_url(str(location))
    target = cache_path(str(location), cache_dir or default_cache_dir())
    ObjectStore(f"s3://{bucket}", settings).get_file(key, target)
    return target


def local_archive(location: str | Path, cache_dir: Path, *, settings: Any = None) -> Path:
    """A local directory holding the archive at ``location`` (a path or an s3:// URL)."""
    if is_remote(location):
        return fetch_archive(str(location), cache_dir, settings=settings)
    return Path(location)


class ArchiveReader:
    """Local directories of the station's jobs' archives (see the module docstring).

    Args:
        cache_dir: where archives read from object storage are kept.
        settings: ``[storage.s3]`` of the station (None: the environment).
    """

    def __init__(self, cache_dir: Path, settings: Any = None) -> None:
        self.cache_dir = Path(cache_dir)
        self.settings = settings
        self._stores: dict[str, ObjectStore] = {}

    def _store(self, url: str) -> ObjectStore:
        bucket, _ = split_s3_url(url)
        if bucket not in self._stores:
            self._stores[bucket] = ObjectStore(f"s3://{bucket}", self.settings)
        return self._stores[bucket]

    def local_dir(self, archive_dir: str | Path, archive_url: str | None) -> Path:
        """The job's local archive when complete, else a copy from ``archive_url``
        (when there is none, the local path, which may not exist)."""
        local = Path(archive_dir)
        if (local / MANIFEST).is_file() or not archive_url:
            return local
        cached = cache_path(archive_url, self.cache_dir)
        if (cached / MANIFEST).is_file():
            return cached
        return fetch_archive(archive_url, self.cache_dir, objects=self._store(archive_url))

    def verify(self, directory: Path, files: dict[str, str]) -> list[str]:
        """Relative paths in ``files`` (path -> SHA-256) whose local copy is missing or differs."""
        bad = []
        for rel, sha in files.items():
            path = directory / rel
            if not path.is_file() or file_sha256(path) != sha:
                bad.append(rel)
        return bad


__all__ = [
    "ArchiveReader",
    "cache_path",
    "default_cache_dir",
    "fetch_archive",
    "is_remote",
    "local_archive",
    "local_file",
]
