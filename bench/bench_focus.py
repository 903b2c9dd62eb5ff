"""Focus plane, a, b and the data-sheet priors on four renderers, with uncertainty coverage.

``python -m bench.bench_focus [--renderers sim,indsim,mcsim,wavesim] [--configs NAMES]
[--seeds N] [--repeats N] [--jobs N] [--quick] [--root DIR]`` (``python -m bench focus`` runs
the full default; not in the default ``make bench`` set: the first run renders
for hours). What it renders and why: :mod:`bench.focus.configs`; targets:
:mod:`bench.focus.evaluate`. Renders are cached under ``out/bench/focus/``
(``--root``), each calibration's result JSON is kept in
``<root>/calibrations/``, and every row with the details of every calibration
(errors, sigmas, z, which priors were used, warnings, failures) goes to
``<root>/results.json``.

Rows per renderer and sweep and data sheet: the focus-plane, a, b, F, f and
rail-zero errors and the worst per-frame p error against their targets (a
failed calibration, exit 2/3/4, is a row with its message, not a crash); for
the standard-corner-only sweeps, whether F and the rail zero fell back to
the data sheet. With ``--repeats N``, each accuracy sweep is rendered N more times with
other seeds, the image moved against the pixel grid by a fraction of a pixel each time
(:func:`bench.focus.configs.repeat_config`), and calibrated with the exact data sheet: the mean error over its seeds (the
bias), the spread and the RMS error (held against the target) tell a bias from one
seed's luck. Per renderer, over ``--seeds`` coverage sweeps: the fraction of
seeds whose error is within 1 and within 3 reported sigma (exact and wrong data
sheets), the RMS of error/sigma, the mean and the worst error. The same over
``--seeds`` random cameras, each its own optics and sweep
(:func:`bench.focus.configs.random_camera_config`): mcsim's in the default full run (not in
``--quick``), and with ``--configs random`` those of every renderer given that draws them
(mcsim, and wavesim the same cameras in wave optics). With ``--configs nocos4``, mcsim's
coverage sweeps rendered again with every ray counted alike (no cos⁴,
:func:`bench.focus.configs.no_cos4_config`).
Then the load average of the machine during the run.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path
from typing import Any

from bench.focus import cache
from bench.focus.configs import (
    ACCURACY,
    RANDOM_RENDERERS,
    RENDERERS,
    PriorOffset,
    SweepConfig,
    coverage_config,
    no_cos4_config,
    quick_config,
    random_camera_config,
    repeat_config,
)
from bench.focus.evaluate import (
    COVERAGE_KEYS_EXACT,
    Comparison,
    accuracy_rows,
    compare,
    coverage_rows,
    failed_row,
    label,
    repeat_rows,
    rim_pull_rows,
)
from bench.focus.summary import accuracy_lines, coverage_lines, repeat_lines, rim_pull_lines
from calibration.pipeline import CalibrationError, calibrate_archive

DEFAULT_SEEDS = 20
QUICK_SEEDS = 3
RANDOM_CAMERAS = "mcsim random cameras"
"""The coverage group of :func:`~bench.focus.configs.random_camera_config`'s mcsim sweeps
(wavesim's: :func:`random_cameras_group`)."""


NO_COS4 = "mcsim without cos4"
"""The coverage group of :func:`~bench.focus.configs.no_cos4_config`'s sweeps."""


def random_cameras_group(renderer: str) -> str:
    """The coverage group of one renderer's random cameras."""
    return f"{renderer} random cameras"


_SAY_LOCK = threading.Lock()


def _say(text: str) -> None:
    with _SAY_LOCK:  # render threads report too
        print(f"[{time.strftime('%H:%M:%S')}] bench_focus: {text}", file=sys.stderr, flush=True)


class LoadSampler:
    """Samples the 1-minute load average every ``interval_s`` in a daemon thread."""

    def __init__(self, interval_s: float = 30.0) -> None:
        self.interval_s = interval_s
        self.samples: list[float] = [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="load-sampler", daemon=True)

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> LoadSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.samples.append(os.getloadavg()[0])

    def summary(self) -> dict[str, float]:
        s = self.samples
        return {"mean": sum(s) / len(s), "min": min(s), "max": max(s), "samples": float(len(s))}


def calibrate(path: Path, workers: int) -> tuple[dict[str, Any] | None, int, str, float]:
    """``(result, exit code, message, seconds)``; the result is None when calibration failed."""
    start = time.perf_counter()
    try:
        result = calibrate_archive(path, workers=workers).to_dict()
    except CalibrationError as exc:
        return None, int(exc.exit_code), f"{type(exc).__name__}: {exc}", time.perf_counter() - start
    except Exception as exc:  # a bug in the core is a finding too; keep benchmarking
        tail = traceback.format_exc().strip().splitlines()[-1]
        return None, 1, f"internal error {type(exc).__name__}: {tail}", time.perf_counter() - start
    return result, 0, "", time.perf_counter() - start


class Run:
    """One benchmark run: renders, calibrations, rows and the JSON details."""

    def __init__(self, root: Path, jobs: int) -> None:
        self.root = root
        self.jobs = jobs
        self.rows: list[dict[str, Any]] = []
        self.details: list[dict[str, Any]] = []

    def calibrate_variant(
        self, config: SweepConfig, base: Path, offset: PriorOffset
    ) -> Comparison | None:
        """Calibrate ``base`` under the data sheet ``offset``; record the details; the comparison."""
        path = cache.priors_variant(base, offset)
        result, code, message, seconds = calibrate(path, self.jobs)
        detail: dict[str, Any] = {
            "renderer": config.renderer,
            "config": config.name,
            "priors": offset.name,
            "archive": str(path),
            "seconds": seconds,
            "exit_code": code,
        }
        self.details.append(detail)
        if result is None:
            detail["error"] = message
            _say(f"{label(config, offset)}: FAILED ({message})")
            return None
        out = self.root / "calibrations" / config.renderer / f"{config.name}@{offset.slug}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
        cmp = compare(result, cache.read_json(path / "truth.json"))
        detail.update(cmp.to_dict())
        detail["result"] = str(out)
        q = cmp.values
        _say(
            f"{label(config, offset)}: focus {_fmt(q['focus'])} mm, a {_fmt(q['a'])} %, "
            f"b {_fmt(q['b'])} %, worst p {cmp.worst_p_px:.4f} px ({seconds:.0f} s)"
        )
        return cmp

    def comparisons(
        self, config: SweepConfig, render: cache.Render
    ) -> list[tuple[PriorOffset, Comparison]]:
        """Each data sheet of ``config`` calibrated; a failed render or calibration is
        recorded as a failed row instead."""
        if render.error:
            self.rows.append(failed_row(config, None, 1, render.error))
            return []
        out = []
        for offset in config.priors:
            cmp = self.calibrate_variant(config, render.path, offset)
            if cmp is None:
                detail = self.details[-1]
                self.rows.append(failed_row(config, offset, detail["exit_code"], detail["error"]))
            else:
                out.append((offset, cmp))
        return out

    def accuracy(self, config: SweepConfig, render: cache.Render) -> Comparison | None:
        """The accuracy rows of every data sheet; the exact data sheet's comparison."""
        exact = None
        for offset, cmp in self.comparisons(config, render):
            self.rows.extend(accuracy_rows(config, offset, cmp))
            if offset.exact:
                exact = cmp
        return exact

    def repeats(
        self,
        config: SweepConfig,
        first: Comparison | None,
        repeats: list[SweepConfig],
        renders: dict[Any, Any],
    ) -> None:
        """The sweep over its seeds: itself and its repeats, exact data sheet."""
        found = [] if first is None else [first]
        for repeat in repeats:
            found += [
                cmp for _, cmp in self.comparisons(repeat, renders[(repeat.renderer, repeat.name)])
            ]
        if len(found) >= 2:
            self.rows.extend(repeat_rows(config, found))

    def coverage(self, renderer: str, configs: list[SweepConfig], renders: dict[Any, Any]) -> None:
        exact: list[Comparison] = []
        off: list[Comparison] = []
        for config in configs:
            for offset, cmp in self.comparisons(config, renders[(config.renderer, config.name)]):
                (exact if offset.exact else off).append(cmp)
        self.rows.extend(coverage_rows(renderer, "exact", exact, len(configs), COVERAGE_KEYS_EXACT))
        self.rows.extend(rim_pull_rows(renderer, exact))
        self.rows.extend(coverage_rows(renderer, "wrong data sheet", off, len(configs)))


def _fmt(entry: dict[str, Any]) -> str:
    err, sigma = entry.get("error"), entry.get("sigma")
    if err is None:
        return "n/a"
    return f"{err:+.4f} ± {sigma:.4f}" if sigma is not None else f"{err:+.4f}"


def select(
    renderers: tuple[str, ...], names: tuple[str, ...] | None, seeds: int, quick: bool
) -> tuple[list[SweepConfig], dict[str, list[SweepConfig]]]:
    """The accuracy sweeps and, per renderer, the coverage sweeps of a run (repeats apart)."""
    accuracy: list[SweepConfig] = []
    coverage: dict[str, list[SweepConfig]] = {}
    for r in renderers:
        chosen = [quick_config(r)] if quick else list(ACCURACY[r])
        accuracy += [c for c in chosen if names is None or c.name in names]
        if seeds > 0 and (names is None or "coverage" in names):
            coverage[r] = [coverage_config(r, k) for k in range(seeds)]
    # the full run draws mcsim's random cameras; ``--configs random`` every renderer's that can
    drawing: tuple[str, ...] = ()
    if names is not None and "random" in names:
        drawing = RANDOM_RENDERERS
    elif names is None and not quick:
        drawing = ("mcsim",)
    for r in (r for r in drawing if r in renderers and seeds > 0):
        coverage[random_cameras_group(r)] = [random_camera_config(k, r) for k in range(seeds)]
    # mcsim's coverage sweeps without cos⁴, on request only (``--configs nocos4``)
    if names is not None and "nocos4" in names and "mcsim" in renderers and seeds > 0:
        coverage[NO_COS4] = [no_cos4_config(k) for k in range(seeds)]
    return accuracy, coverage


def _git_commit() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def run(
    renderers: tuple[str, ...] = RENDERERS,
    names: tuple[str, ...] | None = None,
    seeds: int = DEFAULT_SEEDS,
    jobs: int = 2,
    quick: bool = False,
    root: Path = cache.ROOT,
    repeats: int = 0,
) -> list[dict[str, Any]]:
    """Render what is missing, calibrate everything, return the rows (and write results.json)."""
    started = time.time()
    accuracy, coverage = select(renderers, names, seeds, quick)
    again = {
        (c.renderer, c.name): [repeat_config(c, k) for k in range(1, repeats + 1)] for c in accuracy
    }
    every = accuracy + [c for cs in coverage.values() for c in cs]
    every += [c for cs in again.values() for c in cs]
    bench = Run(root, jobs)
    with LoadSampler() as load:
        _say(f"{len(every)} sweeps ({sum(not cache.is_cached(root, c) for c in every)} to render)")
        renders = cache.render_all(every, root, jobs, progress=_say)
        for config in accuracy:
            key = (config.renderer, config.name)
            exact = bench.accuracy(config, renders[key])
            if again[key]:
                bench.repeats(config, exact, again[key], renders)
        for renderer, configs in coverage.items():
            bench.coverage(renderer, configs, renders)
    rows = bench.rows
    summary = load.summary()
    rows += [
        {
            "name": "load average (1 min) during the run: mean",
            "value": summary["mean"],
            "unit": "",
            "target": None,
            "ok": None,
        },
        {
            "name": "load average (1 min) during the run: max",
            "value": summary["max"],
            "unit": "",
            "target": None,
            "ok": None,
        },
        {
            "name": "wall time of the run",
            "value": (time.time() - started) / 60,
            "unit": "min",
            "target": None,
            "ok": None,
        },
    ]
    rendered = {
        f"{r.config.renderer}/{r.config.name}": {
            "seconds": r.seconds,
            "cached": r.seconds is None,
            "error": r.error,
            "command": cache.render_command(r.config, r.path),
            "about": r.config.about,
        }
        for r in renders.values()
    }
    report = {
        "format": "lfcal-bench-focus/1",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(started)),
        "wall_seconds": time.time() - started,
        "git_commit": _git_commit(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": summary,
        "options": {
            "renderers": list(renderers),
            "configs": names,
            "seeds": seeds,
            "jobs": jobs,
            "quick": quick,
            "repeats": repeats,
        },
        "rows": [_jsonable(r) for r in rows],
        "calibrations": [_jsonable(d) for d in bench.details],
        "renders": rendered,
    }
    root.mkdir(parents=True, exist_ok=True)
    (root / "results.json").write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    return rows


def _jsonable(obj: Any) -> Any:
    """NaN and infinities as None (strict JSON)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    return obj


def _names(text: str) -> tuple[str, ...]:
    return tuple(p.strip() for p in text.split(",") if p.strip())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m bench.bench_focus", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--renderers", type=_names, default=RENDERERS, help="comma list of sim,indsim,mcsim,wavesim"
    )
    p.add_argument(
        "--configs",
        type=_names,
        default=None,
        help="comma list of sweep names (e.g. rotated-end8,coverage); default all",
    )
    p.add_argument(
        "--seeds",
        type=int,
        default=None,
        help=f"coverage seeds per renderer (default {DEFAULT_SEEDS}, quick {QUICK_SEEDS})",
    )
    p.add_argument(
        "--repeats",
        type=int,
        default=0,
        help="more seeds of every accuracy sweep, exact data sheet: mean, sd and RMS error",
    )
    p.add_argument("--jobs", type=int, default=2, help="renders at a time, and calibration workers")
    p.add_argument(
        "--quick", action="store_true", help="one small sweep per renderer and 3 coverage seeds"
    )
    p.add_argument("--root", type=Path, default=cache.ROOT, help="cache and results directory")
    args = p.parse_args(argv)
    unknown = [r for r in args.renderers if r not in RENDERERS]
    if unknown:
        p.error(f"unknown renderer(s) {', '.join(unknown)}: choose from {', '.join(RENDERERS)}")
    seeds = args.seeds if args.seeds is not None else (QUICK_SEEDS if args.quick else DEFAULT_SEEDS)
    rows = run(
        tuple(args.renderers),
        args.configs,
        seeds,
        max(1, args.jobs),
        args.quick,
        args.root,
        max(0, args.repeats),
    )
    from bench.__main__ import print_table

    print_table(rows)
    print("\nsummary (|error|; * missed target, p from the data sheet, σ error/sigma):")
    print("\n".join(accuracy_lines(rows)))
    if repeated := repeat_lines(rows):
        print("\nover the seeds of each accuracy sweep (signed mean error, sd, RMS; * missed):")
        print("\n".join(repeated))
    print()
    print("\n".join(coverage_lines(rows)))
    if pulls := rim_pull_lines(rows):
        print(
            "\nthe white image's lattice scale less the true (L+b)/L, and the rim term it is corrected by:"
        )
        print("\n".join(pulls))
    return 0 if all(r.get("ok") is not False for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
