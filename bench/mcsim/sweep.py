"""Render a whole sweep into an archive directory, in parallel; and a render cache."""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any, TypeVar

from bench.mcsim.archive import (
    frame_file,
    manifest,
    render_log,
    truth,
    write_json,
    write_png,
)
from bench.mcsim.render import WHITE, RenderStats, render_image
from bench.mcsim.spec import SweepSpec, build_spec, merged_options

RENDERER_VERSION = 1
CACHE_ROOT = Path(__file__).resolve().parents[2] / "out" / "bench" / "mcsim"
Spec = TypeVar("Spec")
COMPLETE = ".complete"
ARCHIVE_ENTRIES = ("sweep.json", "truth.json", "render_log.json", "white.png", "frames")


def _render_task(spec: SweepSpec, out_dir: str, index: int) -> RenderStats:
    counts, stats = render_image(spec, index)
    name = "white.png" if index == WHITE else frame_file(index)
    write_png(Path(out_dir) / name, counts)
    return stats


def render_sweep(
    spec: SweepSpec,
    out_dir: Path,
    jobs: int = 1,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Render the white image and every frame into ``out_dir``; return the render log.

    ``sweep.json`` and ``truth.json`` are written after the images.
    """
    out_dir = Path(out_dir)
    (out_dir / "frames").mkdir(parents=True, exist_ok=True)
    tasks = [WHITE, *range(spec.rail.frames)]
    stats: list[RenderStats] = []
    start = time.perf_counter()

    def note(s: RenderStats) -> None:
        stats.append(s)
        if progress is None:
            return
        what = "white" if s.index == WHITE else f"frame {s.index + 1}/{spec.rail.frames}"
        where = "" if s.u_mm is None else f" u={s.u_mm:.2f} mm"
        clipped = "" if s.windows_inside_frame else "  (a window is cut by the frame edge)"
        progress(
            f"{what}{where}: {s.seconds:.1f} s ({s.cpu_seconds:.1f} s CPU), "
            f"{s.rays / 1e6:.1f} M rays, {s.rays_per_cpu_second / 1e6:.1f} M rays/CPU-s{clipped}"
        )

    if jobs <= 1:
        for index in tasks:
            note(_render_task(spec, str(out_dir), index))
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(_render_task, spec, str(out_dir), k) for k in tasks]
            for future in as_completed(futures):
                note(future.result())
    log = render_log(stats, spec.camera)
    log["wall_seconds"] = time.perf_counter() - start
    log["jobs"] = jobs
    write_json(out_dir / "render_log.json", log)
    write_json(out_dir / "truth.json", truth(spec))
    write_json(out_dir / "sweep.json", manifest(spec))
    return log


def clear_archive(out_dir: Path) -> None:
    """Remove what a previous render left in ``out_dir`` (only the archive's own entries)."""
    for name in (*ARCHIVE_ENTRIES, COMPLETE):
        path = out_dir / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


# options added after renders were cached: left out of the key while unset, so the
# renders cached before them (identical without them) stay valid
LATE_OPTIONS = ("vignetting_stop_mm", "vignetting_diameter_mm")


def _cache_key(options: dict[str, Any]) -> str:
    merged = merged_options(options)
    for name in LATE_OPTIONS:
        if merged.get(name) is None:
            merged.pop(name, None)
    return json.dumps(
        {"version": RENDERER_VERSION, "options": merged}, sort_keys=True, default=list
    )


def cached_sweep(name: str, jobs: int | None = None, **options: Any) -> Path:
    """Render the sweep of ``options`` into ``out/bench/mcsim/<name>/`` once; return its path.

    A ``.complete`` marker (holding the options) is written last; a later call
    with the same name and options returns at once, one with other options
    renders again. ``jobs`` defaults to the number of CPUs.
    """
    return cached_render(
        CACHE_ROOT, name, _cache_key(options), lambda: build_spec(**options), render_sweep, jobs
    )


def cached_render(
    root: Path,
    name: str,
    key: str,
    build: Callable[[], Spec],
    render: Callable[..., object],
    jobs: int | None,
) -> Path:
    """``root/<name>/`` rendered by ``render(build(), directory, jobs=…, progress=…)`` (the
    renderer's ``render_sweep``; ``jobs`` defaults to the number of CPUs, progress lines go
    to stderr prefixed with the root's and the sweep's names) unless its ``.complete``
    marker already holds ``key``: rendered into a temporary directory, the marker written
    last, then moved into place (a concurrent render of the same key wins harmlessly)."""
    target = root / name
    marker = target / COMPLETE
    if marker.exists() and marker.read_text() == key:
        return target
    root.mkdir(parents=True, exist_ok=True)
    tmp = root / f".{name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        render(
            build(),
            tmp,
            jobs=jobs or os.cpu_count() or 1,
            progress=lambda line: print(f"{root.name} {name}: {line}", file=sys.stderr, flush=True),
        )
        (tmp / COMPLETE).write_text(key)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if marker.exists() and marker.read_text() == key:  # another process got there first
        shutil.rmtree(tmp)
        return target
    if target.exists():
        shutil.rmtree(target)
    os.replace(tmp, target)
    return target
