"""Every fault kind of the Zaber emulator (and of the simulated camera) injected mid-sweep.

Each fault is injected through the real emulator behind a real pty (or the
simulated camera's fault hooks) when step 1 of an 8-frame sweep is recorded;
the rail's next move or the camera's next grab meets it. The outcome is either
a recovery (the job succeeds with a complete, verified archive) or a failed
job whose last error names the fault, with every frame captured before it
kept; failed jobs are then resumed to a complete archive (re-homing the rail
when it lost its reference, reopening the devices when the link was lost).
"""

from __future__ import annotations

import shutil
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from test_station_helpers import (
    assert_complete_archive,
    assert_kept_frames,
    bench_of,
    frame_cache,
    make_station,
)

import calibration.archive_writer as archive_module
import station.faults as faults_module
from station.events import JobEvent
from station.orchestrator import Orchestrator
from station.store import JobState

END = {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
SWEEP = {"start_mm": 0.0, "stop_mm": 35.0, "step_mm": 5.0, "calibrate": False}  # 8 frames
RAIL = (1, 1)  # device, axis of the rail on the emulated chain


@pytest.fixture
def station(tmp_path: Path, pytestconfig: pytest.Config) -> Iterator[Orchestrator]:
    st = make_station(tmp_path, frame_cache(pytestconfig), timeout_s=1.0)
    yield st
    st.close()


def inject_at_step(
    station: Orchestrator, index: int, inject: Callable[[Any], None]
) -> list[JobEvent]:
    """Run ``inject(devices)`` when step ``index`` is recorded; return the job's events."""
    seen: list[JobEvent] = []
    fired = threading.Event()

    def listener(event: JobEvent) -> None:
        seen.append(event)
        if event.type == "step" and event.id == index and not fired.is_set():
            fired.set()
            inject(station.devices)

    station.add_listener(listener)
    return seen


def run(station: Orchestrator, request: dict[str, Any] = SWEEP) -> Any:
    job = station.submit(request)
    return station.wait_for(job.id, END, timeout_s=90)


def faults_of(events: list[JobEvent]) -> list[str]:
    return [e.data["error"] for e in events if e.type == "fault"]


RECOVERED: dict[str, tuple[Callable[[Any], None], str | None]] = {
    # transport faults: the driver's port re-sends idempotent commands by itself
    "dropped reply": (lambda d: d.bench.emulator.drop_replies(1, device=1), None),
    "garbled reply": (lambda d: d.bench.emulator.garble_replies(1, device=1), None),
    "late reply": (lambda d: d.bench.emulator.delay_replies(1.0, 1, device=1), None),
    # motion faults: the station's policy repeats the move
    "stuck busy": (lambda d: d.bench.emulator.stick_next_move(*RAIL), "still BUSY"),
    "position drift": (lambda d: d.bench.emulator.drift_next_move(*RAIL, 400), "off by"),
    "power cycle": (
        lambda d: d.bench.emulator.power_cycle_on_next_move(*RAIL, 0.5),
        "reference",
    ),
    # camera faults
    "camera timeout": (lambda d: d.camera.fail_next_grabs("timeout"), "no frame within"),
    "incomplete frame": (
        lambda d: d.camera.fail_next_grabs("incomplete", 2),
        "missing packets",
    ),
    "camera lost": (lambda d: d.camera.fail_next_grabs("lost"), "stopped answering"),
}


@pytest.mark.parametrize("kind", list(RECOVERED))
def test_fault_is_recovered_and_the_archive_is_complete(station: Orchestrator, kind: str) -> None:
    inject, evidence = RECOVERED[kind]
    events = inject_at_step(station, 1, inject)
    done = run(station)
    assert done.state is JobState.SUCCEEDED, done.last_error
    assert_complete_archive(station, done.id, 8)
    stats = bench_of(station).emulator.stats
    if kind == "dropped reply":
        assert stats.dropped == 1
    elif kind == "garbled reply":
        assert stats.garbled == 1
    elif kind == "late reply":
        assert stats.delayed == 1
    else:
        assert evidence is not None
        assert any(evidence in f for f in faults_of(events)), faults_of(events)
    if kind == "power cycle":
        assert any(e.type == "phase" and "lost its reference" in e.data["detail"] for e in events)


def _revive(d: Any) -> None:
    d.bench.emulator.set_dead(1, False)


FAILING: dict[str, tuple[Callable[[Any], None], str, Callable[[Any], None] | None]] = {
    "dead device": (lambda d: d.bench.emulator.set_dead(1), "no reply", _revive),
    "stall": (lambda d: d.bench.emulator.stall_next_move(*RAIL), "stall", None),
    "limit hit": (lambda d: d.bench.emulator.limit_on_next_move(*RAIL), "limit", None),
    "disconnect": (
        lambda d: d.bench.emulator.disconnect_on_next_move(*RAIL),
        "connection on",
        None,
    ),
    "camera unplugged": (lambda d: d.camera.unplug(), "unplugged", lambda d: d.camera.replug()),
}


@pytest.mark.parametrize("kind", list(FAILING))
def test_fault_fails_the_job_keeps_frames_and_resume_completes_it(
    station: Orchestrator, kind: str
) -> None:
    inject, message, repair = FAILING[kind]
    events = inject_at_step(station, 1, inject)
    failed = run(station)
    assert failed.state is JobState.FAILED
    assert failed.last_error is not None and message in failed.last_error.lower()
    assert "frames kept" in failed.last_error
    kept = assert_kept_frames(station, failed.id)
    assert 2 <= len(kept) < 8
    assert not station.devices or not bench_of(station).emulator.snapshot(*RAIL).busy
    # the operator fixes the cause; resume continues from the first missing frame
    # (a camera that could not be reconnected makes the station reopen every device:
    # then the new devices need no repair)
    if repair is not None and station.devices is not None:
        repair(station.devices)
    del events[:]
    station.resume(failed.id, "fault cleared")
    done = station.wait_for(failed.id, END, timeout_s=90)
    homed = [e.data["detail"] for e in events if e.type == "phase" and e.data["phase"] == "homing"]
    if kind in ("stall", "limit hit"):
        assert homed == ["rail"]  # the rail lost its reference: homed before continuing
    assert done.state is JobState.SUCCEEDED, done.last_error
    assert_complete_archive(station, failed.id, 8)
    reasons = [t.reason for t in station.transitions(failed.id)]
    assert reasons[-2].startswith(f"resumed with {len(kept)} of 8 frames")


def test_blank_and_saturated_frames_fail_with_the_numbers(station: Orchestrator) -> None:
    blank = run(station, dict(SWEEP, exposure_us=10.0))
    assert blank.state is JobState.FAILED
    assert "the white image is blank" in (blank.last_error or "")
    saturated = run(station, dict(SWEEP, exposure_us=5e6))
    assert saturated.state is JobState.FAILED
    assert "saturated" in (saturated.last_error or "") and "reduce the exposure" in (
        saturated.last_error or ""
    )
    assert station.steps(blank.id) == [] and station.steps(saturated.id) == []


def test_an_overexposed_white_fails_the_calibrating_job_before_the_sweep(
    tmp_path: Path, pytestconfig: pytest.Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A white image whose lit area is clipped: the grab's own check (more than 1 % of the
    pixels at full scale) is relaxed here, so the calibration's refuses it when the MLA
    grid is fitted (in the analysis worker): the job fails before the rail moves, saying
    what and what to do."""
    monkeypatch.setattr(faults_module, "SATURATED_FRACTION", 1.0)
    station = make_station(tmp_path, frame_cache(pytestconfig), timeout_s=1.0, analysis_workers=1)
    try:
        failed = run(station, dict(SWEEP, exposure_us=5e6, calibrate=True))
        assert failed.state is JobState.FAILED
        error = failed.last_error or ""
        assert "the white image is unusable: the white image is overexposed" in error, error
        assert "of its lit pixels are at full scale" in error and "lower exposure" in error
        assert station.steps(failed.id) == []
    finally:
        station.close()


def test_low_disk_space_is_detected_before_a_write(
    station: Orchestrator, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = shutil.disk_usage
    full = threading.Event()

    def disk_usage(path: Any) -> Any:
        usage = real(path)
        return usage._replace(free=1024 * 1024) if full.is_set() else usage

    monkeypatch.setattr(archive_module.shutil, "disk_usage", disk_usage)
    inject_at_step(station, 1, lambda d: full.set())
    failed = run(station)
    assert failed.state is JobState.FAILED
    assert "disk full" in (failed.last_error or "") and "bytes free" in (failed.last_error or "")
    kept = assert_kept_frames(station, failed.id)
    assert 2 <= len(kept) < 8
    full.clear()
    station.resume(failed.id)
    done = station.wait_for(failed.id, END, timeout_s=90)
    assert done.state is JobState.SUCCEEDED, done.last_error
    assert_complete_archive(station, failed.id, 8)
