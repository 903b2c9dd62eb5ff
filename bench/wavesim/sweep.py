"""Render a whole wavesim sweep into an ``lfcal-sweep/1`` archive, in parallel; and a cache.

The archive is mcsim's (:mod:`bench.mcsim.archive`: ``sweep.json``,
``truth.json``, 16-bit PNGs), with ``generator`` set to ``wavesim``, the
ray-tracer entries of ``truth.json``'s ``render`` replaced by the wave optics,
and wavesim's own ``render_log.json``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path
from typing import Any

from bench.mcsim.archive import frame_file, manifest, truth, write_json, write_png
from bench.mcsim.render import WHITE
from bench.mcsim.spec import merged_options
from bench.mcsim.sweep import cached_render
from bench.wavesim.render import WaveStats, render_image
from bench.wavesim.settings import WaveSpec, build_wave_spec, split_options

GENERATOR = "wavesim"
RENDERER_VERSION = 1
CACHE_ROOT = Path(__file__).resolve().parents[2] / "out" / "bench" / "wavesim"
RAY_TRUTH_KEYS = (
    "rays_per_subpixel",
    "subpixels_per_axis",
    "subpixel_jitter",
    "white_rays_per_subpixel",
    "airy_wavelength_um",
    "spherical_mm",
)


def _render_task(ws: WaveSpec, out_dir: str, index: int) -> WaveStats:
    counts, stats = render_image(ws, index)
    name = "white.png" if index == WHITE else frame_file(index)
    write_png(Path(out_dir) / name, counts)
    return stats


def wave_truth(ws: WaveSpec) -> dict[str, Any]:
    """mcsim's truth.json with the generator and the render settings of wavesim."""
    data = truth(ws.sweep)
    data["generator"] = GENERATOR
    render = {k: v for k, v in data["render"].items() if k not in RAY_TRUTH_KEYS}
    render.update(wave_settings(ws))
    data["render"] = render
    return data


def wave_settings(ws: WaveSpec) -> dict[str, Any]:
    w = ws.wave
    return {
        "renderer": GENERATOR,
        "wavelengths_um": list(w.wavelengths_um),
        "wavelength_weights": [1.0 / len(w.wavelengths_um)] * len(w.wavelengths_um),
        "oversample": w.oversample,
        "kernel_rings": w.rings,
        "vignetting_pupil_rows": w.pupil_rows,
    }


def render_sweep(
    ws: WaveSpec,
    out_dir: Path,
    jobs: int = 1,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Render the white image and every frame into ``out_dir``; return the render log."""
    spec = ws.sweep
    out_dir = Path(out_dir)
    (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    tasks = [WHITE, *range(spec.rail.frames)]
    stats: list[WaveStats] = []
    start = time.perf_counter()

    def note(s: WaveStats) -> None:
        stats.append(s)
        if progress is None:
            return
        what = "white" if s.index == WHITE else f"frame {s.index + 1}/{spec.rail.frames}"
        where = "" if s.u_mm is None else f" u={s.u_mm:.2f} mm"
        clipped = "" if s.windows_inside_frame else "  (a window is cut by the frame edge)"
        progress(f"{what}{where}: {s.seconds:.1f} s ({s.cpu_seconds:.1f} s CPU){clipped}")

    if jobs <= 1:
        for index in tasks:
            note(_render_task(ws, str(out_dir), index))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_render_task, ws, str(out_dir), k) for k in tasks]
            for future in as_completed(futures):
                note(future.result())
    frames = [s for s in stats if s.u_mm is not None]
    cpu = sum(s.cpu_seconds for s in frames)
    log = {
        **wave_settings(ws),
        "vignetting_stop_mm": spec.camera.vignetting_stop_mm,
        "vignetting_diameter_mm": spec.camera.vignetting_diameter_mm,
        "frames_cpu_seconds": cpu,
        "cpu_seconds_per_frame": cpu / len(frames) if frames else 0.0,
        "wall_seconds": time.perf_counter() - start,
        "jobs": jobs,
        "images": [asdict(s) for s in sorted(stats, key=lambda s: s.index)],
    }
    write_json(out_dir / "render_log.json", log)
    write_json(out_dir / "truth.json", wave_truth(ws))
    sweep = manifest(spec)
    sweep["generator"] = GENERATOR
    write_json(out_dir / "sweep.json", sweep)
    return log


def _cache_key(options: dict[str, Any]) -> str:
    mcsim_options, wave = split_options(options)
    merged = {**merged_options(mcsim_options), **wave}
    return json.dumps(
        {"version": RENDERER_VERSION, "options": merged}, sort_keys=True, default=list
    )


def cached_sweep(name: str, jobs: int | None = None, **options: Any) -> Path:
    """Render the sweep of ``options`` into ``out/bench/wavesim/<name>/`` once; return its path.

    A ``.complete`` marker (holding the options) is written last; a later call
    with the same name and options returns at once, one with other options
    renders again. ``jobs`` defaults to the number of CPUs.
    """
    return cached_render(
        CACHE_ROOT,
        name,
        _cache_key(options),
        lambda: build_wave_spec(**options),
        render_sweep,
        jobs,
    )
