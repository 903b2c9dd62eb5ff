"""Shared helpers of the station tests (imported by the other ``test_station_*`` modules).

The simulated station: preset ``rotated`` on a 1200×400 px sensor (the
standard corner stays in view over the whole sweep), the emulated Zaber rail
and XY stage on a real pty, driven by the real Zaber driver. Rendered frames
are cached per bench state in pytest's cache directory
(``[camera] frame_cache``, :mod:`drivers.sim.frame_cache`), shared by the xdist workers and the ``kill -9``
subprocess: the first run renders each rail position once (~1 s each), later
runs only read them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calibration.archive import SweepArchive
from calibration.presets import get_preset, with_sweep
from calibration.sim_sweep import fit_frame, truth
from drivers.sim.frame_cache import CachedScene
from drivers.sim.plenoptic_scene import scene_from_preset
from station.config import StationConfig, load_config, with_frame_cache
from station.orchestrator import Orchestrator
from station.store import JobStore

WIDTH, HEIGHT = 1200, 400
SPEEDUP = 20.0
"""Emulated motion runs this many times faster than real time."""

STATION_TOML = """
[camera]
backend = "simulated"
preset = "rotated"
width = {width}
height = {height}
timeout_s = {timeout_s}
seed = 0

[rail]
driver = "emulated"
microstep_um = 0.047625
max_speed_mm_s = 20.0
accel_mm_s2 = 100.0
min_mm = 0.0
max_mm = 100.0
position_tolerance_um = 2.0
settle_s = 0.0
zero_object_distance_mm = 380.0
direction = 1

[xy_stage]
driver = "emulated"
microstep_um = 0.09921875
max_speed_mm_s = 50.0
accel_mm_s2 = 200.0
position_tolerance_um = 2.0
x = {{ device = 2, axis = 1, min_mm = 0.0, max_mm = 300.0 }}
y = {{ device = 2, axis = 2, min_mm = 0.0, max_mm = 300.0 }}
alignment = {{ x_mm = 100.0, y_mm = 100.0 }}
white = {{ x_mm = 300.0, y_mm = 100.0 }}

[optics]
main_focal_mm = 50.0
mla_focal_mm = 2.0
mla_pitch_mm = 0.2
pixel_pitch_mm = 0.0025

[sweep]
start_mm = 0.0
stop_mm = 95.0
step_mm = 5.0
max_frames = 2000

[storage]
data_dir = "data"
database = "data/lfcal.sqlite3"
"""


def write_config(
    directory: Path, *, width: int = WIDTH, height: int = HEIGHT, timeout_s: float = 2.0
) -> Path:
    """A station configuration file in ``directory`` (storage under ``directory/data``)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "station.toml"
    path.write_text(
        STATION_TOML.format(width=width, height=height, timeout_s=timeout_s), encoding="utf-8"
    )
    return path


def frame_cache(pytestconfig: pytest.Config) -> Path:
    """The rendered-frame cache shared by every station test (and later runs)."""
    return Path(pytestconfig.cache.mkdir("lfcal-station-frames"))


def make_station(
    directory: Path,
    cache: Path,
    *,
    analysis_workers: int = 0,
    speedup: float = SPEEDUP,
    **config_kwargs: Any,
) -> Orchestrator:
    """A started orchestrator on the simulated station (close it!)."""
    config = load_config(write_config(directory, **config_kwargs))
    return Orchestrator(
        with_frame_cache(config, cache),
        emulator_speedup=speedup,
        analysis_workers=analysis_workers,
    ).start()


def bench_of(station: Orchestrator) -> Any:
    """The simulated bench of the station's open devices (emulator, camera fault hooks)."""
    devices = station.devices
    assert devices is not None, "the devices are not open"
    return devices.bench


def simulated_truth(config: StationConfig, frames: int, step_mm: float) -> dict[str, Any]:
    """The simulator's ground truth for the configured camera and a sweep from rail 0."""
    cam = config.camera
    preset = with_sweep(get_preset(cam.preset), frames=frames, step_mm=step_mm)
    return truth(fit_frame(preset, cam.width, cam.height, cam.principal_point_px))


def assert_calibration_matches(result: dict[str, Any], truth_: dict[str, Any]) -> None:
    """a, b and the focus plane against the simulator: within 3σ, and near enough for a
    20-frame test sweep (the camera comes from the sweep, no data sheet is trusted)."""
    unc = result["uncertainty"]
    for key in ("a_mm", "b_mm"):
        err = result[key] - truth_[key]
        assert abs(err) <= 3 * unc[key] and abs(err) <= 5e-3 * truth_[key], (key, err, unc[key])
    assert result["Q"] == pytest.approx(truth_["Q"], rel=1e-3)
    err = result["focus"]["object_distance_mm"] - truth_["focus"]["object_distance_mm"]
    assert abs(err) <= 3 * result["focus"]["uncertainty_mm"] and abs(err) <= 2.0, err


def assert_complete_archive(station: Orchestrator, job_id: int, frames: int) -> SweepArchive:
    """Every frame 0..frames-1 exactly once in the manifest and the store, all checksums right."""
    job_dir = station.archive_dir(job_id)
    archive = SweepArchive.open(job_dir)
    check = archive.check(decode=False)
    assert check.ok, check.problems()
    assert not check.unlisted
    assert archive.indices == list(range(frames))
    assert archive.manifest.white_sha256 is not None
    steps = station.steps(job_id)
    assert [s.index for s in steps] == list(range(frames))
    by_index = {e.index: e for e in archive.manifest.frames}
    for step in steps:
        entry = by_index[step.index]
        assert entry.sha256 == step.sha256
        assert entry.rail_mm == pytest.approx(step.actual_mm)
        assert abs(step.actual_mm - step.commanded_mm) <= 0.0021  # 2 µm tolerance + rounding
    assert not list(job_dir.rglob("*.tmp"))
    return archive


def assert_kept_frames(station: Orchestrator, job_id: int) -> list[int]:
    """A stopped job: the recorded frames are 0..n-1, in the manifest, with right checksums."""
    job_dir = station.archive_dir(job_id)
    archive = SweepArchive.open(job_dir)
    check = archive.check(decode=False)
    assert check.ok, check.problems()
    indices = [s.index for s in station.steps(job_id)]
    assert indices == list(range(len(indices)))
    assert archive.indices == indices
    assert not list(job_dir.rglob("*.tmp"))
    return indices


def read_db_steps(db: Path, job_id: int) -> list[int]:
    """Step indices recorded in the database file (read-only, from any process)."""
    with JobStore(db) as store:
        return [s.index for s in store.steps(job_id)]


def manifest_indices(job_dir: Path) -> list[int]:
    """Frame indices listed in ``sweep.json``."""
    data = json.loads((job_dir / "sweep.json").read_text(encoding="utf-8"))
    return [f["index"] for f in data["frames"]]


def test_cached_scene_returns_the_same_frame_for_the_same_state(tmp_path: Path) -> None:
    """The cache key covers the state: same state -> same frame (no render); other -> render."""
    from drivers.sim.sim_camera import SceneState

    scene = CachedScene(scene_from_preset("rotated", width=240, height=160), tmp_path)
    state = SceneState(object_distance_mm=420.0)
    kwargs: dict[str, Any] = {
        "roi": (0, 0, 240, 160),
        "seed": [0, 1],
        "bit_depth": 12,
        "exposure_scale": 1.0,
        "gain_db": 0.0,
    }
    first = scene.render(state, **kwargs)
    again = scene.render(state, **{**kwargs, "seed": [0, 2]})
    assert np.array_equal(first, again) and (scene.hits, scene.misses) == (1, 1)
    other = scene.render(SceneState(object_distance_mm=420.001), **kwargs)
    assert scene.misses == 2 and other.shape == first.shape
