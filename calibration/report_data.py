"""What a calibration report reads from the sweep archive: camera record and archive checksum.

:func:`camera_record` is the one place that reads the camera's identity and its
per-frame data from a manifest (``sweep.json``), tolerantly: newer station
archives carry ``camera.identity`` (``vendor``, ``model``, ``serial``,
``firmware``) and per-frame ``temperature_c``, ``exposure_us``, ``gain_db``;
older ones do not, and then the record says "not recorded".

:func:`archive_digest` is the archive's fingerprint for the report: SHA-256
over a fixed header, the manifest's bytes and every frame's and the white
image's SHA-256 (as the manifest records them; computed from the file where it
records none). With ``verify`` every file is read again and compared with the
recorded checksum, so the report can say whether the archive is intact.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .archive import file_sha256

DIGEST_HEADER = b"lfcal-archive-digest/1\n"
NOT_RECORDED = "not recorded"


@dataclass(frozen=True)
class CameraRecord:
    """Identity and per-frame conditions of the camera that took a sweep.

    Identity fields are strings (``"not recorded"`` when absent); ranges are
    ``(min, max)`` over the frames that record the value, None when none does.
    """

    vendor: str = NOT_RECORDED
    model: str = NOT_RECORDED
    serial: str = NOT_RECORDED
    firmware: str = NOT_RECORDED
    temperature_c: tuple[float, float] | None = None
    exposure_us: tuple[float, float] | None = None
    gain_db: tuple[float, float] | None = None
    frames_with_temperature: int = 0
    frames: int = 0


def _text(value: Any) -> str:
    if value is None or (isinstance(value, str) and not value.strip()):
        return NOT_RECORDED
    return str(value)


def _range(values: list[Any]) -> tuple[float, float] | None:
    nums = [
        float(v)
        for v in values
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(float(v))
    ]
    return (min(nums), max(nums)) if nums else None


def camera_record(manifest: dict[str, Any] | None) -> CameraRecord:
    """The camera record of a parsed ``sweep.json`` (None or an older manifest: "not
    recorded"); never raises on missing or odd-typed entries."""
    if not isinstance(manifest, dict):
        return CameraRecord()
    camera = manifest.get("camera")
    identity = camera.get("identity") if isinstance(camera, dict) else None
    ident = identity if isinstance(identity, dict) else {}
    frames = [f for f in manifest.get("frames") or [] if isinstance(f, dict)]
    temps = [f.get("temperature_c") for f in frames]
    return CameraRecord(
        vendor=_text(ident.get("vendor")),
        model=_text(ident.get("model")),
        serial=_text(ident.get("serial")),
        firmware=_text(ident.get("firmware")),
        temperature_c=_range(temps),
        exposure_us=_range([f.get("exposure_us") for f in frames]),
        gain_db=_range([f.get("gain_db") for f in frames]),
        frames_with_temperature=sum(1 for t in temps if _range([t]) is not None),
        frames=len(frames),
    )


@dataclass(frozen=True)
class ArchiveDigest:
    """An archive's fingerprint (see the module docstring).

    Attributes:
        sha256: hex digest.
        files: frames + white image covered.
        verified: True when every file was re-read and matched, False when one did
            not (``problems``), None when the files were not re-read.
        problems: ``file: what`` for every mismatch or unreadable file.
    """

    sha256: str
    files: int
    verified: bool | None
    problems: list[str] = field(default_factory=list)


def archive_digest(root: str | Path, *, verify: bool = False) -> ArchiveDigest:
    """The fingerprint of the archive in ``root``; ``ValueError`` without a readable manifest."""
    root = Path(root)
    try:
        raw = (root / "sweep.json").read_bytes()
        manifest = json.loads(raw)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{root}: no readable sweep.json ({exc})") from None
    h = hashlib.sha256(DIGEST_HEADER)
    h.update(raw)
    entries: list[tuple[str, str, Any]] = [
        ("white", str(manifest.get("white", "white.png")), manifest.get("white_sha256"))
    ]
    for f in manifest.get("frames") or []:
        if isinstance(f, dict):
            entries.append((str(f.get("index")), str(f.get("file")), f.get("sha256")))
    problems: list[str] = []
    for name, rel, recorded in entries:
        path = root / rel
        actual: str | None = None
        if verify or not isinstance(recorded, str):
            try:
                actual = file_sha256(path)
            except OSError as exc:
                problems.append(f"{rel}: cannot be read ({exc.strerror or exc})")
        if verify and isinstance(recorded, str) and actual is not None and actual != recorded:
            problems.append(f"{rel}: SHA-256 differs from the manifest's")
        digest = recorded if isinstance(recorded, str) else (actual or "missing")
        h.update(f"{name} {rel} {digest}\n".encode())
    verified: bool | None = (not problems) if verify else (False if problems else None)
    return ArchiveDigest(h.hexdigest(), len(entries), verified, problems)


__all__ = [
    "NOT_RECORDED",
    "ArchiveDigest",
    "CameraRecord",
    "archive_digest",
    "camera_record",
]
