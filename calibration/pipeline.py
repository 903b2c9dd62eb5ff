"""From a sweep (streamed frames or an ``lfcal-sweep/1`` archive) to calibrated parameters.

:class:`FrameAnalyzer` holds what every frame of a sweep shares (the MLA grid
fitted on the white image, the optics priors, the board) and turns one raw
frame into a :class:`FrameSummary`; it is picklable, so the station can run it
in worker processes while acquisition goes on. :func:`combine` turns the frame
summaries into a :class:`CalibrationResult`: the focus plane (Eq. 7–9 and the
whole-sweep blur model), ``Q`` at the focus plane, ``a``, ``b``, ``p`` (Eq.
1–5) and the global disparity + blur fit, with uncertainties and a consistency
check. :func:`calibrate_archive` does both for an archive on disk.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import sys
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .archive import ImageError, SweepArchive, SweepManifest
from .board import Board
from .corners import CornerOptions, MicroImageMap
from .focus import FocusAtSweepEdge, corner_size_mm, fit_blur_model, paper_focus
from .frame_analysis import CornerFit, FrameContext, analyze_frame
from .mla_grid import MlaGrid, fit_mla_grid
from .optics import focused_virtual_distance
from .parameters import Estimate, global_fit, paper_estimate, q_at
from .version import DISTRIBUTION, software_version

FOCUS_SYSTEMATIC_MM = 0.15
"""Systematic uncertainty of the blur-model focus plane (mm), added in quadrature to
its statistical one (0.05-0.1 mm on 100-frame sweeps). Measured focus-plane errors:
0.02-0.08 mm on the three presets of the project's simulator, 0.08-0.12 mm on the
three sweeps of the independent renderer (``bench/bench_crosscheck.py``)."""


class CalibrationError(ValueError):
    """The sweep cannot be calibrated; ``exit_code`` is the CLI's documented code."""

    exit_code = 3

    def __init__(self, message: str, partial: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.partial = partial


class FocusAtEdgeError(CalibrationError):
    """The focus plane lies at the edge of the sweep (extend the rail range)."""

    exit_code = 4


@dataclass(frozen=True)
class SweepGeometry:
    """Priors from the manifest or station configuration (mm, px)."""

    width: int
    height: int
    pixel_pitch_mm: float
    principal_point_px: tuple[float, float]
    main_focal_mm: float
    mla_focal_mm: float
    mla_pitch_mm: float
    board: Board
    zero_object_distance_mm: float
    direction: int

    @classmethod
    def from_manifest(cls, m: SweepManifest) -> SweepGeometry:
        return cls(
            width=m.camera.width,
            height=m.camera.height,
            pixel_pitch_mm=m.camera.pixel_pitch_mm,
            principal_point_px=m.camera.pp,
            main_focal_mm=m.optics.main_focal_mm,
            mla_focal_mm=m.optics.mla_focal_mm,
            mla_pitch_mm=m.optics.mla_pitch_mm,
            board=Board(square_mm=m.board.square_mm, reference_gap_mm=m.board.reference_gap_mm),
            zero_object_distance_mm=m.rail.zero_object_distance_mm,
            direction=m.rail.direction,
        )

    @property
    def lens_pitch_px(self) -> float:
        """``D/δ``: lens-centre pitch on the sensor (px)."""
        return self.mla_pitch_mm / self.pixel_pitch_mm

    def to_dict(self) -> dict[str, Any]:
        """The priors a calibration used (JSON-ready): recorded with every result."""
        return {
            "camera": {
                "width": self.width,
                "height": self.height,
                "pixel_pitch_mm": self.pixel_pitch_mm,
                "principal_point_px": list(self.principal_point_px),
            },
            "optics": {
                "main_focal_mm": self.main_focal_mm,
                "mla_focal_mm": self.mla_focal_mm,
                "mla_pitch_mm": self.mla_pitch_mm,
                "lens_pitch_px": self.lens_pitch_px,
            },
            "board": {
                "square_mm": self.board.square_mm,
                "reference_gap_mm": self.board.reference_gap_mm,
            },
            "rail": {
                "zero_object_distance_mm": self.zero_object_distance_mm,
                "direction": self.direction,
            },
        }

    def object_distance_mm(self, rail_mm: float) -> float:
        return self.zero_object_distance_mm + self.direction * rail_mm

    def rail_mm(self, object_distance_mm: float) -> float:
        return (object_distance_mm - self.zero_object_distance_mm) / self.direction


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of the whole calibration (keyword-only tuning, sensible defaults)."""

    interior_fraction: float = 0.8
    corner: CornerOptions = field(default_factory=CornerOptions)
    min_frames: int = 5


@dataclass
class FrameSummary:
    """What one frame contributes (JSON-ready through :meth:`to_dict`)."""

    index: int
    rail_mm: float
    object_distance_mm: float
    Q: float = float("nan")
    Q_se: float = float("nan")
    Q_eq3: float = float("nan")
    Ls_px: float = float("nan")
    Lr_px: float = float("nan")
    edge_width_px: float = float("nan")
    standard: dict[str, Any] | None = None
    reference: dict[str, Any] | None = None
    corners: dict[str, list[list[float]]] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    error: str = ""

    def to_dict(self, *, with_corners: bool = True) -> dict[str, Any]:
        d = dict(self.__dict__)
        if not with_corners:
            d.pop("corners")
        return _json_clean(d)


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
        grid = fit_mla_grid(
            white,
            lens_pitch_px=geometry.lens_pitch_px,
            principal_point_px=geometry.principal_point_px,
        )
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
        summary.rejected = r.rejected
        if not np.isfinite(summary.Q):
            summary.error = "no board corner found in this frame"
        return summary


@dataclass
class CalibrationResult:
    """The calibration of one sweep (JSON-ready through :meth:`to_dict`)."""

    data: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return self.data


def _json_clean(obj: Any) -> Any:
    """Floats that are not finite become None (JSON has no NaN); numpy scalars become Python."""
    if isinstance(obj, dict):
        return {str(k): _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _frame_arrays(frames: list[FrameSummary]) -> dict[str, NDArray[np.float64]]:
    keys = ("object_distance_mm", "rail_mm", "Q", "Q_se", "Ls_px", "Lr_px", "edge_width_px")
    return {k: np.array([getattr(f, k) for f in frames], dtype=np.float64) for k in keys}


def combine(
    frames: Iterable[FrameSummary],
    geometry: SweepGeometry,
    grid: MlaGrid,
    *,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Focus plane, parameters and uncertainties from the frame summaries.

    Raises :class:`CalibrationError` (with the per-frame results in ``partial``)
    when too few frames have corners, and :class:`FocusAtEdgeError` when the
    blur minimum is at the edge of the sweep.
    """
    opts = options or CalibrationOptions()
    g = geometry
    frames = sorted(frames, key=lambda fs: fs.object_distance_mm)
    arr = _frame_arrays(frames)
    u = arr["object_distance_mm"]
    Lp, La = corner_size_mm(arr["Ls_px"], arr["Lr_px"], g.board.reference_gap_mm)
    f, D, delta, F = g.mla_focal_mm, g.mla_pitch_mm, g.pixel_pitch_mm, g.main_focal_mm
    frames_out = []
    for k, fs in enumerate(frames):
        d = fs.to_dict(with_corners=True)
        d["patch_size_px"] = fs.Q * D / delta
        d["Lp_mm_per_px"] = float(Lp[k])
        d["La_mm"] = float(La[k])
        frames_out.append(d)
    n_ref = int(sum(1 for fs in frames if fs.reference and fs.reference.get("found")))
    n_std = int(sum(1 for fs in frames if fs.standard and fs.standard.get("found")))
    warnings: list[str] = []
    partial: dict[str, Any] = {
        "format": "lfcal-result/1",
        "software": {"name": DISTRIBUTION, "version": software_version()},
        "inputs": g.to_dict(),
        "mla": grid.to_dict(),
        "frames": frames_out,
        "corners_found": {
            "standard_frames": n_std,
            "reference_frames": n_ref,
            "frames": len(frames),
        },
    }
    good = np.isfinite(arr["Q"])
    if good.sum() < opts.min_frames:
        raise CalibrationError(
            f"a board corner was found in only {int(good.sum())} of {len(frames)} frames "
            f"(need {opts.min_frames}): is the board aligned with the lens axis and in view?",
            _json_clean(partial),
        )
    if n_ref == 0:
        warnings.append(
            "the reference corner (2s, 0) was not found in any frame (outside the ROI?): "
            "Lr, Lp and La are not available; the focus plane comes from the standard "
            "corner's blur and the disparity model"
        )
    # a first global fit (disparity only) gives b for the blur-shape curvature; then the
    # blur-model focus and Q there give a better b, and the blur model is fitted again
    disp = global_fit(u, arr["Q"], arr["Q_se"], F=F, f=f, D=D, delta=delta)
    b_guess = disp.estimate.b_mm if disp.estimate.b_mm > f else f * 1.2
    dq_du = _local_slope(u, arr["Q"], float(np.nanmedian(u)))
    for _ in range(3):
        a_f_guess = focused_virtual_distance(f, b_guess)
        try:
            blur = fit_blur_model(u, arr["edge_width_px"], F=F, a_f=a_f_guess)
        except FocusAtSweepEdge as exc:
            partial["error"] = str(exc)
            raise FocusAtEdgeError(str(exc), _json_clean(partial)) from exc
        u_focus = blur.object_distance_mm
        u_focus_se = float(np.hypot(blur.object_distance_se_mm, FOCUS_SYSTEMATIC_MM))
        q_f, q_f_se = q_at(u, arr["Q"], arr["Q_se"], u_focus)
        # the focus-plane uncertainty moves Q along the Q(u) curve
        dq_du = _local_slope(u, arr["Q"], u_focus)
        b_new = f * (1.0 + q_f)
        converged = abs(b_new - b_guess) < 1e-7 * b_guess
        b_guess = b_new
        if converged:
            break
    joint = global_fit(
        u, arr["Q"], arr["Q_se"], F=F, f=f, D=D, delta=delta, edge_width_px=arr["edge_width_px"]
    )
    q_total_se = float(np.hypot(q_f_se, dq_du * u_focus_se))
    esif = paper_estimate(
        q_f,
        q_total_se,
        f=f,
        D=D,
        delta=delta,
        focus_object_distance_mm=u_focus,
        focus_se_mm=u_focus_se,
    )
    paper = paper_focus(u, La)
    paper_est: Estimate | None = None
    if paper is not None:
        q_p, q_p_se = q_at(u, arr["Q"], arr["Q_se"], paper.object_distance_mm)
        paper_est = paper_estimate(
            q_p, q_p_se, f=f, D=D, delta=delta, focus_object_distance_mm=paper.object_distance_mm
        )
    consistency = _consistency(esif, joint.estimate)
    if not consistency["consistent"]:
        warnings.append(
            f"the ESIF estimate and the global fit disagree: b by "
            f"{100 * consistency['b_relative']:.3f} % ({consistency['b_sigma']:.1f} sigma), a by "
            f"{100 * consistency['a_relative']:.3f} %: check the rail zero distance, the rail "
            "direction and the optics priors"
        )
    result = dict(partial)
    result.update(
        {
            "a_mm": esif.a_mm,
            "b_mm": esif.b_mm,
            "Q": esif.Q,
            "patch_size_px": esif.patch_size_px,
            "uncertainty": {
                "a_mm": esif.a_se_mm,
                "b_mm": esif.b_se_mm,
                "Q": esif.Q_se,
                "patch_size_px": esif.patch_size_se_px,
                "focus_object_distance_mm": u_focus_se,
            },
            "focus": {
                "object_distance_mm": u_focus,
                "rail_mm": g.rail_mm(u_focus),
                "uncertainty_mm": u_focus_se,
                "method": "blur model fitted to the edge widths of every frame",
                "blur_model": {
                    "A_px2": blur.A_px2,
                    "B_px2": blur.B_px2,
                    "C_px2": blur.C_px2,
                    "v0_mm": blur.v0_mm,
                    "residual_rms_px2": blur.residual_rms_px2,
                },
                "paper_argmin_La": None
                if paper is None
                else {
                    "object_distance_mm": paper.object_distance_mm,
                    "rail_mm": g.rail_mm(paper.object_distance_mm),
                    "best_frame_index": frames[paper.best_index].index,
                },
                "disparity_model": {
                    "object_distance_mm": joint.estimate.focus_object_distance_mm,
                    "uncertainty_mm": joint.estimate.focus_se_mm,
                },
            },
            "estimates": {
                "esif": esif.to_dict(),
                "paper_argmin_La": None if paper_est is None else paper_est.to_dict(),
                "global": joint.estimate.to_dict(),
                "disparity_only": disp.estimate.to_dict(),
            },
            "consistency": consistency,
            "curves": {
                "object_distance_mm": u.tolist(),
                "edge_width_model_px": blur.width_model_px.tolist(),
                "inv_Q_model": joint.inv_q_model.tolist(),
            },
            "warnings": warnings,
        }
    )
    return CalibrationResult(_json_clean(result))


def _local_slope(u: NDArray[np.float64], q: NDArray[np.float64], u0: float) -> float:
    near = np.isfinite(q) & (np.abs(u - u0) <= 10.0)
    if near.sum() < 2:
        near = np.isfinite(q)
    if near.sum() < 2:
        return 0.0
    return float(np.polyfit(u[near], q[near], 1)[0])


def _consistency(a: Estimate, b: Estimate) -> dict[str, Any]:
    """Difference of two estimates of ``b`` and ``a``, in combined sigmas and relative.

    They count as consistent when each difference is within 3 sigma or within
    a systematic floor (0.05 % on b, 0.25 % on a: the global fit's slope picks
    up small defocus-dependent disparity biases that its statistical
    uncertainty does not cover).
    """

    def sig(x: float, y: float, sx: float, sy: float) -> float:
        s = math.hypot(sx, sy)
        return abs(x - y) / s if s > 0 and math.isfinite(s) else float("inf")

    b_sigma = sig(a.b_mm, b.b_mm, a.b_se_mm, b.b_se_mm)
    a_sigma = sig(a.a_mm, b.a_mm, a.a_se_mm, b.a_se_mm)
    b_rel = abs(a.b_mm - b.b_mm) / abs(a.b_mm)
    a_rel = abs(a.a_mm - b.a_mm) / abs(a.a_mm)
    return {
        "b_difference_mm": a.b_mm - b.b_mm,
        "a_difference_mm": a.a_mm - b.a_mm,
        "b_sigma": b_sigma,
        "a_sigma": a_sigma,
        "b_relative": b_rel,
        "a_relative": a_rel,
        "consistent": bool(
            (b_sigma <= 3.0 or b_rel <= 5e-4) and (a_sigma <= 3.0 or a_rel <= 2.5e-3)
        ),
    }


_WORKER: dict[str, Any] = {}


def _worker_init(root: str, analyzer: FrameAnalyzer) -> None:
    _WORKER["archive"] = SweepArchive.open(root)
    _WORKER["analyzer"] = analyzer


def _worker_analyze(index: int, rail_mm: float) -> FrameSummary | str:
    """Decode and analyse one frame in a worker; the error text when it cannot be read."""
    try:
        image = _WORKER["archive"].frame(index)
    except ImageError as exc:
        return str(exc)
    return _WORKER["analyzer"].analyze(index, rail_mm, image)


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
    core, at most 4; 1 analyses in this process).
    """
    archive = SweepArchive.open(path)
    geometry = SweepGeometry.from_manifest(archive.manifest)
    try:
        white = archive.white()
    except ImageError as exc:
        raise CalibrationError(f"white image unusable: {exc}") from exc
    try:
        analyzer = FrameAnalyzer.from_white(geometry, white, options)
    except ValueError as exc:
        raise CalibrationError(f"no microlens grid in the white image: {exc}") from exc
    summaries: list[FrameSummary] = []
    skipped: dict[int, str] = {}
    entries = archive.manifest.frames
    n_workers = default_workers() if workers is None else max(1, workers)

    def collect(entry_index: int, outcome: FrameSummary | str, done: int) -> None:
        if isinstance(outcome, str):
            skipped[entry_index] = outcome
        else:
            summaries.append(outcome)
        if progress is not None:
            progress(done, len(entries))

    if n_workers == 1 or len(entries) < 4:
        _worker_init(str(archive.root), analyzer)
        for n, entry in enumerate(entries):
            collect(entry.index, _worker_analyze(entry.index, entry.rail_mm), n + 1)
    else:
        ctx = multiprocessing.get_context("forkserver" if sys.platform != "win32" else "spawn")
        with ProcessPoolExecutor(
            n_workers,
            mp_context=ctx,
            initializer=_worker_init,
            initargs=(str(archive.root), analyzer),
        ) as pool:
            futures = {pool.submit(_worker_analyze, e.index, e.rail_mm): e.index for e in entries}
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
