"""The analysis worker pool: frames analysed and the sweep calibrated in worker
processes, at a lower CPU priority, with the same numbers as in-process."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from calibration.archive import SweepArchive
from calibration.pipeline import CalibrationError, FrameAnalyzer, SweepGeometry, combine
from station.analysis import ANALYSIS_NICENESS, AnalysisPool
from station.cli import main

FRAMES = 12


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The paper optics, 12 frames 8 mm apart around the focus plane, 2000×700 px."""
    out = tmp_path_factory.mktemp("sim") / "paper"
    args = ["simulate", str(out), "--preset", "paper", "--frames", str(FRAMES)]
    args += ["--step-mm", "8", "--width", "2000", "--height", "700", "--seed", "11"]
    assert main(args) == 0
    return out


@pytest.fixture(scope="module")
def pool() -> Iterator[AnalysisPool]:
    pool = AnalysisPool(1)
    pool.start()
    yield pool
    pool.close()


@pytest.fixture(scope="module")
def analysed(sweep: Path, pool: AnalysisPool) -> tuple:
    archive = SweepArchive.open(sweep)
    geometry = SweepGeometry.from_manifest(archive.manifest)
    analyzer = FrameAnalyzer.from_white(geometry, archive.white())
    camera = archive.manifest.camera
    session = pool.session("test-job-1", analyzer, shape=camera.shape, bit_depth=camera.bit_depth)
    for entry in archive.manifest.frames:
        session.submit(entry.index, entry.rail_mm, sweep / entry.file)
    summaries = session.wait(timeout_s=300)
    return geometry, analyzer, session, [summaries[i] for i in sorted(summaries)]


def test_workers_run_at_a_lower_cpu_priority(pool: AnalysisPool) -> None:
    if not hasattr(os, "nice"):
        pytest.skip("no nice values on this OS")
    worker_nice = pool.executor().submit(os.nice, 0).result(timeout=60)
    assert worker_nice == min(19, os.nice(0) + ANALYSIS_NICENESS)


def test_every_frame_is_analysed_in_the_workers(sweep: Path, analysed: tuple) -> None:
    _, analyzer, session, summaries = analysed
    assert [s.index for s in summaries] == list(range(FRAMES))
    assert session.done_count() == FRAMES
    assert [s.error for s in summaries] == [""] * FRAMES
    archive = SweepArchive.open(sweep)
    here = analyzer.analyze(5, archive.manifest.frames[5].rail_mm, archive.frame(5))
    assert summaries[5].to_dict(with_corners=True) == here.to_dict(with_corners=True)


def test_calibration_in_a_worker_equals_the_in_process_one(sweep: Path, analysed: tuple) -> None:
    geometry, analyzer, session, summaries = analysed
    remote = session.combine(summaries, geometry)
    local = combine(summaries, geometry, analyzer.grid).to_dict()
    for key in ("a_mm", "b_mm", "Q", "patch_size_px"):
        assert remote[key] == local[key]
    assert remote["focus"] == local["focus"]
    truth = json.loads((sweep / "truth.json").read_text())
    assert remote["b_mm"] == pytest.approx(truth["b_mm"], rel=2e-3)


def test_a_failed_calibration_in_a_worker_keeps_its_partial_result(analysed: tuple) -> None:
    geometry, _, session, summaries = analysed
    with pytest.raises(CalibrationError, match=r"found in only 3 of 3 frames") as info:
        session.combine(summaries[:3], geometry)
    partial = info.value.partial
    assert partial is not None
    assert [f["index"] for f in partial["frames"]] == [0, 1, 2]


def test_without_the_white_image_shading_the_micro_image_pitch_is_not_used(
    analysed: tuple,
) -> None:
    # the pitch's reading needs the rim-shading correction, which needs the white's shading
    geometry, analyzer, _, summaries = analysed
    with_shading = combine(summaries, geometry, analyzer.grid).to_dict()
    assert with_shading["camera_model"]["image_scale"]["used"] is True
    bare = combine(summaries, geometry, replace(analyzer.grid, shading=None)).to_dict()
    assert bare["camera_model"]["image_scale"] == {"measured": None, "used": False}
    assert bare["shading_correction"] == {"applied": False}
