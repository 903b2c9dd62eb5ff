"""Crash consistency of a job's archive and step rows, one kill point at a time.

A step writes the frame (temporary file, rename), then the manifest, then the
step row. Each test builds the state a ``kill -9`` leaves at one point and
checks that :func:`station.recovery.reconcile` keeps exactly the verified
frames, so a resumed job captures every missing frame once and none twice.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from calibration.archive import SweepArchive, SweepWriter
from station.recovery import reconcile
from station.store import JobStore, StepRecord

HEADER = {
    "camera": {"width": 64, "height": 48, "pixel_pitch_mm": 0.0025, "bit_depth": 12},
    "optics": {"main_focal_mm": 50.0, "mla_focal_mm": 2.0, "mla_pitch_mm": 0.2},
    "board": {"square_mm": 10.0, "reference_gap_mm": 0.1},
    "rail": {"zero_object_distance_mm": 380.0, "direction": 1},
}


def _image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 4096, (48, 64), dtype=np.uint16)


@pytest.fixture
def job(tmp_path: Path) -> Iterator[tuple[JobStore, int, Path, SweepWriter]]:
    store = JobStore(tmp_path / "jobs.sqlite3")
    record, _ = store.create_job({"frames": 6}, archive_root=tmp_path, frames_total=6)
    writer = SweepWriter.in_place(record.archive_dir, HEADER)
    writer.write_white(_image(99))
    for i in range(3):  # frames 0-2 written and recorded: a clean state
        rec = writer.add_frame(i, float(i), _image(i), commanded_rail_mm=float(i))
        store.record_step(
            StepRecord(record.id, i, float(i), float(i), rec.file, rec.sha256, 1.0, 2.0, 3.0)
        )
    yield store, record.id, Path(record.archive_dir), writer
    store.close()


def test_a_clean_archive_is_verified_and_left_alone(job: tuple) -> None:
    store, job_id, job_dir, _ = job
    before = (job_dir / "sweep.json").read_bytes()
    report = reconcile(store, job_id, job_dir)
    assert report.verified == [0, 1, 2] and not report.adopted and not report.dropped
    assert report.white_ok and (job_dir / "sweep.json").read_bytes() == before
    assert "3 of 6 frames verified by SHA-256" in report.summary(6)


def test_killed_before_the_step_commit_the_frame_is_adopted(job: tuple) -> None:
    store, job_id, job_dir, writer = job
    writer.add_frame(3, 3.0, _image(3), commanded_rail_mm=3.0, captured_at=5.0)  # no step row
    report = reconcile(store, job_id, job_dir)
    assert report.adopted == [3] and report.kept == [0, 1, 2, 3]
    step = store.step(job_id, 3)
    assert step is not None and step.commanded_mm == 3.0 and step.captured_at == 5.0
    # resuming appends frame 4 without touching 3 (it is never captured twice)
    resumed = SweepWriter.resume(job_dir)
    resumed.add_frame(4, 4.0, _image(4))
    assert SweepArchive.open(job_dir).indices == [0, 1, 2, 3, 4]


def test_killed_before_the_manifest_write_the_file_is_removed(job: tuple) -> None:
    store, job_id, job_dir, _ = job
    (job_dir / "frames" / "0003.png").write_bytes(b"a complete PNG that was never listed")
    (job_dir / "frames" / ".0004.png.1a2b3c4d.tmp").write_bytes(b"half a PNG")
    (job_dir / ".sweep.json.5e6f7a8b.tmp").write_bytes(b"{")
    report = reconcile(store, job_id, job_dir)
    assert report.kept == [0, 1, 2] and not report.dropped
    assert sorted(report.removed_files) == [
        ".sweep.json.5e6f7a8b.tmp",
        "frames/.0004.png.1a2b3c4d.tmp",
        "frames/0003.png",
    ]
    check = SweepArchive.open(job_dir).check()
    assert check.ok and not check.unlisted


def test_a_damaged_frame_is_dropped_from_manifest_and_store(job: tuple) -> None:
    store, job_id, job_dir, _ = job
    path = job_dir / "frames" / "0001.png"
    data = bytearray(path.read_bytes())
    data[-20] ^= 0xFF
    path.write_bytes(bytes(data))
    (job_dir / "frames" / "0002.png").unlink()
    report = reconcile(store, job_id, job_dir)
    assert report.kept == [0]
    assert set(report.dropped) == {1, 2} and "SHA-256" in report.dropped[1]
    assert "missing" in report.dropped[2]
    assert [s.index for s in store.steps(job_id)] == [0]
    manifest = json.loads((job_dir / "sweep.json").read_text())
    assert [f["index"] for f in manifest["frames"]] == [0]
    resumed = SweepWriter.resume(job_dir)
    for i in (1, 2):  # captured again, once each
        resumed.add_frame(i, float(i), _image(10 + i))
    assert SweepArchive.open(job_dir).check().ok


def test_a_damaged_white_image_is_captured_again(job: tuple) -> None:
    store, job_id, job_dir, _ = job
    (job_dir / "white.png").write_bytes(b"not the white image")
    report = reconcile(store, job_id, job_dir)
    assert not report.white_ok and report.kept == [0, 1, 2]
    assert "white_sha256" not in json.loads((job_dir / "sweep.json").read_text())


def test_no_archive_yet(tmp_path: Path) -> None:
    with JobStore(tmp_path / "jobs.sqlite3") as store:
        record, _ = store.create_job({}, archive_root=tmp_path, frames_total=3)
        report = reconcile(store, record.id, Path(record.archive_dir))
        assert not report.archive_exists and report.kept == []
        assert report.summary(3) == "no archive on disk yet"
