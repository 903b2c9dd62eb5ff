"""Upload of the station's archives to object storage, safe against outages.

Frames are always written to the local archive first (atomically, with their
SHA-256 in the job store); :class:`ArchiveUploader`, one thread per station,
copies them to ``jobs.archive_url`` afterwards:

- every half second (or at once after :meth:`ArchiveUploader.poke`) it looks at
  this station's jobs whose archive is not completely uploaded
  (:meth:`station.store.JobStore.jobs_to_upload`) and uploads each file of the
  local archive that is new or changed since its last verified upload (hidden
  and temporary files are skipped: a frame appears under its name only once it
  is complete);
- each upload is verified after the fact (:meth:`station.objectstore.ObjectStore.put_file`:
  size, MD5 and SHA-256 read back); only then is the file entered in the job's
  upload journal (``data_dir/.uploads/job-000123.json``: relative path -> size,
  mtime, SHA-256), written atomically;
- during an outage nothing is lost: the local files stay, the uploader retries
  every ``[storage.s3] upload_retry_s``; after a restart (even ``kill -9``) it
  resumes from the journal, so an interrupted upload is simply done again;
- once a pass that began with the job in a final state has uploaded what was left
  (the writer is done by then: the archive no longer changes), the job is marked uploaded (``archive_uploaded_at``). Without ``keep_local_archives``,
  the local copy of a succeeded or cancelled job (never of a resumable one) is then
  deleted; readers fetch it back from the object store (:mod:`station.archive_source`).
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from station.config_sections import StorageConfig
from station.db import StoreError
from station.objectstore import ObjectStore, ObjectStoreUnavailable, split_s3_url
from station.store import JobRecord, JobState, JobStore

POLL_INTERVAL_S = 0.5
RUNNING_STATES = frozenset({JobState.QUEUED, JobState.RUNNING, JobState.PAUSED})
DELETABLE_STATES = frozenset({JobState.SUCCEEDED, JobState.CANCELLED})


def archive_files(directory: Path) -> list[str]:
    """Relative paths of the archive's complete files (no hidden or temporary files)."""
    out: list[str] = []
    if not directory.is_dir():
        return out
    for root, dirs, files in os.walk(directory):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith(".") or name.endswith((".tmp", ".part")):
                continue
            out.append(str((Path(root) / name).relative_to(directory)))
    return out


@dataclass
class UploadState:
    """What the uploader did and what is left (JSON-ready through :meth:`to_dict`)."""

    files_uploaded: int = 0
    bytes_uploaded: int = 0
    jobs_completed: int = 0
    pending_jobs: list[int] = field(default_factory=list)
    error: str | None = None
    error_since: float | None = None
    last_upload_at: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class ArchiveUploader:
    """The station's upload thread (see the module docstring).

    Args:
        store: the station's job store (its own jobs are uploaded).
        objects: the object store of ``[storage] archive_url``.
        data_dir: the station's data directory (journals in ``.uploads/``).
        keep_local: keep local archives once uploaded.
        retry_s: wait between attempts while the object store is unreachable (s).
    """

    def __init__(
        self,
        store: JobStore,
        objects: ObjectStore,
        data_dir: Path,
        *,
        keep_local: bool = True,
        retry_s: float = 2.0,
    ) -> None:
        self.store = store
        self.objects = objects
        self.journal_dir = Path(data_dir) / ".uploads"
        self.keep_local = keep_local
        self.retry_s = retry_s
        self.state = UploadState()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ life

    def start(self) -> ArchiveUploader:
        self._thread = threading.Thread(target=self._loop, name="archive-uploader", daemon=True)
        self._thread.start()
        return self

    def poke(self) -> None:
        """Look for new files now."""
        self._wake.set()

    def stop(self, timeout_s: float = 10.0) -> None:
        """One last pass (bounded by ``timeout_s``), then stop; what is left is
        uploaded by the next start."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def status(self) -> dict[str, Any]:
        with self._lock:
            return self.state.to_dict()

    def _loop(self) -> None:
        while True:
            try:
                pending = self.sync_once()
                ok = True
            except (ObjectStoreUnavailable, StoreError) as exc:
                self._note_error(str(exc))
                ok, pending = False, 1
            except Exception as exc:  # noqa: BLE001 - the uploader never dies
                self._note_error(f"internal error: {type(exc).__name__}: {exc}")
                ok, pending = False, 1
            if self._stop.is_set():
                return
            wait = POLL_INTERVAL_S if ok or not pending else self.retry_s
            self._wake.wait(wait)
            self._wake.clear()

    def _note_error(self, text: str) -> None:
        with self._lock:
            if self.state.error is None:
                self.state.error_since = time.time()
            self.state.error = text

    # ------------------------------------------------------------------ work

    def sync_once(self) -> int:
        """One pass over the station's jobs; returns how many are not complete."""
        jobs = self.store.jobs_to_upload()
        with self._lock:
            self.state.pending_jobs = [j.id for j in jobs]
        left = []
        for job in jobs:
            if self._stop.is_set() and job.state in RUNNING_STATES:
                left.append(job.id)
                continue
            if not self.sync_job(job):
                left.append(job.id)
        with self._lock:
            self.state.pending_jobs = left
            self.state.error = None
            self.state.error_since = None
        return len(left)

    def _journal_path(self, job_id: int) -> Path:
        return self.journal_dir / f"job-{job_id:06d}.json"

    def journal(self, job_id: int) -> dict[str, list[Any]]:
        """The job's upload journal (relative path -> [size, mtime_ns, sha256])."""
        try:
            data = json.loads(self._journal_path(job_id).read_text(encoding="utf-8"))
            return dict(data) if isinstance(data, dict) else {}
        except (OSError, ValueError):
            return {}

    def _save_journal(self, job_id: int, journal: dict[str, list[Any]]) -> None:
        self.journal_dir.mkdir(parents=True, exist_ok=True)
        path = self._journal_path(job_id)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(journal, separators=(",", ":")), encoding="utf-8")
        tmp.replace(path)

    def sync_job(self, job: JobRecord) -> bool:
        """Upload what changed in the job's archive; True once it is complete
        (final state, nothing left: the job is then marked uploaded)."""
        assert job.archive_url is not None
        final = job.state not in RUNNING_STATES
        directory = Path(job.archive_dir)
        _, prefix = split_s3_url(job.archive_url)
        journal = self.journal(job.id)
        for rel in archive_files(directory):
            path = directory / rel
            try:
                st = path.stat()
            except FileNotFoundError:  # replaced meanwhile: next pass
                continue
            seen = journal.get(rel)
            if seen is not None and seen[0] == st.st_size and seen[1] == st.st_mtime_ns:
                continue
            stored = self.objects.put_file(f"{prefix}/{rel}", path)
            journal[rel] = [st.st_size, st.st_mtime_ns, stored.sha256]
            self._save_journal(job.id, journal)
            with self._lock:
                self.state.files_uploaded += 1
                self.state.bytes_uploaded += st.st_size
                self.state.last_upload_at = time.time()
        if not final:  # final when the pass began: the archive no longer changes
            return False
        if not self.store.mark_archive_uploaded(job.id, as_of=job):
            return False  # resumed (or changed) during the pass: upload again
        with self._lock:
            self.state.jobs_completed += 1
        if not self.keep_local and job.state in DELETABLE_STATES:
            shutil.rmtree(directory, ignore_errors=True)
        return True


def start_uploader(store: JobStore, storage: StorageConfig, data_dir: Path) -> ArchiveUploader:
    """The running uploader of a station whose ``[storage] archive_url`` is set
    (``storage``: the station's ``[storage]`` section). The object store must answer
    now (:class:`station.objectstore.ObjectStoreUnavailable` otherwise)."""
    if storage.archive_url is None:
        raise ValueError("[storage] archive_url is not set: there is nothing to upload to")
    objects = ObjectStore(storage.archive_url, storage.s3)
    objects.check()
    return ArchiveUploader(
        store,
        objects,
        data_dir,
        keep_local=storage.keep_local_archives,
        retry_s=storage.s3.upload_retry_s,
    ).start()


__all__ = ["ArchiveUploader", "UploadState", "archive_files", "start_uploader"]
