"""A calibration report from a result and its sweep archive on disk.

:func:`report_from_archive` gathers what :func:`calibration.report_html.build_report`
shows from the archive directory: the manifest (camera identity, per-frame
temperatures), the archive fingerprint (optionally re-reading every file), and
crops of the frame nearest the focus plane rendered with the calibrated and the
designed patch size (flat-fielded with the archive's white image). Anything the
archive cannot give is said in the report instead of failing it: a report of a
result whose archive is gone still shows every number and plot.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .archive import ArchiveError, SweepArchive
from .export_model import CalibratedCamera, ResultError
from .raw_render import FrameMismatch
from .report_data import archive_digest
from .report_html import ReportInputs, build_report, render_crops


def focus_frame_index(result: dict[str, Any]) -> int:
    """The frame whose rail position is nearest the focus plane (else the middle frame);
    ``ValueError`` when the result lists no frames."""
    frames = [f for f in result.get("frames", []) if isinstance(f.get("index"), int)]
    if not frames:
        raise ValueError("the result lists no frames")
    focus = (result.get("focus") or {}).get("rail_mm")
    if not isinstance(focus, int | float):
        return int(frames[len(frames) // 2]["index"])

    def distance(f: dict[str, Any]) -> float:
        rail = f.get("rail_mm")
        return abs(float(rail) - focus) if isinstance(rail, int | float) else float("inf")

    return int(min(frames, key=distance)["index"])


def archive_of(result: dict[str, Any], near: Path | None = None) -> Path | None:
    """The sweep archive of a result: ``station.archive_dir`` when it exists, else ``near``
    (a directory, or a file's directory) when it holds a ``sweep.json``."""
    recorded = (result.get("station") or {}).get("archive_dir")
    if isinstance(recorded, str) and (Path(recorded) / "sweep.json").is_file():
        return Path(recorded)
    if near is not None:
        base = near if near.is_dir() else near.parent
        if (base / "sweep.json").is_file():
            return base
    return None


def report_from_archive(
    result: dict[str, Any],
    archive_dir: Path | None,
    *,
    designed_px: float | None = None,
    verify: bool = False,
    source: str | None = None,
    job_id: int | None = None,
) -> str:
    """The HTML report of ``result`` with what ``archive_dir`` holds (None: no archive)."""
    inputs = ReportInputs(source=source, job_id=job_id)
    if archive_dir is None:
        inputs.crops_note = (
            "The sweep archive is not available: no camera identity, archive checksum or "
            "rendered images."
        )
        return build_report(result, inputs)
    try:
        inputs.manifest = json.loads((archive_dir / "sweep.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        inputs.crops_note = f"The archive's manifest cannot be read: {exc}"
        return build_report(result, inputs)
    try:
        inputs.digest = archive_digest(archive_dir, verify=verify)
    except ValueError as exc:
        inputs.crops_note = str(exc)
    notes = []
    try:
        camera = CalibratedCamera.from_result(result)
        archive = SweepArchive.open(archive_dir)
        index = focus_frame_index(result)
        raw = archive.frame(index)
        white = archive.white()
        inputs.crops = render_crops(raw, camera, designed_px=designed_px, white=white)
        notes.append(f"Frame {index} (nearest the focus plane), flat-fielded with the white image.")
        if designed_px is None:
            notes.append(
                "The designed optics are not known (give the designed b, e.g. the station's "
                "[optics] designed_b_mm), so only the calibrated patch size is shown."
            )
    except (ArchiveError, ResultError, FrameMismatch, ValueError, KeyError) as exc:
        notes.append(f"No rendered images: {exc}")
    inputs.crops_note = " ".join(n for n in [inputs.crops_note, *notes] if n)
    return build_report(result, inputs)


__all__ = ["archive_of", "focus_frame_index", "report_from_archive"]
