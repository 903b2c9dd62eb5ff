"""Accuracy and speed of the MLA grid fit (:func:`calibration.mla_grid.fit_mla_grid`).

For each preset at its full 5120×5120 sensor, a white image is rendered at
the middle of the sweep (noise on) and fitted; the fit is compared with the
simulator's true lattices:

- lens-centre RMS error over every lens whose centre is on the sensor
  (target 0.02 px), and the largest error;
- micro-image-centre RMS error (informative: a pure scale error about the
  principal point cancels in the lens centres);
- rotation error (target 0.005°), image-pitch relative error (target 1e-4);
- fit time (target 3 s), best of ``--repeat`` runs.

Run: ``python -m bench.bench_mla [--size 5120] [--presets paper,rotated,noisy]``.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from calibration.lens_grid import LensGrid
from calibration.mla_grid import MlaGrid, fit_mla_grid
from calibration.presets import get_preset, preset_names
from calibration.sim_sweep import fit_frame, render_white

TARGET_LENS_RMS_PX = 0.02
TARGET_ROTATION_DEG = 0.005
TARGET_PITCH_REL = 1e-4
TARGET_TIME_S = 3.0


def centre_errors(fit_grid: LensGrid, true_grid: LensGrid, width: int, height: int) -> np.ndarray:
    """Distance (px) from each true node on the sensor to the nearest fitted node."""
    ii, jj = true_grid.indices_in(width, height)
    tx, ty = true_grid.centre(ii, jj)
    ni, nj = fit_grid.nearest(tx, ty)
    fx, fy = fit_grid.centre(ni, nj)
    return np.hypot(fx - tx, fy - ty)


def evaluate(name: str, size: int, seed: int = 0, repeat: int = 1) -> tuple[MlaGrid, dict]:
    """Fit one preset's white image; returns the grid and the error/speed figures."""
    preset = fit_frame(get_preset(name), size, size)
    cam = preset.camera
    white = render_white(preset, seed)
    times = []
    grid = None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        grid = fit_mla_grid(
            white, lens_pitch_px=cam.optics.lens_pitch_px, principal_point_px=cam.sensor.pp
        )
        times.append(time.perf_counter() - t0)
    assert grid is not None
    w, h = cam.sensor.width, cam.sensor.height
    lens_err = centre_errors(grid.lens_grid, cam.lens_grid, w, h)
    img_err = centre_errors(grid.image_grid, cam.image_grid, w, h)
    figures = {
        "lens_rms_px": float(np.sqrt(np.mean(lens_err**2))),
        "lens_max_px": float(lens_err.max()),
        "image_rms_px": float(np.sqrt(np.mean(img_err**2))),
        "rotation_err_deg": abs(grid.rotation_deg - cam.mla_rotation_deg),
        "pitch_rel_err": abs(grid.image_pitch_px / cam.image_grid.pitch_px - 1.0),
        "time_s": min(times),
        "n_used": grid.n_lenses_used,
        "n_rejected": grid.n_rejected,
        "residual_rms_px": grid.residual_rms_px,
    }
    return grid, figures


def _row(name: str, value: float, unit: str, target: float | None) -> dict[str, Any]:
    return {
        "name": name,
        "value": value,
        "unit": unit,
        "target": target,
        "ok": None if target is None else bool(value <= target),
    }


def run(
    size: int = 5120, presets: list[str] | None = None, seed: int = 0, repeat: int = 2
) -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target)."""
    rows: list[dict[str, Any]] = []
    for name in presets or preset_names():
        _, f = evaluate(name, size, seed, repeat)
        tag = f"{name} {size}x{size}"
        rows += [
            _row(f"{tag}: lens-centre RMS error", f["lens_rms_px"], "px", TARGET_LENS_RMS_PX),
            _row(f"{tag}: lens-centre max error", f["lens_max_px"], "px", None),
            _row(f"{tag}: micro-image-centre RMS error", f["image_rms_px"], "px", None),
            _row(f"{tag}: rotation error", f["rotation_err_deg"], "deg", TARGET_ROTATION_DEG),
            _row(f"{tag}: image pitch relative error", f["pitch_rel_err"], "", TARGET_PITCH_REL),
            _row(f"{tag}: fit residual RMS", f["residual_rms_px"], "px", None),
            _row(f"{tag}: lenses used", float(f["n_used"]), "", None),
            _row(f"{tag}: fit time", f["time_s"], "s", TARGET_TIME_S),
        ]
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.bench_mla", description=__doc__)
    parser.add_argument("--size", type=int, default=5120, help="square sensor size (px)")
    parser.add_argument("--presets", default=",".join(preset_names()))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=2, help="fits per preset (best time)")
    args = parser.parse_args(argv)
    rows = run(args.size, args.presets.split(","), args.seed, args.repeat)
    width = max(len(r["name"]) for r in rows)
    print(f"{'benchmark'.ljust(width)}  {'value':>10}  unit  {'target':>9}  ok")
    for r in rows:
        target = "" if r["target"] is None else f"<= {r['target']:g}"
        ok = "" if r["ok"] is None else ("yes" if r["ok"] else "NO")
        print(f"{r['name'].ljust(width)}  {r['value']:10.4g}  {r['unit']:<4}  {target:>9}  {ok}")
    return 0 if all(r["ok"] is not False for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
