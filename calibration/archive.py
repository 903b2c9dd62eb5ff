"""Reading and writing sweep archives (format ``lfcal-sweep/1``, OPTICS.md §5).

This is the only module that touches the archive layout::

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

import errno
import hashlib
import json
import math
import os
import re
import secrets
import shutil
import struct
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from types import TracebackType
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray

from .png import PNG_SIGNATURE, encode_png_gray16

FORMAT = "lfcal-sweep/1"
"""The value of the manifest's ``format`` key."""

MANIFEST_NAME = "sweep.json"
DEFAULT_WHITE = "white.png"
FRAMES_DIR = "frames"
DEFAULT_RESERVE_BYTES = 16 * 1024 * 1024
"""Free space (bytes) that every write leaves on the disk on top of its own size."""

_HEX64 = re.compile(r"^[0-9a-fA-F]{64}$")
_PNG_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey + alpha", 6: "RGBA"}


# --------------------------------------------------------------------------- errors


class ArchiveError(ValueError):
    """An archive or one of its files is invalid; ``problems`` lists every problem found."""

    def __init__(self, message: str, problems: list[str] | None = None) -> None:
        self.problems: list[str] = list(problems) if problems is not None else [message]
        super().__init__(message)


class ImageError(ArchiveError):
    """An image file cannot be used; ``path`` is the offending file."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f"{path}: {reason}")


class MissingImageError(ImageError, FileNotFoundError):
    """The image file does not exist."""


class CorruptImageError(ImageError):
    """The file is not a decodable PNG (bad signature, truncated, damaged data)."""


class WrongImageSizeError(ImageError):
    """The image does not have the manifest's ``height × width``."""


class BitDepthError(ImageError):
    """Pixel values exceed ``2**bit_depth − 1`` or the PNG has too few bits per sample."""


class NotGrayscaleError(ImageError):
    """The PNG has colour channels or an alpha channel."""


class ArchiveExistsError(FileExistsError):
    """The destination already holds an archive (and overwriting was not asked for)."""


class DuplicateFrameError(ValueError):
    """A frame with this index is already recorded in the manifest."""


class DiskFull(OSError):  # noqa: N818 - the station catches it by this name
    """Not enough free disk space for a write.

    ``path`` is the file that was to be written, ``needed_bytes`` its size plus the
    reserve, ``free_bytes`` what the file system had available.
    """

    def __init__(self, path: str | os.PathLike[str], needed_bytes: int, free_bytes: int) -> None:
        self.path = Path(path)
        self.needed_bytes = int(needed_bytes)
        self.free_bytes = int(free_bytes)
        super().__init__(
            errno.ENOSPC,
            f"not enough disk space to write {path}: need {needed_bytes} bytes, "
            f"{free_bytes} bytes free",
        )

    def __str__(self) -> str:
        return str(self.strerror)


# ------------------------------------------------------------------------ manifest


@dataclass
class CameraInfo:
    """``camera``: sensor size (px), pixel pitch (mm), bit depth and principal point (px)."""

    width: int
    height: int
    pixel_pitch_mm: float
    bit_depth: int
    principal_point_px: tuple[float, float] | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def pp(self) -> tuple[float, float]:
        """Principal point (x, y) in px; the sensor centre ((W−1)/2, (H−1)/2) when absent."""
        if self.principal_point_px is not None:
            return self.principal_point_px
        return ((self.width - 1) / 2.0, (self.height - 1) / 2.0)

    @property
    def shape(self) -> tuple[int, int]:
        """Array shape ``(height, width)`` of every image of the archive."""
        return (self.height, self.width)

    @property
    def max_count(self) -> int:
        """Largest valid pixel value, ``2**bit_depth − 1``."""
        return (1 << self.bit_depth) - 1


@dataclass
class OpticsInfo:
    """``optics``: main-lens focal length F, microlens focal length f, microlens pitch D (mm).

    The optional tolerances (mm, 1 sigma) say how far the data-sheet F and f
    may be off; absent, the calibration uses documented defaults.
    """

    main_focal_mm: float
    mla_focal_mm: float
    mla_pitch_mm: float
    main_focal_tolerance_mm: float | None = None
    mla_focal_tolerance_mm: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class BoardInfo:
    """``board``: square side s and reference-corner gap Cr (mm)."""

    square_mm: float = 10.0
    reference_gap_mm: float = 0.1
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class RailInfo:
    """``rail``: ``u = zero_object_distance_mm + direction·rail_mm`` (mm).

    ``zero_object_distance_tolerance_mm`` (optional, 1 sigma): how well the rail
    zero distance is known (measured with a ruler: a millimetre or two).
    """

    zero_object_distance_mm: float
    direction: int = 1
    zero_object_distance_tolerance_mm: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class FrameEntry:
    """One ``frames[]`` entry: frame index, rail position (mm), relative file, optional SHA-256."""

    index: int
    rail_mm: float
    file: str
    sha256: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"index": self.index, "rail_mm": self.rail_mm, "file": self.file}
        if self.sha256 is not None:
            out["sha256"] = self.sha256
        _merge_extra(out, self.extra)
        return out


@dataclass
class SweepManifest:
    """The parsed ``sweep.json``. Unknown keys of every object are kept in ``extra``."""

    camera: CameraInfo
    optics: OpticsInfo
    board: BoardInfo
    rail: RailInfo
    white: str = DEFAULT_WHITE
    frames: list[FrameEntry] = field(default_factory=list)
    white_sha256: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def object_distance_mm(self, rail_mm: float) -> float:
        """Board-to-main-lens distance u (mm) at rail position ``rail_mm`` (mm)."""
        return self.rail.zero_object_distance_mm + self.rail.direction * rail_mm

    @property
    def indices(self) -> list[int]:
        """Frame indices in manifest order."""
        return [f.index for f in self.frames]

    def frame_entry(self, index: int) -> FrameEntry:
        """The entry with frame index ``index``; ``KeyError`` if there is none."""
        for entry in self.frames:
            if entry.index == index:
                return entry
        raise KeyError(f"no frame with index {index} in the manifest")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready manifest, known keys first, then the preserved unknown keys."""
        cam: dict[str, Any] = {
            "width": self.camera.width,
            "height": self.camera.height,
            "pixel_pitch_mm": self.camera.pixel_pitch_mm,
            "bit_depth": self.camera.bit_depth,
        }
        if self.camera.principal_point_px is not None:
            cam["principal_point_px"] = list(self.camera.principal_point_px)
        _merge_extra(cam, self.camera.extra)
        optics: dict[str, Any] = {
            "main_focal_mm": self.optics.main_focal_mm,
            "mla_focal_mm": self.optics.mla_focal_mm,
            "mla_pitch_mm": self.optics.mla_pitch_mm,
        }
        for key in ("main_focal_tolerance_mm", "mla_focal_tolerance_mm"):
            if getattr(self.optics, key) is not None:
                optics[key] = getattr(self.optics, key)
        _merge_extra(optics, self.optics.extra)
        board: dict[str, Any] = {
            "square_mm": self.board.square_mm,
            "reference_gap_mm": self.board.reference_gap_mm,
        }
        _merge_extra(board, self.board.extra)
        rail: dict[str, Any] = {
            "zero_object_distance_mm": self.rail.zero_object_distance_mm,
            "direction": self.rail.direction,
        }
        if self.rail.zero_object_distance_tolerance_mm is not None:
            rail["zero_object_distance_tolerance_mm"] = self.rail.zero_object_distance_tolerance_mm
        _merge_extra(rail, self.rail.extra)
        out: dict[str, Any] = {
            "format": FORMAT,
            "camera": cam,
            "optics": optics,
            "board": board,
            "rail": rail,
            "white": self.white,
        }
        if self.white_sha256 is not None:
            out["white_sha256"] = self.white_sha256
        out["frames"] = [f.to_dict() for f in self.frames]
        _merge_extra(out, self.extra)
        return out

    @classmethod
    def from_dict(cls, obj: Any, *, source: str = MANIFEST_NAME) -> SweepManifest:
        """Parse a decoded ``sweep.json``; :class:`ArchiveError` lists every problem."""
        problems = validate_manifest(obj)
        if problems:
            raise ArchiveError(_problem_summary(source, problems), problems)
        cam = obj["camera"]
        pp = cam.get("principal_point_px")
        frames = [
            FrameEntry(
                index=f["index"],
                rail_mm=float(f["rail_mm"]),
                file=f["file"],
                sha256=f.get("sha256"),
                extra=_unknown(f, _FRAME_KEYS),
            )
            for f in obj["frames"]
        ]
        return cls(
            camera=CameraInfo(
                width=cam["width"],
                height=cam["height"],
                pixel_pitch_mm=float(cam["pixel_pitch_mm"]),
                bit_depth=cam["bit_depth"],
                principal_point_px=None if pp is None else (float(pp[0]), float(pp[1])),
                extra=_unknown(cam, _CAMERA_KEYS),
            ),
            optics=OpticsInfo(
                main_focal_mm=float(obj["optics"]["main_focal_mm"]),
                mla_focal_mm=float(obj["optics"]["mla_focal_mm"]),
                mla_pitch_mm=float(obj["optics"]["mla_pitch_mm"]),
                main_focal_tolerance_mm=_optional_float(obj["optics"], "main_focal_tolerance_mm"),
                mla_focal_tolerance_mm=_optional_float(obj["optics"], "mla_focal_tolerance_mm"),
                extra=_unknown(obj["optics"], _OPTICS_KEYS + _OPTICS_OPTIONAL),
            ),
            board=BoardInfo(
                square_mm=float(obj["board"]["square_mm"]),
                reference_gap_mm=float(obj["board"]["reference_gap_mm"]),
                extra=_unknown(obj["board"], _BOARD_KEYS),
            ),
            rail=RailInfo(
                zero_object_distance_mm=float(obj["rail"]["zero_object_distance_mm"]),
                direction=obj["rail"]["direction"],
                zero_object_distance_tolerance_mm=_optional_float(
                    obj["rail"], "zero_object_distance_tolerance_mm"
                ),
                extra=_unknown(obj["rail"], _RAIL_KEYS + _RAIL_OPTIONAL),
            ),
            white=obj["white"],
            frames=frames,
            white_sha256=obj.get("white_sha256"),
            extra=_unknown(obj, _TOP_KEYS),
        )


_TOP_KEYS = ("format", "camera", "optics", "board", "rail", "white", "white_sha256", "frames")
_CAMERA_KEYS = ("width", "height", "pixel_pitch_mm", "bit_depth", "principal_point_px")
_OPTICS_KEYS = ("main_focal_mm", "mla_focal_mm", "mla_pitch_mm")
_OPTICS_OPTIONAL = ("main_focal_tolerance_mm", "mla_focal_tolerance_mm")
_BOARD_KEYS = ("square_mm", "reference_gap_mm")
_RAIL_KEYS = ("zero_object_distance_mm", "direction")
_RAIL_OPTIONAL = ("zero_object_distance_tolerance_mm",)


def _optional_float(section: Mapping[str, Any], key: str) -> float | None:
    value = section.get(key)
    return None if value is None else float(value)


_FRAME_KEYS = ("index", "rail_mm", "file", "sha256")


def _merge_extra(out: dict[str, Any], extra: Mapping[str, Any]) -> None:
    for key, value in extra.items():
        out.setdefault(key, value)


def _unknown(obj: Mapping[str, Any], known: tuple[str, ...]) -> dict[str, Any]:
    return {k: v for k, v in obj.items() if k not in known}


def _problem_summary(source: str, problems: list[str]) -> str:
    head = f"{source}: {len(problems)} problem{'s' if len(problems) != 1 else ''}"
    return head + "\n  " + "\n  ".join(problems)


# ---------------------------------------------------------------------- validation


def _show(value: Any) -> str:
    """A value as it appears in the JSON file, shortened for messages."""
    try:
        text = json.dumps(value, allow_nan=True)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _safe_relpath_problem(value: Any) -> str | None:
    """Why ``value`` is not a relative POSIX path inside the archive, or None."""
    if not isinstance(value, str) or not value:
        return f"must be a non-empty relative path string, got {_show(value)}"
    p = PurePosixPath(value)
    if p.is_absolute() or "\\" in value or re.match(r"^[A-Za-z]:", value):
        return f"must be a relative POSIX path inside the archive, got {_show(value)}"
    if ".." in p.parts:
        return f"must not leave the archive ('..'), got {_show(value)}"
    return None


class _Checker:
    """Collects ``path: reason`` problems while walking a manifest."""

    def __init__(self) -> None:
        self.problems: list[str] = []

    def add(self, path: str, reason: str) -> None:
        self.problems.append(f"{path}: {reason}")

    def section(self, obj: Mapping[str, Any], key: str) -> Mapping[str, Any] | None:
        if key not in obj:
            self.add(key, "required key missing")
            return None
        value = obj[key]
        if not isinstance(value, Mapping):
            self.add(key, f"must be an object, got {_show(value)}")
            return None
        return value

    def get(self, obj: Mapping[str, Any], path: str, key: str) -> tuple[bool, Any]:
        if key not in obj:
            self.add(f"{path}.{key}", "required key missing")
            return False, None
        return True, obj[key]

    def positive_int(self, obj: Mapping[str, Any], path: str, key: str) -> None:
        ok, v = self.get(obj, path, key)
        if ok and not (_is_int(v) and v > 0):
            self.add(f"{path}.{key}", f"must be a positive integer, got {_show(v)}")

    def positive_number(self, obj: Mapping[str, Any], path: str, key: str) -> None:
        ok, v = self.get(obj, path, key)
        if ok and not (_is_number(v) and v > 0):
            self.add(f"{path}.{key}", f"must be a positive number, got {_show(v)}")


def validate_manifest(obj: Any) -> list[str]:
    """Every problem of a decoded ``sweep.json`` as ``"json.path: reason"`` (empty if valid).

    Unknown keys are not problems (readers ignore them). An empty ``frames`` list
    is valid (a job whose acquisition has just started).
    """
    c = _Checker()
    if not isinstance(obj, Mapping):
        c.add("<root>", f"must be a JSON object, got {_show(obj)}")
        return c.problems

    if "format" not in obj:
        c.add("format", f'required key missing (expected "{FORMAT}")')
    elif obj["format"] != FORMAT:
        c.add("format", f'must be "{FORMAT}", got {_show(obj["format"])}')

    cam = c.section(obj, "camera")
    if cam is not None:
        c.positive_int(cam, "camera", "width")
        c.positive_int(cam, "camera", "height")
        c.positive_number(cam, "camera", "pixel_pitch_mm")
        ok, v = c.get(cam, "camera", "bit_depth")
        if ok and not (_is_int(v) and 1 <= v <= 16):
            c.add("camera.bit_depth", f"must be an integer 1..16, got {_show(v)}")
        pp = cam.get("principal_point_px")
        if pp is not None and not (
            isinstance(pp, list) and len(pp) == 2 and all(_is_number(x) for x in pp)
        ):
            c.add(
                "camera.principal_point_px",
                f"must be [x, y] with two finite numbers (px) or be absent, got {_show(pp)}",
            )

    optics = c.section(obj, "optics")
    if optics is not None:
        for key in _OPTICS_KEYS:
            c.positive_number(optics, "optics", key)
        for key in _OPTICS_OPTIONAL:
            if optics.get(key) is not None:
                c.positive_number(optics, "optics", key)

    board = c.section(obj, "board")
    if board is not None:
        c.positive_number(board, "board", "square_mm")
        c.positive_number(board, "board", "reference_gap_mm")
        s: Any = board.get("square_mm")
        gap: Any = board.get("reference_gap_mm")
        if _is_number(s) and _is_number(gap) and 0 < s <= gap:
            c.add(
                "board.reference_gap_mm",
                f"must be smaller than board.square_mm ({_show(s)}), got {_show(gap)}",
            )

    rail = c.section(obj, "rail")
    if rail is not None:
        c.positive_number(rail, "rail", "zero_object_distance_mm")
        ok, v = c.get(rail, "rail", "direction")
        if ok and not (_is_int(v) and v in (1, -1)):
            c.add("rail.direction", f"must be 1 or -1, got {_show(v)}")
        for key in _RAIL_OPTIONAL:
            if rail.get(key) is not None:
                c.positive_number(rail, "rail", key)

    white = obj.get("white")
    if "white" not in obj:
        c.add("white", "required key missing")
    elif (why := _safe_relpath_problem(white)) is not None:
        c.add("white", why)
    if "white_sha256" in obj and not (
        isinstance(obj["white_sha256"], str) and _HEX64.match(obj["white_sha256"])
    ):
        c.add("white_sha256", f"must be 64 hex digits, got {_show(obj['white_sha256'])}")

    if "frames" not in obj:
        c.add("frames", "required key missing")
    elif not isinstance(obj["frames"], list):
        c.add("frames", f"must be an array, got {_show(obj['frames'])}")
    else:
        _validate_frames(c, obj["frames"], white if isinstance(white, str) else None)
    return c.problems


def _validate_frames(c: _Checker, frames: list[Any], white: str | None) -> None:
    seen_index: dict[int, int] = {}
    seen_file: dict[str, int] = {}
    for k, entry in enumerate(frames):
        path = f"frames[{k}]"
        if not isinstance(entry, Mapping):
            c.add(path, f"must be an object, got {_show(entry)}")
            continue
        ok, index = c.get(entry, path, "index")
        if ok:
            if not (_is_int(index) and index >= 0):
                c.add(f"{path}.index", f"must be a non-negative integer, got {_show(index)}")
            elif index in seen_index:
                c.add(
                    f"{path}.index",
                    f"duplicate index {index} (also frames[{seen_index[index]}].index)",
                )
            else:
                seen_index[index] = k
        ok, rail = c.get(entry, path, "rail_mm")
        if ok and not _is_number(rail):
            c.add(f"{path}.rail_mm", f"must be a finite number (mm), got {_show(rail)}")
        ok, file = c.get(entry, path, "file")
        if ok:
            if (why := _safe_relpath_problem(file)) is not None:
                c.add(f"{path}.file", why)
            elif file == white:
                c.add(f"{path}.file", f"is the white image {_show(file)}")
            elif file in seen_file:
                c.add(
                    f"{path}.file",
                    f"duplicate file {_show(file)} (also frames[{seen_file[file]}].file)",
                )
            else:
                seen_file[file] = k
        if "sha256" in entry and not (
            isinstance(entry["sha256"], str) and _HEX64.match(entry["sha256"])
        ):
            c.add(f"{path}.sha256", f"must be 64 hex digits, got {_show(entry['sha256'])}")


def _manifest_path(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    return p / MANIFEST_NAME if p.is_dir() else p


def read_manifest(path: str | os.PathLike[str]) -> SweepManifest:
    """Read and validate ``sweep.json`` (``path`` is the file or the archive directory).

    Raises :class:`ArchiveError` whose ``problems`` lists every problem (a missing
    file and invalid JSON are single problems).
    """
    mpath = _manifest_path(path)
    try:
        text = mpath.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ArchiveError(f"{mpath}: file not found (not an {FORMAT} archive?)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ArchiveError(f"{mpath}: cannot read: {exc}") from exc
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ArchiveError(
            f"{mpath}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
        ) from None
    return SweepManifest.from_dict(obj, source=str(mpath))


def manifest_from_header(header: SweepManifest | Mapping[str, Any]) -> SweepManifest:
    """A manifest from a header (a :class:`SweepManifest` or a dict such as
    ``calibration.sim_sweep.manifest_header``); ``format``, ``white`` and ``frames``
    may be omitted from a dict (defaults: this format, ``white.png``, no frames).
    """
    if isinstance(header, SweepManifest):
        obj: Any = header.to_dict()
    else:
        obj = json.loads(json.dumps(dict(header), allow_nan=True))  # deep copy, JSON types only
        obj.setdefault("format", FORMAT)
        obj.setdefault("white", DEFAULT_WHITE)
        obj.setdefault("frames", [])
    return SweepManifest.from_dict(obj, source="manifest header")


# -------------------------------------------------------------------------- images


def _png_header_problem(data: bytes) -> tuple[str | None, tuple[int, int, int, int] | None]:
    """Walk the PNG chunk structure: (problem or None, IHDR (width, height, bits, colour type))."""
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG file (bad signature)", None
    pos, ihdr = len(PNG_SIGNATURE), None
    while True:
        if pos + 8 > len(data):
            return "truncated PNG (no IEND chunk)", ihdr
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        if pos + 12 + length > len(data):
            return f"truncated PNG (chunk {ctype!r} runs past the end of the file)", ihdr
        if ctype == b"IHDR":
            if length != 13:
                return "corrupt PNG (bad IHDR chunk)", None
            w, h, bits, colour = struct.unpack(">IIBB", data[pos + 8 : pos + 18])
            ihdr = (w, h, bits, colour)
        elif ihdr is None:
            return "corrupt PNG (first chunk is not IHDR)", None
        if ctype == b"IEND":
            return None, ihdr
        pos += 12 + length


def decode_image(
    data: bytes,
    path: str | os.PathLike[str],
    *,
    expected_shape: tuple[int, int] | None,
    bit_depth: int,
) -> NDArray[np.uint16]:
    """Decode PNG bytes (``path`` is only used in messages); see :func:`read_image`."""
    problem, ihdr = _png_header_problem(data)
    if problem is not None:
        raise CorruptImageError(path, problem)
    assert ihdr is not None
    width, height, bits, colour = ihdr
    if colour != 0:
        raise NotGrayscaleError(
            path, f"not a grayscale image (PNG colour type {_PNG_COLOUR_TYPES.get(colour, colour)})"
        )
    if expected_shape is not None and (height, width) != tuple(expected_shape):
        raise WrongImageSizeError(
            path,
            f"wrong size {width}×{height} px, expected {expected_shape[1]}×{expected_shape[0]} px",
        )
    if bits < 16 and bit_depth > bits:
        raise BitDepthError(
            path, f"{bits}-bit PNG cannot hold {bit_depth}-bit counts (a 16-bit PNG is needed)"
        )
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CorruptImageError(path, "corrupt PNG (cannot be decoded)")
    if img.ndim != 2:
        raise NotGrayscaleError(path, f"not a grayscale image (decoded shape {img.shape})")
    out: NDArray[np.uint16] = img.astype(np.uint16, copy=False)
    limit = (1 << bit_depth) - 1
    peak = int(out.max()) if out.size else 0
    if peak > limit:
        n = int(np.count_nonzero(out > limit))
        raise BitDepthError(
            path,
            f"{n} pixel(s) exceed {limit} = 2^{bit_depth}−1 (max {peak}): wrong bit depth, "
            "or counts not right-aligned",
        )
    return out


def read_image(
    path: str | os.PathLike[str],
    *,
    expected_shape: tuple[int, int] | None,
    bit_depth: int,
) -> NDArray[np.uint16]:
    """Read a grey PNG as ``uint16`` counts of shape ``(height, width)``.

    ``expected_shape`` is ``(height, width)`` in px (None: not checked);
    ``bit_depth`` the camera's bits per pixel (values must be ≤ 2**bit_depth − 1).
    An 8-bit (or lower) PNG is accepted when ``bit_depth ≤ 8``.

    Raises :class:`MissingImageError`, :class:`CorruptImageError` (also truncated
    files), :class:`WrongImageSizeError`, :class:`BitDepthError`,
    :class:`NotGrayscaleError`.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise MissingImageError(p, "file not found") from None
    except IsADirectoryError:
        raise CorruptImageError(p, "is a directory, not a PNG file") from None
    except OSError as exc:
        raise CorruptImageError(p, f"cannot read: {exc.strerror or exc}") from exc
    return decode_image(data, p, expected_shape=expected_shape, bit_depth=bit_depth)


def encode_image(
    image: NDArray[Any],
    *,
    expected_shape: tuple[int, int] | None,
    bit_depth: int,
    compression: int = 1,
    name: str = "<image>",
) -> bytes:
    """Encode counts as a 16-bit grey PNG after checking shape, type and range.

    ``image`` must be a 2-D integer array of shape ``expected_shape`` (height,
    width) with values in ``0 .. 2**bit_depth − 1``; ``compression`` is the level of
    :func:`calibration.png.encode_png_gray16` (0: stored, 1: fast Huffman-only
    deflate, the default; the frames are noisy anyway).
    """
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise NotGrayscaleError(name, f"must be a 2-D grey image, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise BitDepthError(name, f"must hold integer counts, got dtype {arr.dtype}")
    if expected_shape is not None and arr.shape != tuple(expected_shape):
        raise WrongImageSizeError(
            name,
            f"wrong size {arr.shape[1]}×{arr.shape[0]} px, "
            f"expected {expected_shape[1]}×{expected_shape[0]} px",
        )
    limit = (1 << bit_depth) - 1
    if arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        if lo < 0 or hi > limit:
            raise BitDepthError(
                name, f"values {lo}..{hi} outside 0..{limit} = 2^{bit_depth}−1 (wrong bit depth?)"
            )
    return encode_png_gray16(arr, level=compression)


def sha256_hex(data: bytes) -> str:
    """SHA-256 of ``data`` as 64 lower-case hex digits."""
    return hashlib.sha256(data).hexdigest()


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes as 64 lower-case hex digits (read in 1 MiB chunks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


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
                problem, _ = _png_header_problem(data)
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
        if not _is_int(index) or index < 0:
            raise ValueError(f"frame index must be a non-negative integer, got {index!r}")
        if not _is_number(rail_mm):
            raise ValueError(f"rail_mm must be a finite number (mm), got {rail_mm!r}")
        clash = set(extra) & set(_FRAME_KEYS)
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
