"""Analysis of one raw frame: corners of the standard and the reference corner, Q, corner sizes.

The station streams frames through :func:`analyze_frame` while the sweep runs;
the offline calibration runs the same function over an archive.

Identification. Every micro-image with a saddle is measured; its corner's main
image position follows from OPTICS.md §1, ``s = (1+Q)·m - Q·r`` (corner image
``s``, lens centre ``m``, main image ``r``, all in sensor pixels), with a first
``Q`` from neighbouring micro-images. The board point is then
``-(r - pp)·δ·u/v(u)`` (the main lens inverts), rounded to the board's corner
lattice: ``(0, 0)`` is the standard corner, ``(2s, 0)`` the reference corner.

Disparity. Per corner, a least-squares fit of ``s_k = (1+Q)·m_k + c`` over all
its micro-images gives ``Q`` and its standard error (lens centres from the
lens lattice, pitch ``D/δ``: Eq. 2 needs lens-centre spacing). The paper's
Eq. 3 (mean over adjacent pairs along x) is reported beside it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .aperture_mask import ApertureMask
from .board import Board
from .corner_candidates import MicroImageMap, find_junctions
from .corners import CornerMeasurement, CornerOptions, measure_corners
from .edge_profiles import CornerLattice, ProfileWindow, half_edge_profiles
from .edge_spread import BinnedEsf, frame_esf
from .edge_window import TAIL_SAMPLES, corner_clearance_px, profile_half_px
from .lens_grid import LensGrid
from .main_image import CORNER_SE_FLOOR_PX
from .optics import image_distance

MIN_MICRO_IMAGES = 3
"""A corner's disparity is fitted from at least this many micro-images that measure it."""

SEARCH_BAND_PITCHES = 8.0
"""Half height of the first search band for corners, in micro-image pitches."""


@dataclass(frozen=True)
class FrameContext:
    """What the analysis of every frame of a sweep shares (pixels, mm)."""

    image_grid: LensGrid
    lens_grid: LensGrid
    principal_point_px: tuple[float, float]
    pixel_pitch_mm: float
    main_focal_mm: float
    board: Board
    interior_radius_px: float
    options: CornerOptions = field(default_factory=CornerOptions)


@dataclass
class CornerFit:
    """Disparity fit of one board corner in one frame."""

    name: str
    measurements: list[CornerMeasurement]
    used: NDArray[np.bool_]
    Q: float = float("nan")
    Q_se: float = float("nan")
    Q_eq3: float = float("nan")
    main_image_px: tuple[float, float] = (float("nan"), float("nan"))
    main_image_se_px: tuple[float, float] = (float("nan"), float("nan"))
    residual_rms_px: float = float("nan")
    size_px: float = float("nan")
    edge_width_px: float = float("nan")
    esf: BinnedEsf | None = None
    lattice: CornerLattice | None = None
    note: str = ""
    clipped_half_edges: int = 0
    """Half-edges whose edge spread the sensor clipped (left out of :attr:`esf`)."""
    vignetted_micro_images: int = 0
    """Used micro-images that show the corner where the main lens vignets them."""

    @property
    def n_used(self) -> int:
        return int(self.used.sum())

    def vignetted(self, mask: ApertureMask | None, image_grid: LensGrid) -> int:
        """How many of the micro-images its disparity used the main lens vignets
        (``mask``: :class:`~calibration.aperture_mask.ApertureMask`; ``image_grid`` the
        micro-image lattice)."""
        if mask is None:
            return 0
        used = [m for m, u in zip(self.measurements, self.used, strict=True) if u]
        if not used:
            return 0
        cx, cy = image_grid.centre(
            np.array([m.lens_i for m in used]), np.array([m.lens_j for m in used])
        )
        return int(np.sum(mask.vignetted(cx, cy)))

    def summary(self) -> dict[str, object]:
        return {
            "found": bool(np.isfinite(self.Q)),
            "micro_images": len(self.measurements),
            "used": self.n_used,
            "Q": self.Q,
            "Q_se": self.Q_se,
            "Q_eq3": self.Q_eq3,
            "main_image_px": list(self.main_image_px),
            "main_image_se_px": list(self.main_image_se_px),
            "residual_rms_px": self.residual_rms_px,
            "size_px": self.size_px,
            "edge_width_px": self.edge_width_px,
            "clipped_half_edges": self.clipped_half_edges,
            "vignetted_micro_images": self.vignetted_micro_images,
            "note": self.note,
        }


@dataclass
class FrameResult:
    """Everything measured in one frame."""

    object_distance_mm: float
    standard: CornerFit | None
    reference: CornerFit | None
    rejected: dict[str, int]

    @property
    def Q(self) -> float:
        """Inverse-variance weighted Q of the corners found."""
        fits = [f for f in (self.standard, self.reference) if f and np.isfinite(f.Q)]
        if not fits:
            return float("nan")
        w = np.array([1.0 / max(f.Q_se, 1e-9) ** 2 for f in fits])
        return float(np.sum(w * np.array([f.Q for f in fits])) / np.sum(w))

    @property
    def Q_se(self) -> float:
        fits = [f for f in (self.standard, self.reference) if f and np.isfinite(f.Q)]
        if not fits:
            return float("nan")
        return float(1.0 / np.sqrt(sum(1.0 / max(f.Q_se, 1e-9) ** 2 for f in fits)))

    @property
    def Ls_px(self) -> float:
        return self.standard.size_px if self.standard else float("nan")

    @property
    def Lr_px(self) -> float:
        return self.reference.size_px if self.reference else float("nan")

    @property
    def edge_width_px(self) -> float:
        """Mean edge-spread sigma over both corners' micro-images (px)."""
        vals = [f.edge_width_px for f in (self.standard, self.reference) if f and f.n_used]
        return float(np.mean(vals)) if vals else float("nan")


def _rough_q(meas: list[CornerMeasurement], ctx: FrameContext) -> float:
    """Median of ``Δs/Δm - 1`` over adjacent micro-image pairs (a first Q for identification)."""
    pos = {(m.lens_i, m.lens_j): (m.x, m.y) for m in meas if m.ok}
    e1 = ctx.lens_grid.e1
    e2 = ctx.lens_grid.e2
    ratios = []
    for (i, j), (x, y) in pos.items():
        for di, dj, e in ((1, 0, e1), (0, 1, e2)):
            other = pos.get((i + di, j + dj))
            if other is not None:
                d = (other[0] - x) * e[0] + (other[1] - y) * e[1]
                ratios.append(d / ctx.lens_grid.pitch_px - 1.0)
    ratios_arr = np.array(ratios)
    ratios_arr = ratios_arr[(ratios_arr > 0.01) & (ratios_arr < 2.0)]
    return float(np.median(ratios_arr)) if ratios_arr.size else float("nan")


def _fit_disparity(fit: CornerFit, ctx: FrameContext) -> None:
    """Least-squares ``s = (1+Q)·m + c`` with iterative 4-sigma outlier rejection."""
    ok = np.array([m.ok for m in fit.measurements], dtype=bool)
    if ok.sum() < MIN_MICRO_IMAGES:
        fit.used = ok & False
        fit.note = f"only {int(ok.sum())} micro-images measured (need {MIN_MICRO_IMAGES})"
        return
    ii = np.array([m.lens_i for m in fit.measurements])
    jj = np.array([m.lens_j for m in fit.measurements])
    mx, my = ctx.lens_grid.centre(ii, jj)
    sx = np.array([m.x for m in fit.measurements])
    sy = np.array([m.y for m in fit.measurements])
    se = np.array([max(m.x_se, m.y_se, CORNER_SE_FLOOR_PX) for m in fit.measurements])
    use = ok.copy()
    for _ in range(4):
        n = int(use.sum())
        if n < MIN_MICRO_IMAGES:
            break
        design = np.zeros((2 * n, 3))
        design[:n, 0] = mx[use]
        design[n:, 0] = my[use]
        design[:n, 1] = 1.0
        design[n:, 2] = 1.0
        target = np.concatenate([sx[use], sy[use]])
        wts = 1.0 / np.concatenate([se[use], se[use]]) ** 2
        sw = np.sqrt(wts)
        coef, *_ = np.linalg.lstsq(design * sw[:, None], target * sw, rcond=None)
        resid = target - design @ coef
        chi2 = float(np.sum(wts * resid**2) / max(1, 2 * n - 3))
        cov = np.linalg.inv((design * wts[:, None]).T @ design) * max(chi2, 1.0)
        rx = sx - (coef[0] * mx + coef[1])
        ry = sy - (coef[0] * my + coef[2])
        r = np.hypot(rx, ry)
        scale = 1.4826 * float(np.median(r[use])) + 1e-3
        new_use = ok & (r <= 4.0 * scale + 3.0 * se)
        if np.array_equal(new_use, use):
            break
        use = new_use
    fit.used = use
    q = coef[0] - 1.0
    fit.Q = float(q)
    fit.Q_se = float(np.sqrt(cov[0, 0]))
    fit.main_image_px = (float(-coef[1] / q), float(-coef[2] / q))
    # r = -c/Q with Q = coef0 - 1: first-order propagation of the fit covariance
    fit.main_image_se_px = tuple(  # type: ignore[assignment]
        float(
            np.sqrt(
                max(
                    (coef[k] / q**2) ** 2 * cov[0, 0]
                    + cov[k, k] / q**2
                    - 2.0 * coef[k] / q**3 * cov[0, k],
                    0.0,
                )
            )
        )
        for k in (1, 2)
    )
    fit.residual_rms_px = float(np.sqrt(np.mean(r[use] ** 2)))
    used = [m for m, u in zip(fit.measurements, use, strict=True) if u]
    sizes = np.array([m.size_px for m in used])
    fit.size_px = float(np.nanmean(sizes)) if np.isfinite(sizes).any() else float("nan")
    fit.edge_width_px = float(np.mean([m.edge_width_px for m in used]))
    fit.Q_eq3 = _eq3(used, ctx)
    fit.lattice = _corner_lattice(
        used,
        np.asarray(coef, dtype=np.float64),
        np.asarray(cov, dtype=np.float64),
        gap=fit.name == "reference",
    )


def _corner_lattice(
    used: list[CornerMeasurement],
    coef: NDArray[np.float64],
    cov: NDArray[np.float64],
    *,
    gap: bool,
) -> CornerLattice:
    """The corner's lattice ``s = (1+Q)·m + c`` with its covariance, the median slopes of
    its edges and, for the reference corner, the mean offset of the halves of each edge
    (its gap ``Cr`` imaged) with that mean's variance; the standard corner's halves meet."""
    slopes = np.array([m.slopes for m in used], dtype=np.float64)
    halves = np.array([m.half_offset_px for m in used], dtype=np.float64)
    if gap and len(used) >= 2:
        half = tuple(float(v) for v in halves.mean(axis=0))
        half_var = tuple(float(v) for v in halves.var(axis=0, ddof=1) / len(used))
    else:
        half, half_var = (0.0, 0.0), (0.0, 0.0)
    return CornerLattice(
        coef=(float(coef[0]), float(coef[1]), float(coef[2])),
        covariance=np.asarray(cov, dtype=np.float64),
        slope_v=float(np.median(slopes[:, 0])),
        slope_h=float(np.median(slopes[:, 1])),
        slope_var=_median_var(slopes),
        half_px=half,  # type: ignore[arg-type]
        half_var_px2=half_var,  # type: ignore[arg-type]
    )


def _median_var(values: NDArray[np.float64]) -> tuple[float, float]:
    """Variance of each column's median: π/2 times that of its mean (normal errors); inf
    from fewer than two values."""
    n = values.shape[0]
    if n < 2:
        return float("inf"), float("inf")
    var = np.var(values, axis=0, ddof=1) * (0.5 * np.pi) / n
    return float(var[0]), float(var[1])


def _eq3(used: list[CornerMeasurement], ctx: FrameContext) -> float:
    """The paper's Eq. 3: mean over x-adjacent pairs of ``(x_ui - x_ui+1)/(x_Mi - x_Mi+1) - 1``."""
    pos = {(m.lens_i, m.lens_j): m for m in used}
    vals = []
    for (i, j), m in pos.items():
        other = pos.get((i + 1, j))
        if other is None:
            continue
        mx0, _ = ctx.lens_grid.centre(i, j)
        mx1, _ = ctx.lens_grid.centre(i + 1, j)
        vals.append((m.x - other.x) / (float(mx0) - float(mx1)) - 1.0)
    return float(np.mean(vals)) if vals else float("nan")


def _reference_gap_px(
    rough: list[CornerMeasurement], ctx: FrameContext, object_distance_mm: float
) -> float:
    """The reference corner's gap ``Cr`` as a micro-image shows it (px): board mm times
    the main lens's ``v/u`` times the micro-images' rough ``Q`` over the pixel pitch; 0 when
    no rough ``Q`` is known."""
    q = _rough_q(rough, ctx)
    if not (np.isfinite(q) and q > 0):
        return 0.0
    v = float(image_distance(object_distance_mm, ctx.main_focal_mm))
    return float(ctx.board.reference_gap_mm * v / object_distance_mm * q / ctx.pixel_pitch_mm)


def _group_by_board_corner(
    meas: list[CornerMeasurement], ctx: FrameContext, object_distance_mm: float
) -> dict[tuple[int, int], list[CornerMeasurement]]:
    """Which board corner (in squares) each measured micro-image shows."""
    q0 = _rough_q(meas, ctx)
    groups: dict[tuple[int, int], list[CornerMeasurement]] = {}
    if not (np.isfinite(q0) and q0 > 0):
        return groups
    v = float(image_distance(object_distance_mm, ctx.main_focal_mm))
    mm_per_px = ctx.pixel_pitch_mm * object_distance_mm / v
    cx, cy = ctx.principal_point_px
    s = ctx.board.square_mm
    for m in meas:
        if not m.ok:
            continue
        mx, my = ctx.lens_grid.centre(m.lens_i, m.lens_j)
        rx = ((1 + q0) * float(mx) - m.x) / q0
        ry = ((1 + q0) * float(my) - m.y) / q0
        bx, by = -(rx - cx) * mm_per_px, -(ry - cy) * mm_per_px
        groups.setdefault((int(round(bx / s)), int(round(by / s))), []).append(m)
    return groups


def analyze_frame(
    frame: NDArray[np.integer] | NDArray[np.floating],
    ctx: FrameContext,
    object_distance_mm: float,
    *,
    micro_image_map: MicroImageMap | None = None,
) -> FrameResult:
    """Find and measure the standard and reference corners in one raw frame.

    ``micro_image_map`` may be passed in to reuse it across frames of a sweep.
    """
    mim = micro_image_map or MicroImageMap(ctx.image_grid, frame.shape, ctx.interior_radius_px)
    # both corners lie on the board's row Y = 0, imaged near the principal point's row:
    # search a band of rows first, the whole frame only when the band shows neither
    half_band = int(SEARCH_BAND_PITCHES * ctx.image_grid.pitch_px)
    cy = int(round(ctx.principal_point_px[1]))
    first = (max(0, cy - half_band), min(int(frame.shape[0]), cy + half_band + 1))
    bands: list[tuple[int, int] | None] = [None]
    if first[1] - first[0] > 0 and first != (0, frame.shape[0]):
        bands.insert(0, first)
    wanted: dict[tuple[int, int], list[CornerMeasurement]] = {}
    for band in bands:
        junctions = find_junctions(frame, mim, sigma_px=ctx.options.saddle_sigma_px, rows=band)
        # identify the board corner of every saddle first, then measure only the two we need
        rough = [
            CornerMeasurement(lens_i=int(i), lens_j=int(j), x=float(x), y=float(y), ok=True)
            for i, j, x, y in zip(junctions.i, junctions.j, junctions.x, junctions.y, strict=True)
        ]
        wanted = {
            k: v
            for k, v in _group_by_board_corner(rough, ctx, object_distance_mm).items()
            if k in ((0, 0), (2, 0))
        }
        if wanted:
            break
    starts = [(m.lens_i, m.lens_j, m.x, m.y) for members in wanted.values() for m in members]
    # the reference corner's edges are split by its gap Cr, imaged at the frame's rough Q
    gap_px = _reference_gap_px(rough, ctx, object_distance_mm)
    gaps = [gap_px if key == (2, 0) else 0.0 for key, members in wanted.items() for _ in members]
    meas = measure_corners(
        frame,
        starts,
        ctx.image_grid,
        interior_radius_px=ctx.interior_radius_px,
        options=ctx.options,
        lens_grid=ctx.lens_grid,
        gaps_px=gaps,
    )
    rejected: dict[str, int] = {}
    for m in meas:
        if not m.ok:
            rejected[m.reason] = rejected.get(m.reason, 0) + 1
    groups = _group_by_board_corner(meas, ctx, object_distance_mm)
    result = FrameResult(object_distance_mm, None, None, rejected)
    for name, key in (("standard", (0, 0)), ("reference", (2, 0))):
        members = groups.get(key, [])
        if not members:
            continue
        fit = CornerFit(name, members, np.zeros(len(members), dtype=bool))
        _fit_disparity(fit, ctx)
        fit.vignetted_micro_images = fit.vignetted(ctx.options.aperture_mask, ctx.image_grid)
        setattr(result, name, fit)
    scale = _board_scale_px_per_mm(result, ctx, object_distance_mm)
    for found in (result.standard, result.reference):
        if found is not None and found.lattice is not None and np.isfinite(found.Q):
            found.esf = _edge_spread(frame, found, ctx, float(found.Q) * scale)
    return result


PROFILE_PLATEAU_FRACTION = 0.5
"""A profile's half length is at most this fraction of the plateau's radius (its 2h + 1
samples must lie inside the plateau, for enough rows of every micro-image)."""

REACH_FRACTION = 0.8
"""Profiles are cut along a half-edge up to this fraction of a board square from its
corner: short of the next corner of the board."""


def _board_scale_px_per_mm(
    result: FrameResult, ctx: FrameContext, object_distance_mm: float
) -> float:
    """Main-image pixels per board millimetre, ``M/δ``: from the two corners' main images
    (``2s`` apart on the board) when both were found, else from the data-sheet focal length."""
    std, ref = result.standard, result.reference
    if std is not None and ref is not None and np.isfinite(std.Q) and np.isfinite(ref.Q):
        dist = float(np.hypot(*np.subtract(ref.main_image_px, std.main_image_px)))
        if np.isfinite(dist) and dist > 0:
            return dist / (2.0 * ctx.board.square_mm)
    v = float(image_distance(object_distance_mm, ctx.main_focal_mm))
    return v / object_distance_mm / ctx.pixel_pitch_mm


def _edge_spread(
    frame: NDArray[np.integer] | NDArray[np.floating],
    fit: CornerFit,
    ctx: FrameContext,
    px_per_board_mm: float,
) -> BinnedEsf | None:
    """The corner's edge-spread function from every micro-image that shows its half-edges."""
    opts = ctx.options
    plateau_px = opts.plateau_px(ctx.image_grid.pitch_px)
    # longer profiles for blurred edges (flat tails), within what the plateau holds
    half_px = profile_half_px(
        fit.edge_width_px,
        minimum=opts.profile_half_px,
        maximum=int(PROFILE_PLATEAU_FRACTION * plateau_px),
    )
    window = ProfileWindow(
        plateau_px=plateau_px,
        clearance_px=corner_clearance_px(fit.edge_width_px, minimum_px=opts.blur_clearance_px),
        reach_px=REACH_FRACTION * ctx.board.square_mm * px_per_board_mm,
        half_px=half_px,
        flat_field=opts.flat_field,
        clip_count=opts.clip_count,
        aperture_mask=opts.aperture_mask,
    )
    assert fit.lattice is not None
    placed = half_edge_profiles(frame, fit.lattice, ctx.lens_grid, ctx.image_grid, window)
    fit.clipped_half_edges = placed.clipped_half_edges
    return frame_esf(
        placed.profiles,
        start_width_px=fit.edge_width_px,
        placement=placed.placement,
        max_flat_px=half_px - TAIL_SAMPLES,
        drift=not window.flat_field.active,
    )
