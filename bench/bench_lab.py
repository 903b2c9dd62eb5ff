"""Using a calibration at full size: ``lfcal render`` and ``lfcal report`` of 5120×5120 frames.

Data (cached under ``out/bench/lab``; about 10 minutes the first time on 2 cores):
a 7-frame ``paper`` sweep around the focus plane (rail 38..62 mm, full 5120×5120
sensor) calibrated by ``lfcal calibrate``, and a raw frame of the text scene
(:func:`calibration.scene.text_scene`) at the focus plane, u = 300 mm, as a 16-bit PNG.

Rows:

- ``lfcal render`` of the scene, in process: PNG checks and decoding, the lattice
  check, rendering and the artefact score, best of 3; and the rendering alone;
- the artefact score with the calibrated p and with the designed p of a camera
  whose b is 3.1 mm instead of 3.0 (p = 24 px instead of 20 px), and their ratio;
- ``lfcal report`` of the sweep (re-reading every file), time and size.

Run: ``python -m bench.bench_lab``.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2

from calibration.export_model import CalibratedCamera, designed_patch_px
from calibration.presets import get_preset
from calibration.raw_image import read_raw_file
from calibration.raw_render import render_frame_with
from calibration.report_archive import report_from_archive
from calibration.scene import text_scene
from calibration.simulator import render_frame
from station.cli import main as lfcal

CACHE = Path("out/bench/lab")
U_MM = 300.0
TARGET_RENDER_S = 5.0
TARGET_SCORE_RATIO = 3.0
TARGET_REPORT_MB = 2.0


def _row(name: str, value: float, unit: str, target: float | None, higher: bool = False) -> dict:
    ok = None if target is None else bool(value >= target if higher else value <= target)
    return {"name": name, "value": float(value), "unit": unit, "target": target, "ok": ok}


def _data() -> tuple[Path, Path]:
    """The calibrated sweep (with ``result.json`` inside) and the scene frame."""
    sweep = CACHE / "paper5120"
    if not (sweep / "result.json").is_file():
        CACHE.mkdir(parents=True, exist_ok=True)
        args = ["--preset", "paper", "--frames", "7", "--start-mm", "38", "--step-mm", "4"]
        assert lfcal(["simulate", str(sweep), *args, "--seed", "1", "--overwrite"]) == 0
        assert lfcal(["calibrate", str(sweep), "--out", str(sweep / "result.json")]) == 0
    scene = CACHE / "scene_paper_u300.png"
    if not scene.is_file():
        cam = replace(get_preset("paper").camera, board=text_scene(centre_mm=(0.0, 0.0)))
        raw = render_frame(cam, object_distance_mm=U_MM, seed=11)
        tmp = scene.with_suffix(".tmp.png")
        assert cv2.imwrite(str(tmp), raw)
        tmp.replace(scene)
    return sweep, scene


def run() -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target)."""
    sweep, scene = _data()
    result = json.loads((sweep / "result.json").read_text())
    camera = CalibratedCamera.from_result(result)
    totals, renders = [], []
    for _ in range(3):
        start = time.perf_counter()
        raw = read_raw_file(scene)
        rendered = render_frame_with(raw, camera, camera.patch_px)
        totals.append(time.perf_counter() - start)
        renders.append(rendered.render_s)
    designed = designed_patch_px(b_mm=3.1, f_mm=camera.f, D_mm=camera.D, delta_mm=camera.delta)
    worse = render_frame_with(raw, camera, designed, check=False)
    start = time.perf_counter()
    html = report_from_archive(result, sweep, designed_px=designed, verify=True)
    report_s = time.perf_counter() - start
    h, w = rendered.image.shape
    return [
        _row(
            f"lfcal render 5120x5120 PNG -> {w}x{h} (decode, check, render, score), best of 3",
            min(totals),
            "s",
            TARGET_RENDER_S,
        ),
        _row("  of which the rendering", min(renders), "s", None),
        _row(f"artefact score, calibrated p = {camera.patch_px:.2f} px", rendered.score, "", None),
        _row(f"artefact score, designed p = {designed:.2f} px (b = 3.1 mm)", worse.score, "", None),
        _row(
            "score ratio designed / calibrated",
            worse.score / rendered.score,
            "",
            TARGET_SCORE_RATIO,
            higher=True,
        ),
        _row("lfcal report, 7 frames of 5120x5120, files re-read", report_s, "s", None),
        _row("report size", len(html.encode()) / 1e6, "MB", TARGET_REPORT_MB),
    ]


if __name__ == "__main__":
    from bench.__main__ import print_table

    print_table(run())
