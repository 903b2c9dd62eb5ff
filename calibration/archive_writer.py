"""Writing sweep archives (format ``lfcal-sweep/1``, OPTICS.md §5): :class:`SweepWriter`
and the atomic, space-checked file writes it makes (see :mod:`calibration.archive`, which
re-exports everything here, for the two writing modes).

Units: millimetres unless a name says ``_px``; pixel values are sensor counts.
"""

from __future__ import annotations

import errno
import json
import os
import secrets
import shutil
import threading
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple

from numpy.typing import NDArray

from .archive_errors import (
    ArchiveError,
    ArchiveExistsError,
    DiskFull,
    DuplicateFrameError,
)
from .archive_images import (
    encode_image,
    sha256_hex,
)
from .archive_manifest import (
    FRAME_KEYS,
    FRAMES_DIR,
    MANIFEST_NAME,
    FrameEntry,
    SweepManifest,
    is_int,
    is_number,
    manifest_from_header,
    read_manifest,
)

DEFAULT_RESERVE_BYTES = 16 * 1024 * 1024
"""Free space (bytes) that every write leaves on the disk on top of its own size."""


# -------------------------------------------------------------------------- writer


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def ensure_free_space(
    path: str | os.PathLike[str], nbytes: int, reserve_bytes: int = DEFAULT_RESERVE_BYTES
) -> None:
    """Raise :class:`DiskFull` unless ``nbytes + reserve_bytes`` are free where ``path`` goes."""
    p = Path(path)
    probe = p.parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    needed = int(nbytes) + int(reserve_bytes)
    if free < needed:
        raise DiskFull(p, needed, free)


def atomic_write_bytes(
    path: str | os.PathLike[str], data: bytes, *, reserve_bytes: int = DEFAULT_RESERVE_BYTES
) -> None:
    """Write ``data`` to ``path`` atomically: temp file in the same directory, fsync, replace.

    Readers see either the old file or the complete new one. :class:`DiskFull`
    before writing when space is short (and on ENOSPC during the write).
    """
    p = Path(path)
    ensure_free_space(p, len(data), reserve_bytes)
    tmp = p.with_name(f".{p.name}.{secrets.token_hex(4)}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException as exc:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError) and exc.errno == errno.ENOSPC and not isinstance(exc, DiskFull):
            raise DiskFull(p, len(data) + reserve_bytes, shutil.disk_usage(p.parent).free) from exc
        raise
    _fsync_dir(p.parent)


class FrameRecord(NamedTuple):
    """What :meth:`SweepWriter.add_frame` wrote: relative file name and its SHA-256."""

    file: str
    sha256: str


def frame_file_name(index: int) -> str:
    """Relative file of frame ``index``: ``frames/0000.png``."""
    return f"{FRAMES_DIR}/{index:04d}.png"


class SweepWriter:
    """Writes an ``lfcal-sweep/1`` archive; see the module docstring for the two modes.

    Use :meth:`create` (staged, then :meth:`commit`), :meth:`in_place` (new
    station job) or :meth:`resume` (continue a job after a restart). Not to be
    constructed directly. Thread-safe: one lock serialises all writes.
    """

    def __init__(
        self,
        *,
        target: Path,
        work_dir: Path,
        manifest: SweepManifest,
        staged: bool,
        overwrite: bool,
        white_written: bool,
        compression: int,
        reserve_bytes: int,
    ) -> None:
        self.target = target
        self.work_dir = work_dir
        self._manifest = manifest
        self.staged = staged
        self.overwrite = overwrite
        self.compression = compression
        self.reserve_bytes = reserve_bytes
        self._white_written = white_written
        self._closed = False
        self._lock = threading.Lock()

    # -- constructors

    @classmethod
    def create(
        cls,
        final_dir: str | os.PathLike[str],
        header: SweepManifest | Mapping[str, Any],
        *,
        overwrite: bool = False,
        compression: int = 1,
        reserve_bytes: int = DEFAULT_RESERVE_BYTES,
    ) -> SweepWriter:
        """Stage a whole archive in ``.{name}.partial-XXXX`` next to ``final_dir``.

        ``header`` is the manifest without frames (its frames, if any, are
        dropped). :class:`ArchiveExistsError` if ``final_dir`` already holds an
        archive and ``overwrite`` is false, or holds other files.
        """
        target = Path(final_dir)
        manifest = manifest_from_header(header)
        manifest.frames = []
        manifest.white_sha256 = None
        _check_target(target, overwrite)
        target.parent.mkdir(parents=True, exist_ok=True)
        while True:
            work = target.parent / f".{target.name}.partial-{secrets.token_hex(4)}"
            try:
                work.mkdir()
                break
            except FileExistsError:
                continue
        (work / FRAMES_DIR).mkdir()
        return cls(
            target=target,
            work_dir=work,
            manifest=manifest,
            staged=True,
            overwrite=overwrite,
            white_written=False,
            compression=compression,
            reserve_bytes=reserve_bytes,
        )

    @classmethod
    def in_place(
        cls,
        job_dir: str | os.PathLike[str],
        header: SweepManifest | Mapping[str, Any],
        *,
        compression: int = 1,
        reserve_bytes: int = DEFAULT_RESERVE_BYTES,
    ) -> SweepWriter:
        """Start a new archive directly in ``job_dir`` (created if missing).

        The manifest (no frames yet) is written at once. :class:`ArchiveExistsError`
        if ``job_dir`` already has a ``sweep.json`` (use :meth:`resume`).
        """
        job = Path(job_dir)
        manifest = manifest_from_header(header)
        manifest.frames = []
        manifest.white_sha256 = None
        if (job / MANIFEST_NAME).exists():
            raise ArchiveExistsError(
                f"{job} already holds an archive ({MANIFEST_NAME}); use SweepWriter.resume"
            )
        (job / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        writer = cls(
            target=job,
            work_dir=job,
            manifest=manifest,
            staged=False,
            overwrite=False,
            white_written=False,
            compression=compression,
            reserve_bytes=reserve_bytes,
        )
        writer._write_manifest()
        return writer

    @classmethod
    def resume(
        cls,
        job_dir: str | os.PathLike[str],
        *,
        compression: int = 1,
        reserve_bytes: int = DEFAULT_RESERVE_BYTES,
    ) -> SweepWriter:
        """Continue appending to the archive in ``job_dir`` (its manifest must be valid)."""
        job = Path(job_dir)
        manifest = read_manifest(job)
        (job / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        return cls(
            target=job,
            work_dir=job,
            manifest=manifest,
            staged=False,
            overwrite=False,
            white_written=(manifest.white_sha256 is not None or (job / manifest.white).is_file()),
            compression=compression,
            reserve_bytes=reserve_bytes,
        )

    # -- state

    @property
    def manifest(self) -> SweepManifest:
        """A copy of the manifest as it stands (including the frames written so far)."""
        with self._lock:
            return SweepManifest.from_dict(self._manifest.to_dict())

    @property
    def indices(self) -> list[int]:
        with self._lock:
            return self._manifest.indices

    def _ensure_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"the writer for {self.target} is already committed or aborted")

    # -- writing

    def write_white(self, image: NDArray[Any]) -> FrameRecord:
        """Write the flat-field image (replacing an earlier one); returns file and SHA-256."""
        with self._lock:
            self._ensure_open()
            rel = self._manifest.white
            data = self._encode(image, rel)
            dest = self.work_dir / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(dest, data, reserve_bytes=self.reserve_bytes)
            digest = sha256_hex(data)
            self._manifest.white_sha256 = digest
            self._white_written = True
            if not self.staged:
                self._write_manifest()
            return FrameRecord(rel, digest)

    def add_frame(
        self, index: int, rail_mm: float, image: NDArray[Any], **extra: Any
    ) -> FrameRecord:
        """Write frame ``index`` at rail position ``rail_mm`` (mm) and record it.

        ``extra`` keys (JSON-serialisable: timestamps, exposure, stage read-back…)
        are stored in the frame's manifest entry. The file is complete before the
        entry appears; in place, the manifest is rewritten atomically afterwards.
        :class:`DuplicateFrameError` if ``index`` is already recorded (nothing is
        written); :class:`DiskFull` when space is short.
        """
        if not is_int(index) or index < 0:
            raise ValueError(f"frame index must be a non-negative integer, got {index!r}")
        if not is_number(rail_mm):
            raise ValueError(f"rail_mm must be a finite number (mm), got {rail_mm!r}")
        clash = set(extra) & set(FRAME_KEYS)
        if clash:
            raise ValueError(f"extra keys {sorted(clash)} are reserved frame keys")
        extra_json = json.loads(json.dumps(extra, allow_nan=False))
        with self._lock:
            self._ensure_open()
            if index in self._manifest.indices:
                raise DuplicateFrameError(
                    f"frame {index} is already recorded in {self.target / MANIFEST_NAME}"
                )
            rel = frame_file_name(index)
            data = self._encode(image, rel)
            atomic_write_bytes(self.work_dir / rel, data, reserve_bytes=self.reserve_bytes)
            digest = sha256_hex(data)
            entry = FrameEntry(index, float(rail_mm), rel, digest, extra_json)
            self._manifest.frames.append(entry)
            self._manifest.frames.sort(key=lambda e: e.index)
            if not self.staged:
                try:
                    self._write_manifest()
                except BaseException:
                    self._manifest.frames.remove(entry)
                    raise
            return FrameRecord(rel, digest)

    def _encode(self, image: NDArray[Any], name: str) -> bytes:
        cam = self._manifest.camera
        return encode_image(
            image,
            expected_shape=cam.shape,
            bit_depth=cam.bit_depth,
            compression=self.compression,
            name=name,
        )

    def _write_manifest(self) -> None:
        text = json.dumps(self._manifest.to_dict(), indent=2, allow_nan=False) + "\n"
        atomic_write_bytes(
            self.work_dir / MANIFEST_NAME, text.encode("utf-8"), reserve_bytes=self.reserve_bytes
        )

    # -- finishing

    def commit(self) -> Path:
        """Finish the archive and return its directory.

        Staged: writes the manifest and renames the staging directory to the
        final name (replacing an existing archive only with ``overwrite``); the
        white image must have been written. In place: rewrites the manifest.
        """
        with self._lock:
            self._ensure_open()
            if not self._white_written:
                raise ArchiveError(
                    f"{self.target}: the white image was not written (call write_white first)"
                )
            self._write_manifest()
            if self.staged:
                self._publish()
            self._closed = True
            return self.target

    def _publish(self) -> None:
        _check_target(self.target, self.overwrite)
        old: Path | None = None
        if self.target.exists():
            if any(self.target.iterdir()):
                old = self.target.parent / f".{self.target.name}.old-{secrets.token_hex(4)}"
                os.replace(self.target, old)
            else:
                self.target.rmdir()
        os.replace(self.work_dir, self.target)
        _fsync_dir(self.target.parent)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        """Give up: remove the staging directory (staged) — in place, files stay as they are."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self.staged:
                shutil.rmtree(self.work_dir, ignore_errors=True)

    def __enter__(self) -> SweepWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Commit on success, :meth:`abort` on an exception (or when the commit fails)."""
        if exc_type is None:
            if not self._closed:
                try:
                    self.commit()
                except BaseException:
                    self.abort()
                    raise
        else:
            self.abort()


def _check_target(target: Path, overwrite: bool) -> None:
    """Refuse to replace an existing archive (unless ``overwrite``) or a non-archive directory."""
    if not target.exists():
        return
    if not target.is_dir():
        raise ArchiveExistsError(f"{target} exists and is not a directory")
    if (target / MANIFEST_NAME).exists():
        if not overwrite:
            raise ArchiveExistsError(
                f"{target} already holds an archive; pass overwrite=True to replace it"
            )
        return
    if any(target.iterdir()):
        raise ArchiveExistsError(f"{target} exists, is not empty and is not an archive")
