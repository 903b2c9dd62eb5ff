"""Accuracy and speed of the ESIF core on simulated sweeps, against the simulator's truth.

For each preset (cut to a frame that shows both corners) a 100-frame sweep is
rendered (cached under ``out/bench``), calibrated, and compared with
``truth.json``. Targets (issue 10): a <= 0.03 %, b <= 0.01 %, focus plane
<= 0.3 mm, worst p error over all frames <= 0.02 px (issue 3: corner RMS at the
focus plane <= 0.05 px and not worse than ``cv2.cornerSubPix`` on the same
micro-images, lens-centre RMS <= 0.02 px); calibrate <= 15 s for 100 frames of
3000x1000 on 2 idle cores (the load average is printed).

Run: ``python -m bench.bench_accuracy [--presets paper,rotated,noisy] [--frames N]``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.archive import SweepArchive
from calibration.pipeline import calibrate_archive
from calibration.presets import get_preset, with_sweep
from calibration.sim_sweep import fit_frame, write_sweep

FRAME_SIZES = {"paper": (3000, 1000), "rotated": (2400, 800), "noisy": (3000, 1100)}
CACHE = Path("out/bench")


def _sweep(name: str, frames: int) -> Path:
    w, h = FRAME_SIZES[name]
    path = CACHE / f"{name}_{w}x{h}_{frames}"
    if (path / "sweep.json").is_file() and (path / "truth.json").is_file():
        return path
    preset = get_preset(name)
    if frames != preset.sweep.frames:
        step = preset.sweep.step_mm * (preset.sweep.frames - 1) / max(frames - 1, 1)
        preset = with_sweep(preset, frames=frames, step_mm=step)
    write_sweep(path, fit_frame(preset, w, h), seed=1, overwrite=True)
    return path


def _corner_rms(
    result: dict[str, Any], truth: dict[str, Any], archive: SweepArchive
) -> tuple[float, float, int]:
    """ESIF and cv2.cornerSubPix RMS (px) on the micro-images used in the frame nearest focus."""
    u0 = truth["focus"]["object_distance_mm"]
    frames = [f for f in result["frames"] if f.get("Q") is not None]
    best = min(frames, key=lambda f: abs(f["object_distance_mm"] - u0))
    tframe = next(t for t in truth["frames"] if t["index"] == best["index"])
    image = archive.frame(best["index"]).astype(np.float32)
    esif, cv = [], []
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    for name in ("standard", "reference"):
        tmap = {(c["i"], c["j"]): (c["x"], c["y"]) for c in tframe["corners"][name]}
        for i, j, x, y, *_ in best["corners"].get(name, []):
            t = tmap.get((int(i), int(j)))
            if t is None:
                continue
            esif.append(np.hypot(x - t[0], y - t[1]))
            start = np.array([[[round(t[0]), round(t[1])]]], dtype=np.float32)
            r = cv2.cornerSubPix(image, start, (5, 5), (-1, -1), crit)[0, 0]
            cv.append(np.hypot(r[0] - t[0], r[1] - t[1]))
    return (
        float(np.sqrt(np.mean(np.square(esif)))),
        float(np.sqrt(np.mean(np.square(cv)))),
        len(esif),
    )


def _lens_rms(result: dict[str, Any], truth: dict[str, Any]) -> float:
    from calibration.lens_grid import LensGrid

    lens = result["mla"]["lens_grid"]
    fitted = LensGrid(tuple(lens["origin_px"]), lens["pitch_px"], np.radians(lens["rotation_deg"]))
    t = truth["mla"]
    true = LensGrid(tuple(t["lens_origin_px"]), t["lens_pitch_px"], np.radians(t["rotation_deg"]))
    w, h = truth["sensor"]["width"], truth["sensor"]["height"]
    ii, jj = true.indices_in(w, h)
    tx, ty = true.centre(ii, jj)
    fi, fj = fitted.nearest(tx, ty)
    fx, fy = fitted.centre(fi, fj)
    return float(np.sqrt(np.mean((fx - tx) ** 2 + (fy - ty) ** 2)))


def evaluate(name: str, frames: int = 100) -> list[dict[str, Any]]:
    path = _sweep(name, frames)
    truth = json.loads((path / "truth.json").read_text())
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    result = calibrate_archive(path).to_dict()
    seconds = time.perf_counter() - t0
    archive = SweepArchive.open(path)
    tq = {f["index"]: f for f in truth["frames"]}
    p_err = [
        abs(f["patch_size_px"] - tq[f["index"]]["patch_size_px"])
        for f in result["frames"]
        if f.get("patch_size_px") is not None
    ]
    esif_rms, cv_rms, n_corners = _corner_rms(result, truth, archive)
    rows = [
        ("a error", 100 * abs(result["a_mm"] / truth["a_mm"] - 1), "%", 0.03),
        ("b error", 100 * abs(result["b_mm"] / truth["b_mm"] - 1), "%", 0.01),
        (
            "focus plane error",
            abs(result["focus"]["object_distance_mm"] - truth["focus"]["object_distance_mm"]),
            "mm",
            0.3,
        ),
        ("worst p error (all frames)", max(p_err), "px", 0.02),
        (f"corner RMS at focus ESIF (n={n_corners})", esif_rms, "px", 0.05),
        ("corner RMS at focus cv2.cornerSubPix", cv_rms, "px", None),
        ("lens-centre RMS error", _lens_rms(result, truth), "px", 0.02),
        (
            f"calibrate {len(result['frames'])} frames {truth['sensor']['width']}x"
            f"{truth['sensor']['height']} (load average {load:.1f})",
            seconds,
            "s",
            15.0,
        ),
    ]
    out = []
    for label, value, unit, target in rows:
        ok = None if target is None else bool(value <= target)
        if label.startswith("corner RMS at focus ESIF"):
            ok = bool(value <= 0.05 and esif_rms <= cv_rms)
        out.append(
            {"name": f"{name}: {label}", "value": value, "unit": unit, "target": target, "ok": ok}
        )
    return out


def run(
    presets: tuple[str, ...] = ("paper", "rotated", "noisy"), frames: int = 100
) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in presets:
        rows.extend(evaluate(name, frames))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--presets", default="paper,rotated,noisy")
    parser.add_argument("--frames", type=int, default=100)
    args = parser.parse_args()
    from bench.__main__ import print_table

    print_table(run(tuple(args.presets.split(",")), args.frames))


if __name__ == "__main__":
    main()
