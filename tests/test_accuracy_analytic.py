"""The calibration on the two analytic renderers: the project's simulator and the
independent one (``bench/crosscheck/indsim.py``), the same small camera as the ray
tracer's test, 25 frames 4 mm apart; bounds twice the targets of issue 10
(:mod:`renderer_sweeps`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from renderer_sweeps import calibrate, check_accuracy, render_indsim

from calibration.optics import CameraOptics, main_aperture_for_matching, mla_distance_for_focus
from calibration.presets import get_preset, with_sweep
from calibration.sim_sweep import fit_frame, write_sweep


def test_the_independent_renderers_sweep_is_calibrated_within_twice_the_targets(
    tmp_path: Path,
) -> None:
    sweep = render_indsim(tmp_path / "indsim", frames=25, step_mm=4, seed=3)
    result, truth = calibrate(sweep)
    check_accuracy(result, truth)


@pytest.mark.parametrize(
    ("direction", "zero_object_distance_mm"),
    [(1, 170.0), (-1, 266.0)],  # the same object distances, the rail run the other way
)
def test_the_project_simulators_sweep_is_calibrated_within_twice_the_targets(
    tmp_path: Path, direction: int, zero_object_distance_mm: float
) -> None:
    F, f, D, b, u0 = 25.0, 1.5, 0.125, 1.95, 220.3
    L = mla_distance_for_focus(u0, F, f, b)
    optics = CameraOptics(
        F=F, f=f, D=D, delta=0.0025, b=b, L=L, aperture=main_aperture_for_matching(L, b, D)
    )
    preset = get_preset("paper")
    preset = replace(preset, camera=replace(preset.camera, optics=optics))
    preset = with_sweep(
        preset,
        zero_object_distance_mm=zero_object_distance_mm,
        direction=direction,
        frames=25,
        step_mm=4.0,
    )
    sweep = write_sweep(tmp_path / "sim", fit_frame(preset, 2100, 360), seed=4)
    result, truth = calibrate(Path(sweep))
    check_accuracy(result, truth)
