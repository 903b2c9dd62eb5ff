"""Crash recovery: make a job's archive and its step rows agree, verified by SHA-256.

A sweep step writes in this order: frame file (temporary file, fsync, rename),
manifest (same), step row (SQLite transaction). A process killed anywhere in
between leaves one of these states, which :func:`reconcile` resolves:

* a temporary file (``.0007.png.1a2b3c4d.tmp``): deleted;
* a frame file the manifest does not list (killed before the manifest write):
  deleted; the step is captured again;
* a manifest entry without a step row (killed before the SQLite commit): its
  file is checked against the manifest's SHA-256 and, if it matches, the step is
  **adopted** (row inserted from the manifest entry) -- never captured twice;
* a step row and manifest entry whose file is missing or does not match the
  stored checksum: both are dropped and the step is captured again;
* a step row without a manifest entry: dropped (captured again);
* a white image that is missing or does not match ``white_sha256``: forgotten,
  and captured again.

Nothing else is touched. The manifest, if it changed, is rewritten atomically.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from calibration.archive import (
    FRAMES_DIR,
    MANIFEST_NAME,
    ArchiveError,
    FrameEntry,
    SweepManifest,
    atomic_write_bytes,
    read_manifest,
    sha256_hex,
)
from station.store import ACTIVE_STATES, JobRecord, JobState, JobStore, StepRecord


@dataclass
class VerifyReport:
    """What :func:`reconcile` found and did for one job.

    Attributes:
        verified: step indices whose frame matches its checksum (kept).
        adopted: indices found in the manifest without a step row, verified and recorded.
        dropped: index -> why the frame will be captured again.
        white_ok: the white image is present and matches its checksum.
        removed_files: stray files deleted (temporary or unlisted frames).
        archive_exists: the job directory holds a manifest.
    """

    verified: list[int] = field(default_factory=list)
    adopted: list[int] = field(default_factory=list)
    dropped: dict[int, str] = field(default_factory=dict)
    white_ok: bool = False
    removed_files: list[str] = field(default_factory=list)
    archive_exists: bool = False

    @property
    def kept(self) -> list[int]:
        """Every index whose frame is usable (verified or adopted), sorted."""
        return sorted(set(self.verified) | set(self.adopted))

    def summary(self, frames_total: int) -> str:
        """One sentence for the job's transition reason."""
        if not self.archive_exists:
            return "no archive on disk yet"
        parts = [f"{len(self.kept)} of {frames_total} frames verified by SHA-256"]
        if self.adopted:
            parts.append(
                f"{len(self.adopted)} recovered from the manifest ({_ranges(self.adopted)})"
            )
        if self.dropped:
            why = "; ".join(f"{i}: {r}" for i, r in sorted(self.dropped.items())[:5])
            parts.append(f"{len(self.dropped)} dropped and to be captured again ({why})")
        parts.append("white image " + ("verified" if self.white_ok else "to be captured"))
        return ", ".join(parts)


def _ranges(indices: list[int]) -> str:
    out: list[str] = []
    for i in sorted(indices):
        if out and out[-1].split("-")[-1] == str(i - 1):
            out[-1] = out[-1].split("-")[0] + f"-{i}"
        else:
            out.append(str(i))
    return ", ".join(out)


def _file_sha(path: Path) -> str | None:
    try:
        return sha256_hex(path.read_bytes())
    except OSError:
        return None


def _entry_time(entry: FrameEntry, key: str, default: float) -> float:
    value = entry.extra.get(key)
    return float(value) if isinstance(value, int | float) else default


def write_manifest(job_dir: Path, manifest: SweepManifest) -> None:
    """Rewrite ``sweep.json`` atomically (same format as :class:`SweepWriter`)."""
    text = json.dumps(manifest.to_dict(), indent=2, allow_nan=False) + "\n"
    atomic_write_bytes(job_dir / MANIFEST_NAME, text.encode("utf-8"))


def reconcile(store: JobStore, job_id: int, job_dir: Path) -> VerifyReport:
    """Verify the job's frames against the stored checksums and repair the bookkeeping.

    Raises :class:`calibration.archive.ArchiveError` if the manifest exists but
    cannot be read (it is written atomically, so that means outside damage).
    """
    report = VerifyReport()
    steps = {s.index: s for s in store.steps(job_id)}
    manifest_path = job_dir / MANIFEST_NAME
    if not manifest_path.is_file():
        store.delete_steps(job_id, sorted(steps))
        for index in steps:
            report.dropped[index] = "no archive manifest"
        return report
    report.archive_exists = True
    manifest = read_manifest(job_dir)
    changed = False

    for path in _stray_temp_files(job_dir):
        path.unlink(missing_ok=True)
        report.removed_files.append(str(path.relative_to(job_dir)))

    keep: list[FrameEntry] = []
    for entry in manifest.frames:
        actual = _file_sha(job_dir / entry.file)
        step = steps.pop(entry.index, None)
        expected = entry.sha256 or (step.sha256 if step else None)
        if actual is None:
            why = f"{entry.file} is missing"
        elif expected is None:
            why = f"{entry.file} has no recorded checksum"
        elif actual != expected or (step is not None and step.sha256 != actual):
            why = f"{entry.file} does not match its SHA-256"
        else:
            why = ""
        if why:
            report.dropped[entry.index] = why
            changed = True
            if step is not None:
                store.delete_steps(job_id, [entry.index])
            (job_dir / entry.file).unlink(missing_ok=True)
            continue
        keep.append(entry)
        if step is not None:
            report.verified.append(entry.index)
            continue
        now = time.time()
        store.record_step(
            StepRecord(
                job_id=job_id,
                index=entry.index,
                commanded_mm=float(entry.extra.get("commanded_rail_mm", entry.rail_mm)),
                actual_mm=entry.rail_mm,
                file=entry.file,
                sha256=actual or "",
                started_at=_entry_time(entry, "started_at", now),
                captured_at=_entry_time(entry, "captured_at", now),
                written_at=now,
            )
        )
        report.adopted.append(entry.index)

    for index in sorted(steps):  # rows without a manifest entry
        report.dropped[index] = "recorded but not listed in the manifest"
    store.delete_steps(job_id, sorted(steps))

    listed = {e.file for e in keep}
    frames_dir = job_dir / FRAMES_DIR
    if frames_dir.is_dir():
        for path in sorted(frames_dir.iterdir()):
            rel = f"{FRAMES_DIR}/{path.name}"
            if path.is_file() and not path.name.startswith(".") and rel not in listed:
                path.unlink(missing_ok=True)
                report.removed_files.append(rel)

    white_sha = manifest.white_sha256
    if white_sha is not None and _file_sha(job_dir / manifest.white) == white_sha:
        report.white_ok = True
    elif white_sha is not None:
        manifest.white_sha256 = None
        changed = True
    if changed:
        manifest.frames = keep
        write_manifest(job_dir, manifest)
    return report


def _stray_temp_files(job_dir: Path) -> list[Path]:
    out: list[Path] = []
    for folder in (job_dir, job_dir / FRAMES_DIR):
        if folder.is_dir():
            out.extend(
                p for p in folder.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp")
            )
    return out


def archive_manifest(job_dir: Path) -> SweepManifest | None:
    """The job's manifest, or None if there is none yet or it cannot be read."""
    try:
        return read_manifest(job_dir)
    except ArchiveError:
        return None


def interrupt_orphaned_jobs(
    store: JobStore, transition: Callable[..., JobRecord]
) -> dict[int, VerifyReport]:
    """At start-up: every job of this station found ``running`` or ``paused`` (the
    previous process died under it) has its archive reconciled (:func:`reconcile`)
    and becomes ``interrupted`` with what was found, through ``transition`` (called
    as ``transition(job_id, state, reason, last_error=reason)``). Returns the
    verification reports (job id -> report); a job whose archive cannot be
    verified still becomes ``interrupted``, with that reason."""
    reports: dict[int, VerifyReport] = {}
    for job in store.list_jobs(states=set(ACTIVE_STATES), station=store.own_station):
        try:
            report = reconcile(store, job.id, Path(job.archive_dir))
            reports[job.id] = report
            summary = report.summary(job.frames_total)
        except Exception as exc:  # noqa: BLE001 - the job must still become interrupted
            summary = f"its archive could not be verified: {exc}"
        reason = (
            f"the station process ended while the job was {job.state.value} "
            f"(found at start-up); {summary}"
        )
        transition(job.id, JobState.INTERRUPTED, reason, last_error=reason)
    return reports


__all__ = [
    "VerifyReport",
    "archive_manifest",
    "interrupt_orphaned_jobs",
    "reconcile",
    "write_manifest",
]
