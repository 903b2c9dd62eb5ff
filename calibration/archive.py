"""Reading and writing sweep archives (format ``lfcal-sweep/1``, OPTICS.md §5).

This module and its parts (:mod:`calibration.archive_manifest`, the manifest and its
validation; :mod:`calibration.archive_images`, PNG decoding and checksums;
:mod:`calibration.archive_errors`) are the only code that touches the archive layout::

    SWEEP/
      sweep.json        manifest
      white.png         flat-field image, same size as the frames
      frames/0000.png   one 16-bit grey PNG per rail position (right-aligned counts)

Reading
    :func:`validate_manifest` lists every problem of a parsed ``sweep.json`` with
    its JSON path; :func:`read_manifest` raises :class:`ArchiveError` carrying all
    of them. :func:`read_image` decodes one PNG and raises a specific
    :class:`ImageError` subclass (missing, corrupt/truncated, wrong size, bit
    depth exceeded, not grayscale). :class:`SweepArchive` opens a directory;
    :meth:`SweepArchive.check` verifies every file (and SHA-256 checksums when
    the manifest has them) without raising, so a calibration can go on with the
    good frames.

Writing
    :class:`SweepWriter` has two modes:

    - :meth:`SweepWriter.create` (simulator, whole sweeps): everything is written
      into a hidden sibling ``.{name}.partial-XXXX`` and :meth:`SweepWriter.commit`
      renames it to the final name, so an interrupted write never leaves a
      directory that looks like a complete archive.
    - :meth:`SweepWriter.in_place` / :meth:`SweepWriter.resume` (station, one frame
      at a time): writes into the job directory itself. Every file is written
      atomically (temporary file in the same directory, ``fsync``,
      ``os.replace``) and the manifest is rewritten atomically after every frame,
      so a frame is listed only once its file is complete. An index that is
      already recorded is refused.

    Before each write the free disk space is checked; :class:`DiskFull` names the
    path and the number of bytes needed.

Units: millimetres unless a name says ``_px``; pixel values are sensor counts.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from .archive_errors import (
    ArchiveError,
    ArchiveExistsError,
    BitDepthError,
    CorruptImageError,
    DiskFull,
    DuplicateFrameError,
    ImageError,
    MissingImageError,
    NotGrayscaleError,
    WrongImageSizeError,
)
from .archive_images import (
    decode_image,
    encode_image,
    file_sha256,
    png_header_problem,
    read_image,
    sha256_hex,
)
from .archive_manifest import (
    DEFAULT_WHITE,
    FORMAT,
    FRAMES_DIR,
    MANIFEST_NAME,
    BoardInfo,
    CameraInfo,
    FrameEntry,
    OpticsInfo,
    RailInfo,
    SweepManifest,
    manifest_from_header,
    read_manifest,
    validate_manifest,
)
from .archive_writer import (
    DEFAULT_RESERVE_BYTES,
    FrameRecord,
    SweepWriter,
    atomic_write_bytes,
    ensure_free_space,
    frame_file_name,
)

__all__ = [
    "DEFAULT_RESERVE_BYTES",
    "DEFAULT_WHITE",
    "FORMAT",
    "FRAMES_DIR",
    "MANIFEST_NAME",
    "ArchiveCheck",
    "ArchiveError",
    "ArchiveExistsError",
    "BitDepthError",
    "BoardInfo",
    "CameraInfo",
    "CorruptImageError",
    "DiskFull",
    "DuplicateFrameError",
    "FrameEntry",
    "FrameRecord",
    "ImageError",
    "MissingImageError",
    "NotGrayscaleError",
    "OpticsInfo",
    "RailInfo",
    "SweepArchive",
    "SweepManifest",
    "SweepWriter",
    "WrongImageSizeError",
    "atomic_write_bytes",
    "decode_image",
    "encode_image",
    "ensure_free_space",
    "file_sha256",
    "frame_file_name",
    "manifest_from_header",
    "read_image",
    "read_manifest",
    "sha256_hex",
    "validate_manifest",
]
"""The archive's whole interface; the manifest, image and error modules are its parts."""


# -------------------------------------------------------------------------- reader


@dataclass
class ArchiveCheck:
    """Result of :meth:`SweepArchive.check`.

    ``white``: problems of the white image; ``frames``: problems per frame index
    (only frames with problems); ``good_indices``: frames that can be used;
    ``unlisted``: files under ``frames/`` that the manifest does not list (ignored).
    """

    white: list[str] = field(default_factory=list)
    frames: dict[int, list[str]] = field(default_factory=dict)
    good_indices: list[int] = field(default_factory=list)
    unlisted: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when the white image and every listed frame are usable."""
        return not self.white and not self.frames

    def problems(self) -> list[str]:
        """Every problem as one line each (white first, then frames by index)."""
        out = list(self.white)
        for index in sorted(self.frames):
            out.extend(f"frame {index}: {p}" for p in self.frames[index])
        return out


class SweepArchive:
    """Read-only access to an ``lfcal-sweep/1`` directory.

    ``frame(index)`` addresses frames by their manifest ``index``; iterating yields
    ``(FrameEntry, image)`` in manifest order.
    """

    def __init__(self, root: str | os.PathLike[str], manifest: SweepManifest) -> None:
        self.root = Path(root)
        self.manifest = manifest

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> SweepArchive:
        """Open an archive directory (or its ``sweep.json``); :class:`ArchiveError` if invalid."""
        p = Path(path)
        root = p.parent if p.name == MANIFEST_NAME and p.is_file() else p
        return cls(root, read_manifest(root))

    def __len__(self) -> int:
        return len(self.manifest.frames)

    def __iter__(self) -> Iterator[tuple[FrameEntry, NDArray[np.uint16]]]:
        return self.iter_frames()

    @property
    def indices(self) -> list[int]:
        return self.manifest.indices

    def path_of(self, relative: str) -> Path:
        return self.root / relative

    def _read(self, relative: str) -> NDArray[np.uint16]:
        cam = self.manifest.camera
        return read_image(self.path_of(relative), expected_shape=cam.shape, bit_depth=cam.bit_depth)

    def white(self) -> NDArray[np.uint16]:
        """The flat-field image as uint16 counts; raises an :class:`ImageError` subclass."""
        return self._read(self.manifest.white)

    def frame(self, index: int) -> NDArray[np.uint16]:
        """The frame with manifest index ``index``; ``KeyError`` or :class:`ImageError`."""
        return self._read(self.manifest.frame_entry(index).file)

    def iter_frames(
        self, *, skip_bad: bool = False
    ) -> Iterator[tuple[FrameEntry, NDArray[np.uint16]]]:
        """``(entry, image)`` in manifest order; with ``skip_bad`` unreadable frames are skipped."""
        for entry in self.manifest.frames:
            try:
                img = self._read(entry.file)
            except ImageError:
                if skip_bad:
                    continue
                raise
            yield entry, img

    def _check_file(self, relative: str, expected_sha: str | None, decode: bool) -> list[str]:
        cam = self.manifest.camera
        path = self.path_of(relative)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return [f"{relative}: file not found"]
        except OSError as exc:
            return [f"{relative}: cannot read: {exc.strerror or exc}"]
        problems: list[str] = []
        if expected_sha is not None:
            actual = sha256_hex(data)
            if actual.lower() != expected_sha.lower():
                problems.append(
                    f"{relative}: SHA-256 mismatch (manifest {expected_sha}, file {actual})"
                )
        try:
            if decode:
                decode_image(data, relative, expected_shape=cam.shape, bit_depth=cam.bit_depth)
            else:
                problem, _ = png_header_problem(data)
                if problem is not None:
                    problems.append(f"{relative}: {problem}")
        except ImageError as exc:
            problems.append(str(exc))
        return problems

    def check(self, *, decode: bool = True) -> ArchiveCheck:
        """Verify every file without raising.

        Checks existence, SHA-256 (when the manifest lists ``sha256`` /
        ``white_sha256``) and, with ``decode`` (default), decodes each image and
        checks size, grey format and bit depth; ``decode=False`` only checks the
        PNG structure (fast).
        """
        result = ArchiveCheck()
        result.white = self._check_file(self.manifest.white, self.manifest.white_sha256, decode)
        for entry in self.manifest.frames:
            problems = self._check_file(entry.file, entry.sha256, decode)
            if problems:
                result.frames[entry.index] = problems
            else:
                result.good_indices.append(entry.index)
        listed = {e.file for e in self.manifest.frames}
        frames_dir = self.root / FRAMES_DIR
        if frames_dir.is_dir():
            for p in sorted(frames_dir.iterdir()):
                rel = f"{FRAMES_DIR}/{p.name}"
                if not p.name.startswith(".") and rel not in listed:
                    result.unlisted.append(rel)
        return result
