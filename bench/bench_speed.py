"""Speed of the ESIF core: one frame's analysis, and a full-size 100-frame calibration.

- one frame's analysis (3000x1000 and 5120x5120), target <= 0.15 s for the ROI the
  station streams (3000x1000), so analysis keeps up with acquisition (wall time and
  the process's CPU time: the wall time doubles when other jobs share the 2 cores);
- ``lfcal calibrate`` of 100 frames of 3000x1000 (the accuracy benchmark's cached
  ``paper`` sweep), target <= 15 s on 2 idle cores; the load average is printed beside;
- ``lfcal calibrate`` of a 100-frame 5120x5120 sweep, target <= 120 s: projected from
  the measured white-image fit, PNG decode and per-frame analysis times on 2 worker
  processes (rendering 100 full frames for the benchmark alone takes ~50 min), and
  measured for real when that sweep is cached in ``out/bench/full_paper_5120``
  (``lfcal simulate out/bench/full_paper_5120 --preset paper --frames 100``, or
  ``python -m bench.bench_speed --render-full``).

Run: ``python -m bench.bench_speed [--render-full]``.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from calibration.archive import decode_image, encode_image
from calibration.pipeline import FrameAnalyzer, SweepGeometry, default_workers
from calibration.presets import get_preset
from calibration.sim_sweep import fit_frame, frame_seed, render_white
from calibration.simulator import render_frame


def _geometry(preset: Any) -> SweepGeometry:
    from calibration.archive import SweepManifest
    from calibration.sim_sweep import manifest_header

    return SweepGeometry.from_manifest(SweepManifest.from_dict(manifest_header(preset)))


def _time_frames(width: int, height: int, n: int) -> dict[str, float]:
    preset = fit_frame(get_preset("paper"), width, height)
    geometry = _geometry(preset)
    white = render_white(preset, seed=0)
    t0 = time.perf_counter()
    analyzer = FrameAnalyzer.from_white(geometry, white)
    fit_s = time.perf_counter() - t0
    rails = np.linspace(5.0, 95.0, n)
    frames = [
        render_frame(
            preset.camera,
            object_distance_mm=preset.sweep.object_distance_mm(r),
            seed=frame_seed(0, k),
        )
        for k, r in enumerate(rails)
    ]
    analyzer.analyze(0, float(rails[0]), frames[0])  # builds the pixel map once per sweep
    times = []
    cpu = []
    for k, (r, img) in enumerate(zip(rails, frames, strict=True)):
        t0, c0 = time.perf_counter(), time.process_time()
        analyzer.analyze(k, float(r), img)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    shape = (height, width)
    data = encode_image(frames[0], expected_shape=shape, bit_depth=12, name="f.png")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "f.png"
        path.write_bytes(data)
        t0 = time.perf_counter()
        decode_image(path.read_bytes(), "f.png", expected_shape=shape, bit_depth=12)
        decode_s = time.perf_counter() - t0
    return {
        "fit_s": fit_s,
        "frame_s": float(np.median(times)),
        "frame_cpu_s": float(np.median(cpu)),
        "decode_s": decode_s,
    }


def _calibrate_small() -> list[dict[str, Any]]:
    """``calibrate_archive`` of the accuracy benchmark's 100-frame 3000x1000 ``paper`` sweep."""
    from bench.bench_accuracy import _sweep
    from calibration.pipeline import calibrate_archive

    path = _sweep("paper", 100)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    calibrate_archive(path)
    seconds = time.perf_counter() - t0
    return [
        {
            "name": f"calibrate 100 frames 3000x1000 (load average {load:.1f})",
            "value": seconds,
            "unit": "s",
            "target": 15.0,
            "ok": seconds <= 15.0,
        }
    ]


FULL_SWEEP = Path("out/bench/full_paper_5120")


def render_full_sweep() -> Path:
    """The cached 100-frame 5120x5120 ``paper`` sweep (rendered when missing, ~50 min)."""
    if not (FULL_SWEEP / "sweep.json").is_file():
        from calibration.sim_sweep import write_sweep

        write_sweep(FULL_SWEEP, get_preset("paper"), seed=0, overwrite=True)
    return FULL_SWEEP


def _measured_full() -> list[dict[str, Any]]:
    if not (FULL_SWEEP / "sweep.json").is_file():
        return []
    from calibration.pipeline import calibrate_archive

    t0 = time.perf_counter()
    calibrate_archive(FULL_SWEEP)
    seconds = time.perf_counter() - t0
    return [
        {
            "name": "calibrate 100 frames 5120x5120 (measured, cached sweep)",
            "value": seconds,
            "unit": "s",
            "target": 120.0,
            "ok": seconds <= 120.0,
        }
    ]


def run(n: int = 5) -> list[dict[str, Any]]:
    small = _time_frames(3000, 1000, n)
    full = _time_frames(5120, 5120, 3)
    workers = min(2, default_workers())
    projected = full["fit_s"] + 100 * (full["frame_s"] + full["decode_s"]) / workers
    return [
        {
            "name": f"analysis of one 3000x1000 frame (median; load average {os.getloadavg()[0]:.1f})",
            "value": small["frame_s"],
            "unit": "s",
            "target": 0.15,
            "ok": small["frame_s"] <= 0.15,
        },
        {
            "name": "analysis of one 3000x1000 frame, CPU time (median)",
            "value": small["frame_cpu_s"],
            "unit": "s",
            "target": 0.15,
            "ok": small["frame_cpu_s"] <= 0.15,
        },
        *_calibrate_small(),
        {
            "name": "analysis of one 5120x5120 frame (median)",
            "value": full["frame_s"],
            "unit": "s",
            "target": None,
            "ok": None,
        },
        {
            "name": "MLA fit of a 5120x5120 white image",
            "value": full["fit_s"],
            "unit": "s",
            "target": None,
            "ok": None,
        },
        {
            "name": "decode one 5120x5120 16-bit PNG",
            "value": full["decode_s"],
            "unit": "s",
            "target": None,
            "ok": None,
        },
        {
            "name": f"calibrate 100 frames 5120x5120, {workers} workers (projected)",
            "value": projected,
            "unit": "s",
            "target": 120.0,
            "ok": projected <= 120.0,
        },
        *_measured_full(),
    ]


if __name__ == "__main__":
    from bench.__main__ import print_table

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if "--render-full" in sys.argv[1:]:
        render_full_sweep()
    print_table(run())
