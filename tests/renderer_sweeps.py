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

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from calibration.archive_images import read_image
from calibration.pipeline import calibrate_archive
from calibration.png import encode_png_gray16
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


def render_mcsim_short(out: Path, seed: int, *extra: str, frames: int = 31) -> Path:
    """mcsim's 50 px camera, 31 frames 2 mm apart from rail 20 mm (focus inside), with
    ``extra`` options; ``frames``: only the first ones of that sweep."""
    return render_mcsim(
        out, frames=frames, step_mm=2, seed=seed, extra=(*extra, "--start-mm", "20")
    )


def with_sensor_defects(
    sweep: Path,
    out: Path,
    *,
    seed: int,
    prnu: float = 0.01,
    dsnu_counts: float = 2.0,
    hot_fraction: float = 2e-4,
    dead_fraction: float = 5e-5,
    flicker: float = 0.02,
) -> Path:
    """A copy of ``sweep`` as a real sensor would have recorded it: a fixed gain per pixel
    (PRNU, 1σ fraction), a fixed offset per pixel (DSNU, 1σ counts), hot pixels (a fixed
    extra 200 counts to full scale) and dead ones (0), the same in the white image and
    every frame, and each frame's exposure off by ``flicker`` (1σ fraction); counts
    rounded and held to the manifest's bit depth, checksums rewritten."""
    shutil.copytree(sweep, out)
    manifest = json.loads((out / "sweep.json").read_text())
    bit_depth = int(manifest["camera"].get("bit_depth", 12))
    full_scale = (1 << bit_depth) - 1
    rng = np.random.default_rng(seed)
    shape = read_image(out / manifest["white"], expected_shape=None, bit_depth=bit_depth).shape
    gain = 1.0 + prnu * rng.standard_normal(shape)
    offset = dsnu_counts * rng.standard_normal(shape)
    hot = np.where(rng.random(shape) < hot_fraction, rng.uniform(200, full_scale, shape), 0.0)
    dead = rng.random(shape) < dead_fraction

    def record(name: str, exposure: float) -> str:
        recorded = read_image(out / name, expected_shape=shape, bit_depth=bit_depth)
        counts = recorded.astype(np.float64)
        counts = counts * gain * exposure + offset + hot
        counts = np.clip(np.rint(np.where(dead, 0.0, counts)), 0, full_scale)
        data = encode_png_gray16(counts.astype(np.uint16))
        (out / name).write_bytes(data)
        return hashlib.sha256(data).hexdigest()

    white_sha = record(manifest["white"], 1.0)
    if "white_sha256" in manifest:
        manifest["white_sha256"] = white_sha
    for frame in manifest["frames"]:
        sha = record(frame["file"], 1.0 + flicker * rng.standard_normal())
        if "sha256" in frame:
            frame["sha256"] = sha
    (out / "sweep.json").write_text(json.dumps(manifest, indent=2))
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
