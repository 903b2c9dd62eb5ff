"""The orchestrator on the simulated station: a calibrated sweep, pause/resume, cancel, queue.

Real components throughout: the emulated Zaber rail and XY stage on a pty
behind the real driver, the simulated camera (frames cached per bench state,
see ``test_station_helpers``), a real SQLite file, real archive files and real
analysis worker processes. Pause and cancel are requested from an event
listener when a given step is recorded, so they land mid-sweep
deterministically: the writer thread runs the listener before it takes the
next frame, and the hardware thread is at most three frames ahead.
"""

from __future__ import annotations

import io
import json
import threading
from collections.abc import Iterator
from contextlib import redirect_stdout
from pathlib import Path

import pytest
from test_station_helpers import (
    assert_calibration_matches,
    assert_complete_archive,
    assert_kept_frames,
    bench_of,
    frame_cache,
    make_station,
    simulated_truth,
)

from calibration.pipeline import FrameAnalyzer, SweepGeometry
from station.events import JobEvent
from station.jobs_cli import jobs_main
from station.orchestrator import Orchestrator, ResultNotReady
from station.store import InvalidTransition, JobState
from station.sweep import RequestInvalid

END = {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
SHORT = {"start_mm": 0.0, "stop_mm": 35.0, "step_mm": 5.0, "calibrate": False}  # 8 frames


@pytest.fixture
def station(tmp_path: Path, pytestconfig: pytest.Config) -> Iterator[Orchestrator]:
    st = make_station(tmp_path, frame_cache(pytestconfig))
    yield st
    st.close()


def on_step(station: Orchestrator, index: int, action: object) -> None:
    """Call ``action(event)`` (in the writer thread) when step ``index`` is recorded.

    Register it before submitting the job, so no event can slip past it."""
    fired = threading.Event()

    def listener(event: JobEvent) -> None:
        if event.type == "step" and event.id == index and not fired.is_set():
            fired.set()
            action(event)  # type: ignore[operator]

    station.add_listener(listener)


def test_full_sweep_ends_in_a_calibration_matching_the_simulator(
    tmp_path: Path, pytestconfig: pytest.Config
) -> None:
    station = make_station(tmp_path, frame_cache(pytestconfig), analysis_workers=1)
    try:
        events = station.subscribe()
        job = station.submit({})  # the configured sweep: 0..95 mm, 5 mm steps
        # the worker may pick the job up before submit() returns: queued or already running
        assert job.frames_total == 20 and job.state in (JobState.QUEUED, JobState.RUNNING)
        done = station.wait_for(job.id, END, timeout_s=120)
        assert done.state is JobState.SUCCEEDED, done.last_error
        assert_complete_archive(station, job.id, 20)

        result = station.result(job.id)
        t = simulated_truth(station.config, 20, 5.0)
        assert_calibration_matches(result, t)
        assert result["station"]["job_id"] == job.id
        on_disk = json.loads((station.archive_dir(job.id) / "result.json").read_text())
        assert on_disk["a_mm"] == result["a_mm"]
        # every step carries its analysis summary
        assert all(s.summary is not None and s.summary["Q"] for s in station.steps(job.id))

        seen = events.drain()
        steps = [e.id for e in seen if e.type == "step"]
        assert steps == list(range(20))  # monotonic event ids = step indices
        assert sum(e.type == "analysis" for e in seen) == 20
        states = [e.data["state"] for e in seen if e.type == "state"]
        assert states == ["queued", "running", "succeeded"]
        phases = [e.data["phase"] for e in seen if e.type == "phase"]
        assert phases[:1] == ["preparing"] and "white" in phases and "calibrating" in phases

        replay = station.replay(job.id, after=16)
        assert [e.id for e in replay if e.type == "step"] == [17, 18, 19]
        assert replay[-1].type == "state" and replay[-1].data["state"] == "succeeded"
        assert replay[0].data["summary"]["Q"] == pytest.approx(result["frames"][17]["Q"], rel=1e-9)
        transitions = [(t.from_state, t.to_state) for t in station.transitions(job.id)]
        assert transitions == [
            (None, JobState.QUEUED),
            (JobState.QUEUED, JobState.RUNNING),
            (JobState.RUNNING, JobState.SUCCEEDED),
        ]
    finally:
        station.close()


def test_pause_at_a_step_boundary_then_resume_to_a_complete_archive(
    station: Orchestrator,
) -> None:
    on_step(station, 1, lambda e: station.pause(e.job_id, "operator checks the board"))
    job = station.submit(SHORT)
    paused = station.wait_for(job.id, {JobState.PAUSED, *END}, timeout_s=60)
    assert paused.state is JobState.PAUSED
    kept = assert_kept_frames(station, job.id)
    assert 2 <= len(kept) < 8
    assert paused.frames_done == len(kept)  # every grabbed frame was written before pausing
    emulator = bench_of(station).emulator
    assert not emulator.snapshot(1, 1).busy  # the rail is stopped
    assert station.pause(job.id).state is JobState.PAUSED  # pausing again changes nothing
    station.resume(job.id, "board checked")
    done = station.wait_for(job.id, END, timeout_s=60)
    assert done.state is JobState.SUCCEEDED, done.last_error
    assert_complete_archive(station, job.id, 8)
    trans = station.transitions(job.id)
    assert [t.to_state for t in trans] == [
        JobState.QUEUED,
        JobState.RUNNING,
        JobState.PAUSED,
        JobState.RUNNING,
        JobState.SUCCEEDED,
    ]
    assert trans[2].reason == "operator checks the board" and trans[3].reason == "board checked"


def test_pause_before_the_white_image_then_resume(station: Orchestrator) -> None:
    """A pause that lands before the white image: after resuming, the XY stage goes to the
    white position again and the flat field is a real white image."""
    fired = threading.Event()

    def listener(event: JobEvent) -> None:
        if event.type == "phase" and event.data["phase"] == "preparing" and not fired.is_set():
            fired.set()
            station.pause(event.job_id)

    station.add_listener(listener)  # before submitting: the worker may start at once
    job = station.submit(SHORT)
    paused = station.wait_for(job.id, {JobState.PAUSED, *END}, timeout_s=60)
    assert paused.state is JobState.PAUSED and paused.frames_done == 0
    station.resume(job.id)
    done = station.wait_for(job.id, END, timeout_s=60)
    assert done.state is JobState.SUCCEEDED, done.last_error
    archive = assert_complete_archive(station, job.id, 8)
    geometry = SweepGeometry.from_manifest(archive.manifest)
    FrameAnalyzer.from_white(geometry, archive.white())  # raises unless a white image


def test_cancel_mid_sweep_keeps_frames_and_the_queue_moves_on(station: Orchestrator) -> None:
    on_step(station, 1, lambda e: station.cancel(e.job_id, "wrong board"))
    first = station.submit(SHORT)
    second = station.submit(SHORT)
    third = station.submit(SHORT)
    assert station.cancel(third.id).state is JobState.CANCELLED  # queued: at once
    stopped = station.wait_for(first.id, END, timeout_s=60)
    assert stopped.state is JobState.CANCELLED
    kept = assert_kept_frames(station, first.id)
    assert 2 <= len(kept) < 8
    assert station.transitions(first.id)[-1].reason.startswith("wrong board")
    done = station.wait_for(second.id, END, timeout_s=60)
    assert done.state is JobState.SUCCEEDED, done.last_error
    assert_complete_archive(station, second.id, 8)
    assert station.status(third.id).frames_done == 0
    assert not station.archive_dir(third.id).exists()
    # finished jobs refuse every control request (409 in the web layer)
    for action in (station.pause, station.resume, station.cancel):
        with pytest.raises(InvalidTransition, match="cancelled"):
            action(first.id)
    with pytest.raises(InvalidTransition, match="succeeded: cannot pause"):
        station.pause(second.id)
    with pytest.raises(ResultNotReady, match="calibrate false"):
        station.result(second.id)
    with pytest.raises(ResultNotReady, match="wrong board"):
        station.result(first.id)


def test_requests_are_validated_against_the_configuration(station: Orchestrator) -> None:
    with pytest.raises(RequestInvalid) as info:
        station.submit({"start_mm": -5, "stop_mm": 120, "step_mm": 0, "exposure_us": 1})
    problems = dict(info.value.problems)
    assert "outside the rail's travel [0, 100] mm" in problems["start_mm"]
    assert "outside the rail's travel" in problems["stop_mm"]
    assert "greater than 0 mm" in problems["step_mm"]
    assert "outside the camera's exposure range [10, 6e+07]" in problems["exposure_us"]
    with pytest.raises(RequestInvalid, match="make 9501 frames; at most 2000"):
        station.submit({"start_mm": 0, "stop_mm": 95, "step_mm": 0.01})
    with pytest.raises(RequestInvalid, match="must not be below start_mm"):
        station.submit({"start_mm": 50, "stop_mm": 10})
    with pytest.raises(RequestInvalid, match="unknown field"):
        station.submit({"start": 1})
    assert station.jobs() == []  # nothing was stored
    first = station.submit(SHORT, idempotency_key="abc")
    again = station.submit(SHORT, idempotency_key="abc")
    assert again.id == first.id and len(station.jobs()) == 1
    station.cancel(first.id)


def test_jobs_cli_lists_and_shows_jobs(station: Orchestrator) -> None:
    job = station.submit(SHORT)
    station.wait_for(job.id, END, timeout_s=60)
    db = str(station.config.storage.database)
    out = io.StringIO()
    with redirect_stdout(out):
        assert jobs_main(["--db", db]) == 0
    row = next(line.split() for line in out.getvalue().splitlines()[1:])
    assert row[0] == str(job.id) and row[2].startswith("SIM-") and row[3:5] == ["succeeded", "8/8"]
    assert row[1] == station.store.station_id
    out = io.StringIO()
    with redirect_stdout(out):
        assert jobs_main(["--db", db, "--json", str(job.id)]) == 0
    data = json.loads(out.getvalue())
    assert [t["to"] for t in data["transitions"]] == ["queued", "running", "succeeded"]
    assert jobs_main(["--db", db, "--state", "nonsense"]) == 2


def test_manifest_records_the_camera_state_of_every_frame(station: Orchestrator) -> None:
    """Per frame: DeviceTemperature, exposure and gain actually applied, trigger, flat field."""

    def on_white(event: JobEvent) -> None:  # devices open, no frame taken yet
        if event.type == "phase" and event.data.get("phase") == "white":
            bench_of(station).camera.sensor_temperature_c = 41.25

    def warm_up(event: JobEvent) -> None:  # the sensor warms up during the sweep
        bench_of(station).camera.sensor_temperature_c = 42.5

    station.add_listener(on_white)
    on_step(station, 3, warm_up)
    job = station.submit(SHORT)
    done = station.wait_for(job.id, END, timeout_s=60)
    assert done.state is JobState.SUCCEEDED, done.last_error
    manifest = json.loads((station.archive_dir(job.id) / "sweep.json").read_text())
    frames = manifest["frames"]
    assert len(frames) == 8
    temperatures = [f["temperature_c"] for f in frames]
    assert temperatures[0] == 41.25 and temperatures[-1] == 42.5
    assert set(temperatures) == {41.25, 42.5} and temperatures == sorted(temperatures)
    exposure = station.config.camera.exposure_us
    for f in frames:
        assert (f["exposure_us"], f["gain"], f["gain_feature"]) == (exposure, 0.0, "Gain")
        assert (f["trigger"], f["flat_field"]) == ("software", "off")
    header = manifest["station"]["camera"]
    assert (header["trigger"], header["flat_field"]) == ("software", "off")
