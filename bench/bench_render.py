"""Patch rendering of a full 5120×5120 raw frame, and the seam-score scan over the patch size.

The frame is the ``paper`` preset at the focus plane (u = 300 mm, ESIF patch
size p = 20 px, seam-free patch size 14.51 px, see ``calibration/rendering.py``),
simulated once (about a minute) and cached under ``out/bench``. Rows:

- render time (true micro-image lattice, seam-free patch, uint16 input), best of 5;
- seam-scan time for patch sizes 11..24 px in 0.1 px steps (131 renders), and per size;
- the scan's best patch size against the seam-free one (target 0.5 px, as in the tests);
- the seam score at the seam-free patch size and at the ESIF/designed p = 20 px.

Run: ``python -m bench.bench_render``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.presets import get_preset
from calibration.rendering import (
    best_patch_size,
    render_patches,
    seam_scan,
    seamless_patch_px,
)
from calibration.simulator import render_frame

CACHE = Path("out/bench")
U_MM = 300.0
TARGET_RENDER_S = 0.5
TARGET_SCAN_PER_SIZE_S = 0.1
TARGET_BEST_P_ERR_PX = 0.5
TARGET_SCORE_RATIO = 1.5


def _frame(u_mm: float) -> np.ndarray:
    path = CACHE / f"render_paper_u{u_mm:g}_5120.npy"
    if path.is_file():
        return np.load(path)
    raw = render_frame(get_preset("paper").camera, object_distance_mm=u_mm, seed=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, raw)
    tmp.replace(path)
    return raw


def _row(name: str, value: float, unit: str, target: float | None, higher: bool = False) -> dict:
    ok = None if target is None else bool(value >= target if higher else value <= target)
    return {"name": name, "value": float(value), "unit": unit, "target": target, "ok": ok}


def run(u_mm: float = U_MM, step_px: float = 0.1) -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target)."""
    cam = get_preset("paper").camera
    o = cam.optics
    raw = _frame(u_mm)
    grid = cam.image_grid
    p_esif = float(o.patch_px(u_mm))
    p_true = seamless_patch_px(
        p_esif, lens_pitch_px=o.lens_pitch_px, image_pitch_px=o.image_pitch_px
    )
    times = []
    for _ in range(5):
        start = time.perf_counter()
        img = render_patches(raw, image_grid=grid, patch_size_px=p_true)
        times.append(time.perf_counter() - start)
    sizes = np.arange(11.0, 24.0 + 1e-9, step_px)
    start = time.perf_counter()
    scores = seam_scan(raw, image_grid=grid, patch_sizes_px=sizes)
    scan_s = time.perf_counter() - start
    best = best_patch_size(sizes, scores)
    at = seam_scan(raw, image_grid=grid, patch_sizes_px=[p_true, p_esif])
    h, w = img.shape
    return [
        _row(
            f"render {raw.shape[1]}x{raw.shape[0]} -> {w}x{h}, best of 5",
            min(times),
            "s",
            TARGET_RENDER_S,
        ),
        _row(f"seam scan, {sizes.size} patch sizes", scan_s, "s", None),
        _row("seam scan per patch size", scan_s / sizes.size, "s", TARGET_SCAN_PER_SIZE_S),
        _row(
            f"scan best p - seam-free p ({p_true:.2f} px)",
            abs(best - p_true),
            "px",
            TARGET_BEST_P_ERR_PX,
        ),
        _row("seam score at seam-free p", float(at[0]), "", None),
        _row(f"seam score at ESIF/designed p = {p_esif:.2f} px", float(at[1]), "", None),
        _row(
            "score ratio ESIF p / seam-free p",
            float(at[1] / at[0]),
            "",
            TARGET_SCORE_RATIO,
            higher=True,
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.bench_render", description=__doc__)
    parser.add_argument("--u", type=float, default=U_MM, help="object distance (mm)")
    parser.add_argument("--step", type=float, default=0.1, help="scan step (px)")
    args = parser.parse_args(argv)
    rows = run(args.u, args.step)
    width = max(len(r["name"]) for r in rows)
    print(f"{'benchmark'.ljust(width)}  {'value':>9}  unit  {'target':>8}  ok")
    for r in rows:
        target = "" if r["target"] is None else f"{r['target']:g}"
        ok = "" if r["ok"] is None else ("yes" if r["ok"] else "NO")
        print(f"{r['name'].ljust(width)}  {r['value']:9.4f}  {r['unit']:<4}  {target:>8}  {ok}")
    return 0 if all(r["ok"] is not False for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
