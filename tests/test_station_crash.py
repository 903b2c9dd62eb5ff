"""``kill -9`` of a real ``lfcal sweep`` process mid-sweep, then restart and resume.

The sweep runs in a subprocess (``python -m station.jobs_cli sweep``: the
function ``lfcal sweep`` calls) on the simulated station. When its progress
output reports the 6th frame, the process is killed with SIGKILL -- wherever
it is: moving the rail, writing a PNG, renaming it, rewriting the manifest or
committing the step. A new station on the same database and data directory
then finds the job ``running``, verifies its frames against the stored
checksums and marks it ``interrupted``; ``resume`` re-homes the (new, never
homed) emulated stages and continues from the first missing frame to a
complete archive -- every frame exactly once, every checksum right -- and a
calibration that matches the simulator.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_station_helpers import (
    assert_calibration_matches,
    assert_complete_archive,
    assert_kept_frames,
    frame_cache,
    manifest_indices,
    read_db_steps,
    simulated_truth,
    write_config,
)

from station.config import load_config, with_frame_cache
from station.orchestrator import Orchestrator
from station.store import JobState

ROOT = Path(__file__).resolve().parents[1]
END = {JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED, JobState.INTERRUPTED}
KILL_AT_FRAME = 6


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid:
            out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while True:
        alive = [p for p in pids if _alive(p)]
        if not alive or time.monotonic() > deadline:
            return alive
        threading.Event().wait(0.05)


def test_kill_9_mid_sweep_then_restart_and_resume(
    tmp_path: Path, pytestconfig: pytest.Config
) -> None:
    cache = frame_cache(pytestconfig)
    config_path = write_config(tmp_path)
    cmd = [
        sys.executable, "-m", "station.jobs_cli", "sweep",
        "--config", str(config_path),
        "--sim-frame-cache", str(cache),
        "--emulator-speedup", "5",
    ]  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    lines: queue.Queue[str | None] = queue.Queue()

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=pump, daemon=True).start()
    seen: list[str] = []
    helpers: list[int] = []
    try:
        deadline = time.monotonic() + 90
        while True:
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            assert line is not None, "the sweep ended before it was killed:\n" + "".join(seen)
            seen.append(line)
            m = re.search(r"frame (\d+)/20", line)
            if m and int(m.group(1)) >= KILL_AT_FRAME:
                helpers = _children(proc.pid)
                os.kill(proc.pid, signal.SIGKILL)
                break
    finally:
        if proc.poll() is None and not helpers:
            proc.kill()
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    # the analysis worker processes follow their parent
    assert _wait_gone(helpers, timeout_s=30) == []

    config = load_config(config_path)
    db = Path(config.storage.database)
    job_dir = next(Path(config.storage.data_dir).glob("job-000001-*"))
    on_disk = manifest_indices(job_dir)
    in_db = read_db_steps(db, 1)
    assert len(in_db) >= KILL_AT_FRAME
    # the kill may fall between the manifest write and the step commit, never the reverse
    assert set(in_db) <= set(on_disk) and len(on_disk) - len(in_db) <= 1

    station = Orchestrator(
        with_frame_cache(config, cache), emulator_speedup=20.0, analysis_workers=1
    ).start()
    try:
        job = station.record(1)
        assert job.state is JobState.INTERRUPTED
        report = station.recovery_reports[1]
        assert report.kept == on_disk and not report.dropped
        assert sorted(report.adopted) == sorted(set(on_disk) - set(in_db))
        assert report.white_ok
        last = station.transitions(1)[-1]
        assert (last.from_state, last.to_state) == (JobState.RUNNING, JobState.INTERRUPTED)
        assert f"{len(on_disk)} of 20 frames verified by SHA-256" in last.reason
        assert assert_kept_frames(station, 1) == on_disk

        station.resume(1, "restarted after the crash")
        done = station.wait_for(1, END, timeout_s=120)
        assert done.state is JobState.SUCCEEDED, done.last_error
        assert_complete_archive(station, 1, 20)
        trans = [(t.from_state, t.to_state) for t in station.transitions(1)]
        assert trans == [
            (None, JobState.QUEUED),
            (JobState.QUEUED, JobState.RUNNING),
            (JobState.RUNNING, JobState.INTERRUPTED),
            (JobState.INTERRUPTED, JobState.QUEUED),
            (JobState.QUEUED, JobState.RUNNING),
            (JobState.RUNNING, JobState.SUCCEEDED),
        ]
        result = station.result(1)
        t = simulated_truth(config, 20, 5.0)
        assert_calibration_matches(result, t)
        assert len(result["frames"]) == 20
    finally:
        station.close()
