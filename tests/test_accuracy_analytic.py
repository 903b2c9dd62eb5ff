"""The calibration on the two analytic renderers: the project's simulator and the
independent one (``bench/crosscheck/indsim.py``), the same small camera as the ray
tracer's test, 25 frames 4 mm apart; bounds twice the targets of issue 10
(:mod:`renderer_sweeps`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from renderer_sweeps import calibrate, check_accuracy, render_indsim, with_sensor_defects

from calibration.optics import CameraOptics, main_aperture_for_matching, mla_distance_for_focus
from calibration.presets import get_preset, with_sweep
from calibration.sim_sweep import fit_frame, write_sweep


@pytest.fixture(scope="module")
def indsim_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_indsim(tmp_path_factory.mktemp("indsim") / "sweep", frames=25, step_mm=4, seed=3)


@pytest.fixture(scope="module")
def indsim_calibrated(indsim_sweep: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    return calibrate(indsim_sweep)


def test_the_independent_renderers_sweep_is_calibrated_within_twice_the_targets(
    indsim_calibrated: tuple[dict[str, Any], dict[str, Any]],
) -> None:
    check_accuracy(*indsim_calibrated)


def test_a_real_sensors_fixed_pattern_and_flicker_leave_the_calibration_within_its_sigma(
    indsim_sweep: Path, indsim_calibrated: tuple[dict[str, Any], dict[str, Any]], tmp_path: Path
) -> None:
    """PRNU 1 %, DSNU 2 counts, 1 in 5000 pixels hot and 1 in 20000 dead (the same in the
    white image and every frame), each frame's exposure off by 2 % (1σ): the same
    targets, no new warning (a lone hot pixel at full scale is no clip), and a, b and
    the focus plane within 1σ of the clean sweep's."""
    clean, truth = indsim_calibrated
    result, _ = calibrate(with_sensor_defects(indsim_sweep, tmp_path / "defects", seed=5))
    check_accuracy(result, truth)
    assert result["warnings"] == clean["warnings"]
    for value, sigma in (("a_mm", "a_mm"), ("b_mm", "b_mm")):
        assert abs(result[value] - clean[value]) <= result["uncertainty"][sigma]
    moved = result["focus"]["object_distance_mm"] - clean["focus"]["object_distance_mm"]
    assert abs(moved) <= result["focus"]["uncertainty_mm"], moved


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
