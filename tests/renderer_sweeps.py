"""Small sweeps of the three renderers for the accuracy tests, and the checks they share.

The optics are a small camera (50 px lenses, F = 25 mm, f = 1.5 mm, b = 1.95 mm,
focus at u = 220.3 mm, between rail steps), cheap enough to render in a test:
the project's simulator, the independent analytic renderer
(``bench/crosscheck/indsim.py``) and the Monte-Carlo ray tracer
(``bench/mcsim``, its ``small`` preset: 30 rays per sub-pixel, 2×2 point
samples, no PSF). The bounds are twice the targets of issue 10 (focus plane
0.3 mm, a 0.03 %, b 0.01 %, p 0.02 px) where the data sheet's f is exact, and
every uncertainty must cover its error (3σ).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from calibration.pipeline import calibrate_archive
from station.summary_table import truth_value

ROOT = Path(__file__).resolve().parents[1]

SMALL_OPTICS = ["--F", "25", "--f", "1.5", "--D", "0.125", "--b", "1.95", "--u0", "220.3"]


def render_indsim(out: Path, *, frames: int, step_mm: float, seed: int) -> Path:
    cmd = [sys.executable, "-m", "bench.crosscheck.indsim", str(out), "--frames", str(frames)]
    cmd += ["--start-mm", "0", "--step-mm", str(step_mm), "--width", "2100", "--height", "360"]
    cmd += ["--pp", "1950,179.5", *SMALL_OPTICS, "--u-rail0", "170", "--theta-deg", "0.3"]
    cmd += ["--mla-offset=0.7,-1.2", "--seed", str(seed), "--jobs", "1"]
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL, timeout=900)
    return out


def render_mcsim(
    out: Path, *, frames: int, step_mm: float, seed: int, extra: tuple[str, ...] = ()
) -> Path:
    """A sweep of ``bench/mcsim``'s small camera; ``extra`` options go to its command line."""
    cmd = [sys.executable, "-m", "bench.mcsim", str(out), "--preset", "small", *extra]
    cmd += ["--frames", str(frames), "--step-mm", str(step_mm), "--seed", str(seed), "--jobs", "1"]
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL, timeout=900)
    return out


def calibrate(sweep: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    result = calibrate_archive(sweep, workers=1).to_dict()
    truth = json.loads((sweep / "truth.json").read_text())
    return result, truth


def check_accuracy(result: dict[str, Any], truth: dict[str, Any]) -> None:
    """Twice the issue-10 targets, and uncertainties that cover the errors."""
    u0 = truth_value(truth, "focus.object_distance_mm")
    a, b = truth_value(truth, "a_mm"), truth_value(truth, "b_mm")
    assert u0 is not None and a is not None and b is not None
    focus = result["focus"]
    focus_err = focus["object_distance_mm"] - u0
    assert abs(focus_err) <= 0.6, focus_err
    assert abs(focus_err) <= 3 * focus["uncertainty_mm"], (focus_err, focus["uncertainty_mm"])
    rail_true = truth_value(truth, "focus.rail_mm")  # where the station drives the board
    if rail_true is not None:
        assert abs(focus["rail_mm"] - rail_true) <= 0.6, (focus["rail_mm"], rail_true)
    # the paper's route with the exact data-sheet f: the focus plane's accuracy in a and b
    route = result["estimates"]["paper_route"]
    assert abs(route["a_mm"] / a - 1) <= 6e-4, route["a_mm"] / a - 1
    assert abs(route["b_mm"] / b - 1) <= 2e-4, route["b_mm"] / b - 1
    # the camera from the sweep (no data sheet trusted): its uncertainty covers its error
    unc = result["uncertainty"]
    assert abs(result["a_mm"] - a) <= 3 * unc["a_mm"], (result["a_mm"], a, unc["a_mm"])
    assert abs(result["b_mm"] - b) <= 3 * unc["b_mm"], (result["b_mm"], b, unc["b_mm"])
    # F from the magnification, both corners' main images placed with the camera's Q(u)
    focal = truth_value(truth, "main_focal_mm")
    assert focal is not None
    f_err = result["main_focal_mm"] - focal
    assert abs(f_err) <= 3 * unc["main_focal_mm"], (f_err, unc["main_focal_mm"])
    if result["corners_found"]["reference_frames"]:
        assert result["camera_model"]["main_image_systematic"]["main_focal_mm"] >= 0
    # the calibrated camera's p at every frame's distance
    p_true = {f["index"]: f.get("p_px", f.get("patch_size_px")) for f in truth["frames"]}
    worst = max(abs(f["patch_size_px"] - p_true[f["index"]]) for f in result["frames"])
    assert worst <= 0.04, worst
