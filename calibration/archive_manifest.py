"""The sweep manifest ``sweep.json`` (OPTICS.md §5): its dataclasses, validation that lists
every problem with its JSON path, and reading (:mod:`calibration.archive` is the archive)."""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

from .archive_errors import ArchiveError

FORMAT = "lfcal-sweep/1"
"""The value of the manifest's ``format`` key."""

MANIFEST_NAME = "sweep.json"
DEFAULT_WHITE = "white.png"
FRAMES_DIR = "frames"

_HEX64 = re.compile(r"^[0-9a-fA-F]{64}$")


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
                extra=_unknown(f, FRAME_KEYS),
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


FRAME_KEYS = ("index", "rail_mm", "file", "sha256")


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


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
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
        if ok and not (is_int(v) and v > 0):
            self.add(f"{path}.{key}", f"must be a positive integer, got {_show(v)}")

    def positive_number(self, obj: Mapping[str, Any], path: str, key: str) -> None:
        ok, v = self.get(obj, path, key)
        if ok and not (is_number(v) and v > 0):
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
        if ok and not (is_int(v) and 1 <= v <= 16):
            c.add("camera.bit_depth", f"must be an integer 1..16, got {_show(v)}")
        pp = cam.get("principal_point_px")
        if pp is not None and not (
            isinstance(pp, list) and len(pp) == 2 and all(is_number(x) for x in pp)
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
        if is_number(s) and is_number(gap) and 0 < s <= gap:
            c.add(
                "board.reference_gap_mm",
                f"must be smaller than board.square_mm ({_show(s)}), got {_show(gap)}",
            )

    rail = c.section(obj, "rail")
    if rail is not None:
        c.positive_number(rail, "rail", "zero_object_distance_mm")
        ok, v = c.get(rail, "rail", "direction")
        if ok and not (is_int(v) and v in (1, -1)):
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
            if not (is_int(index) and index >= 0):
                c.add(f"{path}.index", f"must be a non-negative integer, got {_show(index)}")
            elif index in seen_index:
                c.add(
                    f"{path}.index",
                    f"duplicate index {index} (also frames[{seen_index[index]}].index)",
                )
            else:
                seen_index[index] = k
        ok, rail = c.get(entry, path, "rail_mm")
        if ok and not is_number(rail):
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
