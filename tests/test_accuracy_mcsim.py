"""The calibration on the Monte-Carlo ray tracer (point-sampled pixels, ray noise, no PSF).

A 50-frame sweep (2 mm steps) of ``bench/mcsim``'s small camera; bounds are twice
the targets of issue 10, and every uncertainty must cover its error
(:mod:`renderer_sweeps`).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from renderer_sweeps import calibrate, check_accuracy, render_mcsim


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_mcsim(tmp_path_factory.mktemp("mcsim") / "small", frames=50, step_mm=2, seed=7)


def test_the_ray_traced_sweep_is_calibrated_within_twice_the_targets(sweep: Path) -> None:
    result, truth = calibrate(sweep)
    check_accuracy(result, truth)
    assert result["corners_found"]["reference_frames"] > 25
    assert all(p["determined_by"] == "sweep" for k, p in result["priors"].items() if k != "L_mm")
