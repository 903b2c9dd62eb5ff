"""From a sweep (streamed frames or an ``lfcal-sweep/1`` archive) to calibrated parameters.

:class:`FrameAnalyzer` holds what every frame of a sweep shares (the MLA grid
fitted on the white image, the optics priors, the board) and turns one raw
frame into a :class:`FrameSummary`; it is picklable, so the station can run it
in worker processes while acquisition goes on. :func:`combine`
(:mod:`calibration.combine`) turns the frame summaries into a
:class:`CalibrationResult`. :func:`calibrate_archive` does both for an archive
on disk.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import sys
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .aperture_mask import full_aperture_mask
from .archive import ImageError, SweepArchive
from .blas_threads import single_blas_thread
from .camera_model import ModelError, check_priors
from .clipping import OverexposedWhiteError, check_white_exposure
from .combine import combine
from .corner_candidates import MicroImageMap
from .edge_spread import BinnedEsf
from .frame_analysis import CornerFit, FrameContext, analyze_frame
from .heap_reuse import reuse_freed_memory
from .mla_grid import MlaGrid, fit_mla_grid
from .shading import measure_shading
from .summary import (
    CalibrationError,
    CalibrationOptions,
    CalibrationResult,
    FocusAtEdgeError,
    FocusNotDeterminedError,
    FrameSummary,
    PriorError,
    SweepGeometry,
)
from .white_rim import measure_rim

__all__ = [
    "CalibrationError",
    "CalibrationOptions",
    "CalibrationResult",
    "FocusAtEdgeError",
    "FocusNotDeterminedError",
    "FrameAnalyzer",
    "FrameSummary",
    "PriorError",
    "SweepGeometry",
    "calibrate_archive",
    "combine",
    "default_workers",
]


def _corner_rows(fit: CornerFit | None) -> list[list[float]]:
    """Per used micro-image: lens i, j, corner x, y, x_se, y_se, size (px)."""
    if fit is None:
        return []
    return [
        [m.lens_i, m.lens_j, m.x, m.y, m.x_se, m.y_se, m.size_px]
        for m, used in zip(fit.measurements, fit.used, strict=True)
        if used
    ]


class FrameAnalyzer:
    """Analyses frames of one sweep; build once from the white image (picklable)."""

    def __init__(
        self, geometry: SweepGeometry, grid: MlaGrid, options: CalibrationOptions | None = None
    ) -> None:
        self.geometry = geometry
        self.grid = grid
        self.options = options or CalibrationOptions()
        radius = self.options.interior_fraction * 0.5 * geometry.lens_pitch_px
        self.context = FrameContext(
            image_grid=grid.image_grid,
            lens_grid=grid.lens_grid,
            principal_point_px=geometry.principal_point_px,
            pixel_pitch_mm=geometry.pixel_pitch_mm,
            main_focal_mm=geometry.main_focal_mm,
            board=geometry.board,
            interior_radius_px=radius,
            options=self.options.corner,
        )
        self._map: MicroImageMap | None = None

    @classmethod
    def from_white(
        cls, geometry: SweepGeometry, white: NDArray[Any], options: CalibrationOptions | None = None
    ) -> FrameAnalyzer:
        """The analyzer of a sweep from its white image: the MLA grid, the shading and the
        options they set. :class:`~calibration.clipping.OverexposedWhiteError` (before any
        fit) when the white image is clipped over too much of its lit area, ``ValueError``
        when it shows no microlens grid."""
        clipped = 0.0
        if geometry.max_count is not None:
            clipped = check_white_exposure(white, geometry.max_count)
        grid = fit_mla_grid(
            white,
            lens_pitch_px=geometry.lens_pitch_px,
            principal_point_px=geometry.principal_point_px,
        )
        shading = measure_shading(
            white,
            grid.image_grid,
            background=grid.background,
            lens_grid=grid.lens_grid,
            unvignetted=(grid.principal_point_px, grid.vignetting_onset_px),
        )
        rim = measure_rim(
            white,
            grid.image_grid,
            background=grid.background,
            unvignetted=(grid.principal_point_px, grid.vignetting_onset_px),
        )
        options = options or CalibrationOptions()
        if geometry.max_count is not None:
            # edge spreads only from unclipped profiles
            corner = dataclasses.replace(options.corner, clip_count=float(geometry.max_count))
            options = dataclasses.replace(options, corner=corner)
        if np.isfinite(shading.plateau_fraction):
            # edge spreads only where the whole microlens aperture is seen (the white plateau)
            corner = dataclasses.replace(
                options.corner, blur_radius_fraction=shading.plateau_fraction
            )
            options = dataclasses.replace(options, corner=corner)
        flat_field = shading.flat_field(grid.background)
        if flat_field is not None:
            # edge profiles flat-fielded by the micro-images' bowl (rims, vignetting); in
            # vignetted micro-images only the pixels that see the whole microlens aperture
            mask = full_aperture_mask(
                white,
                grid.image_grid,
                grid.lens_grid,
                flat_field,
                plateau_px=options.corner.plateau_px(grid.image_grid.pitch_px),
                principal_point_px=grid.principal_point_px,
                onset_px=grid.vignetting_onset_px,
            )
            corner = dataclasses.replace(options.corner, flat_field=flat_field, aperture_mask=mask)
            options = dataclasses.replace(options, corner=corner)
        grid = dataclasses.replace(grid, shading=shading, rim=rim, white_clipped_fraction=clipped)
        return cls(geometry, grid, options)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_map"] = None  # rebuilt in each process
        return state

    def analyze(self, index: int, rail_mm: float, image: NDArray[Any]) -> FrameSummary:
        """Measure one raw frame taken at rail position ``rail_mm`` (mm)."""
        u = self.geometry.object_distance_mm(rail_mm)
        summary = FrameSummary(index=index, rail_mm=rail_mm, object_distance_mm=u)
        if image.shape != (self.geometry.height, self.geometry.width):
            summary.error = (
                f"frame is {image.shape[1]}x{image.shape[0]} px, the sweep is "
                f"{self.geometry.width}x{self.geometry.height} px"
            )
            return summary
        if self._map is None:
            self._map = MicroImageMap(
                self.context.image_grid, image.shape, self.context.interior_radius_px
            )
        r = analyze_frame(image, self.context, u, micro_image_map=self._map)
        summary.Q, summary.Q_se = r.Q, r.Q_se
        summary.Q_eq3 = r.standard.Q_eq3 if r.standard else float("nan")
        summary.Ls_px, summary.Lr_px = r.Ls_px, r.Lr_px
        summary.edge_width_px = r.edge_width_px
        summary.standard = r.standard.summary() if r.standard else None
        summary.reference = r.reference.summary() if r.reference else None
        summary.corners = {
            "standard": _corner_rows(r.standard),
            "reference": _corner_rows(r.reference),
        }
        esfs = [fit.esf for fit in (r.standard, r.reference) if fit is not None and fit.esf]
        summary.esf = {
            fit.name: fit.esf.to_dict()
            for fit in (r.standard, r.reference)
            if fit is not None and fit.esf is not None
        }
        if esfs:
            summary.edge_spread_px = BinnedEsf.merge(esfs).spread_px()
        summary.rejected = r.rejected
        if not np.isfinite(summary.Q):
            summary.error = "no board corner found in this frame"
        return summary


_WORKER: dict[str, Any] = {}


def _worker_init(root: str) -> None:
    _WORKER["archive"] = SweepArchive.open(root)
    _WORKER["analyzer"] = None


def _pool_worker_init(root: str) -> None:
    """A pool process's initializer: one BLAS thread for its life (:mod:`.blas_threads`) and
    freed array memory kept for reuse (:mod:`.heap_reuse`)."""
    single_blas_thread()
    reuse_freed_memory()
    _worker_init(root)


def _worker_ready() -> None:
    """A task that only makes the pool start a process."""


def _worker_analyze(index: int, rail_mm: float, analyzer: FrameAnalyzer) -> FrameSummary | str:
    """Decode and analyse one frame in a worker; the error text when it cannot be read.

    Every task carries the analyzer (a few kB); a worker keeps the first it receives, whose
    pixel map it builds once."""
    if _WORKER["analyzer"] is None:
        _WORKER["analyzer"] = analyzer
    try:
        image = _WORKER["archive"].frame(index)
    except ImageError as exc:
        return str(exc)
    return _WORKER["analyzer"].analyze(index, rail_mm, image)


def _start_pool(root: str, workers: int) -> ProcessPoolExecutor:
    """``workers`` analysis processes, started at once (they import the calibration while
    the caller fits the white image): forked from a server that has imported this module."""
    if sys.platform == "win32":
        ctx: Any = multiprocessing.get_context("spawn")
    else:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload([__name__])
    pool = ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_pool_worker_init, initargs=(root,)
    )
    for _ in range(workers):
        pool.submit(_worker_ready)
    return pool


def default_workers() -> int:
    """Analysis processes: one per core, at most 4."""
    return max(1, min(4, os.cpu_count() or 1))


def calibrate_archive(
    path: str | Path,
    *,
    options: CalibrationOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
    workers: int | None = None,
) -> CalibrationResult:
    """Calibrate an ``lfcal-sweep/1`` archive; unreadable frames are skipped and reported.

    Frames are decoded and analysed in ``workers`` processes (default: one per
    core, at most 4; 1 analyses in this process). BLAS runs one thread per process
    throughout (:mod:`calibration.blas_threads`), and every process keeps its freed array
    memory for reuse from then on (:mod:`calibration.heap_reuse`; this one too).
    """
    reuse_freed_memory()
    with single_blas_thread():
        return _calibrate_archive(path, options=options, progress=progress, workers=workers)


def _analyzer(
    archive: SweepArchive, geometry: SweepGeometry, options: CalibrationOptions | None
) -> FrameAnalyzer:
    """The sweep's analyzer from its white image, or a :class:`CalibrationError` saying why not."""
    try:
        white = archive.white()
    except ImageError as exc:
        raise CalibrationError(f"white image unusable: {exc}") from exc
    try:
        return FrameAnalyzer.from_white(geometry, white, options)
    except OverexposedWhiteError as exc:
        raise CalibrationError(str(exc)) from exc
    except ValueError as exc:
        raise CalibrationError(f"no microlens grid in the white image: {exc}") from exc


def _analyzer_and_pool(
    archive: SweepArchive,
    geometry: SweepGeometry,
    options: CalibrationOptions | None,
    workers: int,
) -> tuple[FrameAnalyzer, ProcessPoolExecutor]:
    """The analyzer and the worker pool, started (a forkserver imports the calibration, then
    forks the workers: ~0.8 s) while the white image is fitted; no pool when that fails."""
    with ThreadPoolExecutor(1) as starter:
        starting = starter.submit(_start_pool, str(archive.root), workers)
        try:
            analyzer = _analyzer(archive, geometry, options)
        except BaseException:
            if starting.exception() is None:
                starting.result().shutdown(cancel_futures=True)
            raise
        return analyzer, starting.result()


def _calibrate_archive(
    path: str | Path,
    *,
    options: CalibrationOptions | None,
    progress: Callable[[int, int], None] | None,
    workers: int | None,
) -> CalibrationResult:
    archive = SweepArchive.open(path)
    geometry = SweepGeometry.from_manifest(archive.manifest)
    try:
        check_priors(geometry.priors(), np.array([e.rail_mm for e in archive.manifest.frames]))
    except ModelError as exc:
        raise PriorError(str(exc)) from exc
    summaries: list[FrameSummary] = []
    skipped: dict[int, str] = {}
    entries = archive.manifest.frames
    n_workers = default_workers() if workers is None else max(1, workers)
    root = str(archive.root)

    def collect(entry_index: int, outcome: FrameSummary | str, done: int) -> None:
        if isinstance(outcome, str):
            skipped[entry_index] = outcome
        else:
            summaries.append(outcome)
        if progress is not None:
            progress(done, len(entries))

    if n_workers == 1 or len(entries) < 4:
        analyzer = _analyzer(archive, geometry, options)
        _worker_init(root)
        for n, entry in enumerate(entries):
            collect(entry.index, _worker_analyze(entry.index, entry.rail_mm, analyzer), n + 1)
    else:
        analyzer, pool = _analyzer_and_pool(archive, geometry, options, n_workers)
        with pool:
            futures = {
                pool.submit(_worker_analyze, e.index, e.rail_mm, analyzer): e.index for e in entries
            }
            for n, fut in enumerate(as_completed(futures)):
                collect(futures[fut], fut.result(), n + 1)
    try:
        result = combine(summaries, geometry, analyzer.grid, options=options)
    except CalibrationError as exc:
        if exc.partial is not None:
            exc.partial["skipped_frames"] = {str(k): v for k, v in sorted(skipped.items())}
        raise
    if skipped:
        result.data["skipped_frames"] = {str(k): v for k, v in sorted(skipped.items())}
        result.data["warnings"].append(
            f"{len(skipped)} frame(s) could not be read and were skipped"
        )
    return result
