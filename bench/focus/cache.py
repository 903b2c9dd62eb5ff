"""Render the benchmark's sweeps once, and write the manifests of the data-sheet variants.

A sweep lives in ``ROOT/<renderer>/<config>/`` (the renderer's own archive
plus ``truth.json``); the ``.complete`` marker, written last, holds the render
command, so an interrupted or changed render is done again. The renderer's
output goes to ``ROOT/<renderer>/<config>.log``. A variant with another data
sheet is ``<config>/priors/<slug>/``: its own ``sweep.json``, and relative
symbolic links to the base render's ``truth.json``, white image and frames.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.focus.configs import PriorOffset, SweepConfig
from calibration.sim_sweep import DataSheet
from station.summary_table import truth_value

ROOT = Path("out/bench/focus")
MARKER = ".complete"
MARKER_FORMAT = "lfcal-bench-focus/1"
RENDERER_REVISIONS = {"sim": 1, "indsim": 2, "mcsim": 1, "wavesim": 1}
"""Bumped when a renderer's output changes, so its cached sweeps are rendered again
(indsim 2: board raster at least 32 points per sensor pixel)."""


@dataclass
class Render:
    """A rendered sweep: where it is, and the wall time it took (None: from the cache)."""

    config: SweepConfig
    path: Path
    seconds: float | None = None
    error: str | None = None


def sweep_dir(root: Path, config: SweepConfig) -> Path:
    return root / config.renderer / config.name


def render_command(config: SweepConfig, out: Path, jobs: int = 1) -> list[str]:
    """The command that renders ``config`` into ``out`` (which must not exist)."""
    seed = ["--seed", str(config.seed)]
    if config.renderer == "sim":
        return [sys.executable, "-m", "station.cli", "simulate", str(out), *seed, *config.args]
    if config.renderer == "indsim":
        module = "bench.crosscheck.indsim"
    elif config.renderer == "mcsim":
        module = "bench.mcsim"
    elif config.renderer == "wavesim":
        module = "bench.wavesim"
    else:
        raise ValueError(f"unknown renderer {config.renderer!r}")
    return [sys.executable, "-m", module, str(out), *seed, "--jobs", str(jobs), *config.args]


def _marker_text(config: SweepConfig) -> str:
    key = {
        "format": MARKER_FORMAT,
        "renderer": config.renderer,
        "revision": RENDERER_REVISIONS[config.renderer],
        "args": list(config.args),
        "seed": config.seed,
    }
    return json.dumps(key, sort_keys=True) + "\n"


def is_cached(root: Path, config: SweepConfig) -> bool:
    marker = sweep_dir(root, config) / MARKER
    return marker.is_file() and marker.read_text() == _marker_text(config)


def render(config: SweepConfig, root: Path = ROOT, jobs: int = 1) -> Render:
    """The cached sweep of ``config``, rendered now (in a subprocess) when missing or stale.

    A renderer that fails gives a :class:`Render` with the error (the tail of
    its output), not an exception: one broken sweep must not stop the others.
    """
    out = sweep_dir(root, config)
    if is_cached(root, config):
        return Render(config, out)
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    log = out.parent / f"{config.name}.log"
    start = time.perf_counter()
    with log.open("w") as fh:
        proc = subprocess.run(
            render_command(config, out, jobs), stdout=fh, stderr=subprocess.STDOUT, check=False
        )
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-3:]
        error = f"renderer exit {proc.returncode}: " + " / ".join(tail)
        return Render(config, out, seconds, error)
    (out / MARKER).write_text(_marker_text(config))
    return Render(config, out, seconds)


def render_all(
    configs: list[SweepConfig],
    root: Path = ROOT,
    jobs: int = 1,
    progress: Callable[[str], None] | None = None,
) -> dict[tuple[str, str], Render]:
    """Every sweep (once per renderer and name), ``jobs`` renders at a time.

    Each renderer runs on one process, except a single missing sweep, which gets
    all ``jobs`` processes of its renderer.
    """
    unique = list({(c.renderer, c.name): c for c in configs}.values())
    missing = [c for c in unique if not is_cached(root, c)]
    done: dict[tuple[str, str], Render] = {}
    for c in unique:
        if c not in missing:
            done[(c.renderer, c.name)] = Render(c, sweep_dir(root, c))
    inner = jobs if len(missing) == 1 else 1

    def one(config: SweepConfig) -> Render:
        if progress:
            progress(f"rendering {config.renderer} {config.name} ...")
        result = render(config, root, inner)
        if progress:
            what = result.error or f"{result.seconds or 0.0:.0f} s"
            progress(f"rendered {config.renderer} {config.name}: {what}")
        return result

    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        for result in pool.map(one, missing):
            done[(result.config.renderer, result.config.name)] = result
    return done


def read_json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


def datasheet_for(truth: dict[str, Any], offset: PriorOffset) -> DataSheet:
    """The data sheet ``offset`` away from the rendered camera's true F, f and rail zero."""

    def true(key: str) -> float:
        value = truth_value(truth, key)
        if value is None:
            raise ValueError(f"truth.json has no {key}")
        return value

    return DataSheet(
        main_focal_mm=true("main_focal_mm") * (1.0 + offset.main_focal_rel)
        if offset.main_focal_rel
        else None,
        mla_focal_mm=true("mla_focal_mm") * (1.0 + offset.mla_focal_rel)
        if offset.mla_focal_rel
        else None,
        rail_zero_mm=true("priors.rail_zero_object_distance_mm.calibrated") + offset.rail_zero_mm
        if offset.rail_zero_mm
        else None,
    )


def _link(target: Path, link: Path) -> None:
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(target)


def priors_variant(base: Path, offset: PriorOffset) -> Path:
    """The archive of ``base`` described by the data sheet ``offset`` (``base`` itself when exact).

    Only the manifest differs (written atomically); the images and ``truth.json``
    are links into ``base``.
    """
    if offset.exact:
        return base
    manifest = read_json(base / "sweep.json")
    truth = read_json(base / "truth.json")
    variant = base / "priors" / offset.slug
    variant.mkdir(parents=True, exist_ok=True)
    entries = {"truth.json", str(manifest["white"]).split("/")[0]}
    entries |= {str(f["file"]).split("/")[0] for f in manifest["frames"]}
    for entry in sorted(entries):
        _link(Path("..") / ".." / entry, variant / entry)
    text = json.dumps(datasheet_for(truth, offset).apply(manifest), indent=1) + "\n"
    tmp = variant / "sweep.json.tmp"
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(variant / "sweep.json")
    return variant
