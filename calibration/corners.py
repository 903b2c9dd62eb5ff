"""ESIF corner detection in the micro-images of a raw frame (the paper's Algorithm 1, Eq. 6).

For every micro-image that shows a board corner:

1. **candidate**: the strongest saddle (most negative Hessian determinant of the
   Gaussian-smoothed frame, at half resolution) inside the micro-image's
   interior disc;
2. **refinement**: the edge blocks below are placed around the candidate; a
   corner found more than ``restart_px`` away is measured again around the
   corner found. The paper's median filter + Hough lines (Canny and
   probabilistic Hough find the half-edges leaving the corner, their
   intersection refines the start) run when ``CornerOptions.hough`` is set,
   as a diagnostic: the line count is recorded, never a rejection (the
   paper's "exactly 4 lines" rule loses good micro-images in noise and
   vignetting); by default they are skipped (about a third of a frame's
   analysis time, for a start point the saddle already gives to a pixel);
3. **edge blocks**: rows above (A) and below (D) the corner sample the vertical
   edge, columns left (B) and right (C) the horizontal edge; each row/column
   profile is fitted with the blurred-step model of :mod:`calibration.edge_fit`
   (on the raw counts, so the filter cannot bias the sub-pixel positions),
   divided by the white image's shading about the micro-image when there is one
   (``CornerOptions.flat_field``): a level that falls across an edge moves the
   fitted step, and the bowl of cos⁴ and vignetting falls radially, so it pulled
   every corner towards its micro-image's centre and read ``Q`` low (beyond the
   fully lit plateau the bowl is the white's measured fall, not the plateau's
   paraboloid: the rims blurred inwards by diffraction read ``Q`` 0.1 % low); each
   profile is fitted on the samples whose mirror about its edge is fitted too
   (:func:`calibration.edge_fit.fit_edges_symmetric`): a window cut unevenly by the
   plateau or the profile's end read long-tailed (diffraction) edges towards its
   longer side, inwards near the rim (wave optics: ``Q`` 0.04 % low);
4. **corner**: ``x = (x̄_A + x̄_D)/2``, ``y = (ȳ_B + ȳ_C)/2`` (Eq. 6 with equal
   weight per side; a common slope per edge absorbs a small board tilt). Equal
   side weights keep the reference corner unbiased: its edges jog by ``±Cr/2``
   on the two sides of the corner.

The **corner pixel size** is the width of the region around the corner in which
the edge fits do not resolve the edge, measured as an equivalent width: along
each edge, the sum over one profile per pixel of the missing fraction of edge
contrast (``1 - C/C_far``), averaged over the two edges. It grows with blur, and
for the reference corner it adds about the gap ``Cr`` (in pixels) minus a
blur-dependent part, which is why Eq. 7's ``Lp`` is only approximate.
Coordinates are sensor pixels, pixel centres at integers, arrays ``[y, x]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .aperture_mask import ApertureMask
from .corner_candidates import hough_refine
from .edge_fit import EdgeFits, fit_edges_symmetric
from .flat_field import FlatField
from .lens_grid import LensGrid

MIN_FITTED_SAMPLES = 7
"""Fewest samples of an edge profile its fit may use (four parameters)."""


@dataclass(frozen=True)
class CornerOptions:
    """Tunables of the corner detector (pixels unless stated)."""

    saddle_sigma_px: float = 2.0
    interior_fraction: float = 0.72
    profile_half_px: int = 6
    min_points_per_block: int = 4
    resolved_contrast: float = 0.9
    size_window_px: float = 5.0
    hough_threshold: int = 8
    hough: bool = False
    restart_px: float = 1.5
    max_block_offset_px: float = 3.0
    """A corner whose two halves of an edge lie farther apart than expected (0, or the
    reference corner's gap as :func:`measure_corners` is told) by more than this is
    rejected: not a corner, or two different edges."""
    blur_clearance_px: float = 3.0
    """Least distance (px) of an edge-spread profile from its corner along the edge; more
    for blurred edges (:func:`calibration.edge_window.corner_clearance_px`)."""
    blur_radius_fraction: float = 0.7
    profile_core_half_px: int = 2
    """A corner's edge profile (all of it within the micro-image interior) leaves its samples
    beyond the fully lit plateau (``blur_radius_fraction`` of the micro-image radius) out of
    its fit when its samples within this distance of its centre, and at least
    ``MIN_FITTED_SAMPLES`` in all, lie on the plateau."""
    flat_field: FlatField = FlatField()
    """The white image's smooth shading about each micro-image centre: the corners' edge
    profiles are divided by it before they are fitted, and the edge-spread profiles before
    their levels are read (:mod:`calibration.flat_field`)."""
    clip_count: float = float("inf")
    """The count at which the sensor clips (its full scale, ``2**bit_depth − 1``): the
    edge-spread profiles of a half-edge with a clipped sample are not used
    (:mod:`calibration.clipping`)."""
    aperture_mask: ApertureMask | None = None
    """The pixels of micro-images the main lens vignets that still see their whole
    microlens aperture (:mod:`calibration.aperture_mask`): the edge spreads use only those
    pixels. Corners are still measured in vignetted micro-images, and counted
    (``CornerFit.vignetted_micro_images``): leaving them out lost the reference corner in
    most frames."""

    def plateau_px(self, image_pitch_px: float) -> float:
        """Radius (px) of the micro-images' fully lit plateau, ``blur_radius_fraction`` of
        half the micro-image pitch."""
        return self.blur_radius_fraction * 0.5 * image_pitch_px


@dataclass
class CornerMeasurement:
    """One micro-image's corner (sensor pixels) and its diagnostics."""

    lens_i: int
    lens_j: int
    x: float = float("nan")
    y: float = float("nan")
    x_se: float = float("nan")
    y_se: float = float("nan")
    size_x_px: float = float("nan")
    size_y_px: float = float("nan")
    edge_width_px: float = float("nan")
    residual_rms: float = float("nan")
    points: dict[str, int] = field(default_factory=dict)
    hough_lines: int = -1
    ok: bool = False
    reason: str = ""
    detail: str = ""
    half_offset_px: tuple[float, float] = (0.0, 0.0)
    """Half the offset between the two opposite blocks of each edge, ``((x_A - x_D)/2,
    (y_B - y_C)/2)``: 0 for the standard corner, ``±Cr/2`` imaged for the reference corner."""
    slopes: tuple[float, float] = (0.0, 0.0)
    """``(dx/dy of the vertical edge, dy/dx of the horizontal edge)``: a board turned about
    the optical axis."""

    @property
    def size_px(self) -> float:
        """Corner pixel size: mean of the sizes along the two edges."""
        return 0.5 * (self.size_x_px + self.size_y_px)

    def to_dict(self) -> dict[str, object]:
        d = dict(self.__dict__)
        d["size_px"] = self.size_px
        return d


@dataclass
class _Block:
    """Profiles of one edge block of one micro-image."""

    owner: int
    name: str  # "A", "D" (vertical edge, row profiles), "B", "C" (horizontal edge, column profiles)
    along: NDArray[np.float64]  # row (A, D) or column (B, C) coordinate of each profile
    start: NDArray[np.float64]  # coordinate of the first sample across the edge
    rows: slice | None = None  # where its profiles sit in the batch


def _collect_blocks(
    owner: int,
    x0: int,
    y0: int,
    centre: tuple[float, float],
    radius: float,
    shape: tuple[int, int],
    opts: CornerOptions,
) -> list[_Block]:
    """The four edge blocks around the start point ``(x0, y0)``: row profiles above (A) and
    below (D) it across the vertical edge, column profiles left (B) and right (C) of it
    across the horizontal edge, each profile wholly within ``radius`` of the micro-image
    ``centre`` and in the frame (``shape``)."""
    h = opts.profile_half_px
    height, width = shape
    cx, cy = centre
    r2 = radius * radius
    span = int(radius) + 1
    blocks: list[_Block] = []
    for name, sign, first in (("A", -1, 0), ("D", 1, 1)):
        ys = y0 + sign * np.arange(first, span + 1)
        ok = (ys >= 0) & (ys < height) & (x0 - h >= 0) & (x0 + h < width)
        far = max((x0 - h - cx) ** 2, (x0 + h - cx) ** 2) + (ys - cy) ** 2
        ys = ys[ok & (far <= r2)]
        if ys.size:
            blocks.append(_Block(owner, name, ys.astype(float), np.full(ys.size, x0 - h, float)))
    for name, sign, first in (("B", -1, 0), ("C", 1, 1)):
        xs = x0 + sign * np.arange(first, span + 1)
        ok = (xs >= 0) & (xs < width) & (y0 - h >= 0) & (y0 + h < height)
        far = max((y0 - h - cy) ** 2, (y0 + h - cy) ** 2) + (xs - cx) ** 2
        xs = xs[ok & (far <= r2)]
        if xs.size:
            blocks.append(_Block(owner, name, xs.astype(float), np.full(xs.size, y0 - h, float)))
    return blocks


def _profiles(
    img: NDArray[np.float32],
    blocks: list[_Block],
    centres: NDArray[np.float64],
    gradients: NDArray[np.float64],
    plateau_px: float,
    opts: CornerOptions,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Every block's profiles (one row each, in block order), divided by the flat field
    about their micro-image's centre with its shading gradient (``centres``, ``gradients``:
    one row per block, px and per px), and which samples their fits use: those on the fully
    lit plateau (within ``plateau_px`` of the centre), unless fewer than
    ``MIN_FITTED_SAMPLES`` or the central ``2·core + 1``
    (``CornerOptions.profile_core_half_px``) are, when the whole profile is fitted."""
    h = opts.profile_half_px
    offsets = np.arange(-h, h + 1, dtype=np.float64)
    counts = np.array([b.along.size for b in blocks])
    vertical = np.repeat([b.name in "AD" for b in blocks], counts)[:, None]
    along = np.concatenate([b.along for b in blocks])[:, None]
    across = np.concatenate([b.start for b in blocks])[:, None] + h + offsets[None, :]
    xs = np.where(vertical, across, along)
    ys = np.where(vertical, along, across)
    values = img[ys.astype(np.intp), xs.astype(np.intp)].astype(np.float64)
    dx = xs - np.repeat(centres[:, 0], counts)[:, None]
    dy = ys - np.repeat(centres[:, 1], counts)[:, None]
    valid = dx * dx + dy * dy <= plateau_px * plateau_px
    core = np.abs(offsets) <= min(opts.profile_core_half_px, h)
    short = ~valid[:, core].all(axis=1) | (valid.sum(axis=1) < MIN_FITTED_SAMPLES)
    valid[short] = True
    if opts.flat_field.active:
        tilt = (
            np.repeat(gradients[:, 0], counts)[:, None],
            np.repeat(gradients[:, 1], counts)[:, None],
        )
        values = opts.flat_field.divide(values, (dx, dy), tilt)
    return values, valid


def _deficit_width(first: tuple[Any, ...], second: tuple[Any, ...], window_px: float) -> float:
    """Equivalent width of the unresolved region along one edge (pixels).

    The sum over the profiles within ``window_px`` of the corner of the
    missing fraction of edge contrast ``1 - C/C_far``: one profile per pixel,
    so the sum is the width of a region with no edge at all that would lose
    the same contrast. It grows with the blur; the reference corner's gap adds
    about ``Cr`` in pixels.
    """
    along = np.concatenate([first[0], second[0]])
    ratio = np.concatenate([first[4], second[4]])
    centre = first[0][0]
    near = np.abs(along - centre) <= window_px
    expected = 2 * int(window_px) + 1
    if int(near.sum()) < expected:
        return float("nan")
    return float(np.sum(1.0 - ratio[near]))


def _edge_from_blocks(
    first: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]],
    second: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]],
) -> tuple[float, float, float, float, float]:
    """Common-slope line fit through the edge points of two opposite blocks.

    Each block is ``(along, across, se, use)``. Returns ``(intercept_first,
    intercept_second, slope, se of the mean intercept, reference coordinate)``:
    the edge point at ``along = ref`` is ``mean(intercepts)``.
    """
    a1, c1, s1, u1 = first
    a2, c2, s2, u2 = second
    groups = [(a1[u1], c1[u1], s1[u1]), (a2[u2], c2[u2], s2[u2])]
    ref = float(0.5 * (np.mean(groups[0][0]) + np.mean(groups[1][0])))
    # weighted least squares of a common slope and one intercept per block, in closed
    # form: the slope from the deviations about each block's weighted means
    wts = [1.0 / np.maximum(se, 0.005) ** 2 for _, _, se in groups]
    w_sums = [float(np.sum(w)) for w in wts]
    d_means, c_means, d_dev, c_dev = [], [], [], []
    for (along, across, _), w, w_sum in zip(groups, wts, w_sums, strict=True):
        d_means.append(float(np.sum(w * (along - ref))) / w_sum)
        c_means.append(float(np.sum(w * across)) / w_sum)
        d_dev.append(along - ref - d_means[-1])
        c_dev.append(across - c_means[-1])
    w, dd, dc = np.concatenate(wts), np.concatenate(d_dev), np.concatenate(c_dev)
    sxx = float(np.sum(w * dd * dd))
    if not sxx > 0.0:
        return _edge_from_blocks_lstsq(groups, ref)
    slope = float(np.sum(w * dd * dc)) / sxx
    intercepts = [cm - slope * dm for dm, cm in zip(d_means, c_means, strict=True)]
    s2_unit = float(np.sum(w * (dc - slope * dd) ** 2)) / max(1, dd.size - 3)
    # variance of the mean intercept: 1/W1 + 1/W2 + (d̄1 + d̄2)²/Sxx, over four
    var_sum = 1.0 / w_sums[0] + 1.0 / w_sums[1] + (d_means[0] + d_means[1]) ** 2 / sxx
    mean_se = 0.5 * float(np.sqrt(max(var_sum, 0.0) * max(s2_unit, 1.0)))
    return intercepts[0], intercepts[1], slope, mean_se, ref


def _edge_from_blocks_lstsq(
    groups: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]],
    ref: float,
) -> tuple[float, float, float, float, float]:
    """:func:`_edge_from_blocks` by a least-norm solution, for points all at one position
    along the edge (the slope undetermined)."""
    along = np.concatenate([g[0] for g in groups])
    across = np.concatenate([g[1] for g in groups])
    se = np.concatenate([g[2] for g in groups])
    wts = 1.0 / np.maximum(se, 0.005) ** 2
    design = np.zeros((along.size, 3))
    n1 = groups[0][0].size
    design[:n1, 0] = 1.0
    design[n1:, 1] = 1.0
    design[:, 2] = along - ref
    sw = np.sqrt(wts)
    coef, *_ = np.linalg.lstsq(design * sw[:, None], across * sw, rcond=None)
    resid = across - design @ coef
    dof = max(1, along.size - 3)
    s2_unit = float(np.sum(wts * resid**2) / dof)
    cov = np.linalg.pinv((design * wts[:, None]).T @ design) * max(s2_unit, 1.0)
    mean_se = 0.5 * float(np.sqrt(max(cov[0, 0] + cov[1, 1] + 2 * cov[0, 1], 0.0)))
    return float(coef[0]), float(coef[1]), float(coef[2]), mean_se, ref


def measure_corners(
    frame: NDArray[np.floating] | NDArray[np.integer],
    starts: list[tuple[int, int, float, float]],
    image_grid: LensGrid,
    *,
    interior_radius_px: float,
    options: CornerOptions | None = None,
    lens_grid: LensGrid | None = None,
    gaps_px: Sequence[float] | None = None,
) -> list[CornerMeasurement]:
    """ESIF corner measurement for each start ``(i, j, x0, y0)`` (lens index, rough position).

    ``gaps_px``: per start, how far apart the two halves of each edge are expected to lie
    (the reference corner's gap ``Cr`` as the micro-image shows it); 0 for all when None.

    ``lens_grid`` (the lens centres) gives each micro-image the tilt of the shading
    ``options.flat_field`` divides out (without it only the bowl about the micro-image
    centre is divided).

    All edge profiles of all micro-images are fitted in one batch. A corner
    found more than ``restart_px`` from its start is measured again with its
    edge blocks placed around the corner found (the start is a half-resolution
    saddle; the paper's Hough lines refine it instead when ``options.hough`` is set).
    """
    opts = options or CornerOptions()
    img = np.asarray(frame, dtype=np.float32)
    gaps = [0.0] * len(starts) if gaps_px is None else [float(g) for g in gaps_px]
    results = _measure_batch(img, starts, gaps, image_grid, interior_radius_px, opts, lens_grid)
    again = [
        k
        for k, m in enumerate(results)
        if m.ok and np.hypot(m.x - starts[k][2], m.y - starts[k][3]) > opts.restart_px
    ]
    if again:
        restarts = [(starts[k][0], starts[k][1], results[k].x, results[k].y) for k in again]
        second = _measure_batch(
            img, restarts, [gaps[k] for k in again], image_grid, interior_radius_px, opts, lens_grid
        )
        for k, m in zip(again, second, strict=True):
            results[k] = m
    return results


def _measure_batch(
    img: NDArray[np.float32],
    starts: list[tuple[int, int, float, float]],
    gaps: list[float],
    image_grid: LensGrid,
    interior_radius_px: float,
    opts: CornerOptions,
    lens_grid: LensGrid | None,
) -> list[CornerMeasurement]:
    height, width = img.shape
    results: list[CornerMeasurement] = []
    all_blocks: list[_Block] = []
    block_centres: list[tuple[float, float]] = []
    block_gradients: list[tuple[float, float]] = []
    # samples beyond the fully lit plateau (the rim, which the flat field does not model)
    # are left out of the fits
    plateau_px = opts.plateau_px(image_grid.pitch_px)
    hp = opts.profile_half_px
    win = int(round(interior_radius_px))
    n_rows = 0
    for owner, (i, j, xs, ys) in enumerate(starts):
        m = CornerMeasurement(lens_i=int(i), lens_j=int(j))
        results.append(m)
        cx, cy = image_grid.centre(i, j)
        cxf, cyf = float(cx), float(cy)
        x0, y0 = int(round(xs)), int(round(ys))
        if not (win <= x0 < width - win and win <= y0 < height - win):
            if not (hp <= x0 < width - hp and hp <= y0 < height - hp):
                m.reason = "corner candidate at the frame border"
                continue
        if opts.hough:
            patch_r = min(win, x0, y0, width - 1 - x0, height - 1 - y0)
            patch = img[y0 - patch_r : y0 + patch_r + 1, x0 - patch_r : x0 + patch_r + 1]
            m.hough_lines, ddx, ddy = hough_refine(patch, threshold=opts.hough_threshold)
            if abs(ddx) <= 2 and abs(ddy) <= 2:
                x0, y0 = int(round(x0 + ddx)), int(round(y0 + ddy))
        if np.hypot(x0 - cxf, y0 - cyf) > interior_radius_px - 2:
            m.reason = "corner outside the micro-image interior (rim or vignetting)"
            continue
        gradient = (0.0, 0.0)
        if lens_grid is not None and opts.flat_field.active:
            lens_x, lens_y = lens_grid.centre(i, j)
            gx, gy = opts.flat_field.gradients((cx, cy), (lens_x, lens_y))
            gradient = (float(gx), float(gy))
        for b in _collect_blocks(owner, x0, y0, (cxf, cyf), interior_radius_px, img.shape, opts):
            b.rows = slice(n_rows, n_rows + b.along.size)
            n_rows += b.along.size
            all_blocks.append(b)
            block_centres.append((cxf, cyf))
            block_gradients.append(gradient)
    if not all_blocks:
        return results
    stacked, valid = _profiles(
        img,
        all_blocks,
        np.array(block_centres, dtype=np.float64),
        np.array(block_gradients, dtype=np.float64),
        plateau_px,
        opts,
    )
    fits = fit_edges_symmetric(stacked, valid=valid, min_samples=MIN_FITTED_SAMPLES)
    by_owner: dict[int, dict[str, _Block]] = {}
    for b in all_blocks:
        by_owner.setdefault(b.owner, {})[b.name] = b
    for owner, owned in by_owner.items():
        _finish(results[owner], owned, fits, opts, gaps[owner])
    return results


def _finish(
    m: CornerMeasurement,
    blocks: dict[str, _Block],
    fits: EdgeFits,
    opts: CornerOptions,
    gap_px: float,
) -> None:
    missing = [n for n in "ADBC" if n not in blocks]
    if missing:
        m.reason = "edge block outside the micro-image interior"
        m.detail = f"block(s) {', '.join(missing)}"
        return
    per: dict[str, tuple] = {}
    widths: list[NDArray[np.float64]] = []
    resid: list[NDArray[np.float64]] = []
    contrast_far: dict[str, float] = {}
    for edge, names in (("v", "AD"), ("h", "BC")):
        cs = []
        for n in names:
            b = blocks[n]
            rows = b.rows
            assert rows is not None
            c = np.where(fits.ok[rows], np.abs(fits.contrast[rows]), 0.0)
            far = c[len(c) // 2 :] if len(c) >= 4 else c
            cs.append(far[far > 0])
        allc = np.concatenate(cs) if cs else np.empty(0)
        contrast_far[edge] = float(np.median(allc)) if allc.size else 0.0
    for n in "ADBC":
        b = blocks[n]
        rows = b.rows
        assert rows is not None
        edge = "v" if n in "AD" else "h"
        cfar = contrast_far[edge]
        ok = fits.ok[rows]
        contrast = np.where(ok, np.abs(fits.contrast[rows]), 0.0)
        ratio = contrast / cfar if cfar > 0 else np.zeros_like(contrast)
        across = b.start + fits.position[rows]
        use = ok & (ratio >= opts.resolved_contrast)
        per[n] = (b.along, across, fits.position_se[rows], use, ratio)
        m.points[n] = int(use.sum())
        widths.append(fits.width[rows][use])
        resid.append(fits.rms_residual[rows][use] / max(cfar, 1e-9))
    few = [n for n in "ADBC" if m.points[n] < opts.min_points_per_block]
    if few:
        m.reason = "too few resolved edge points"
        m.detail = ", ".join(f"block {n}: {m.points[n]}" for n in few)
        return
    xa, xd, x_slope, x_se, x_ref = _edge_from_blocks(per["A"][:4], per["D"][:4])
    yb, yc, y_slope, y_se, y_ref = _edge_from_blocks(per["B"][:4], per["C"][:4])
    off_x, off_y = abs(abs(xa - xd) - gap_px), abs(abs(yb - yc) - gap_px)
    if off_x > opts.max_block_offset_px or off_y > opts.max_block_offset_px:
        m.reason = "the two sides of an edge disagree (not a corner, or two different edges)"
        m.detail = f"by {max(abs(xa - xd), abs(yb - yc)):.1f} px (expected {gap_px:.1f} px)"
        return
    m.x = 0.5 * (xa + xd)
    m.y = 0.5 * (yb + yc)
    m.half_offset_px = (0.5 * (xa - xd), 0.5 * (yb - yc))
    m.slopes = (x_slope, y_slope)
    m.x_se, m.y_se = x_se, y_se
    m.size_y_px = _deficit_width(per["A"], per["D"], opts.size_window_px)
    m.size_x_px = _deficit_width(per["B"], per["C"], opts.size_window_px)
    m.edge_width_px = float(np.median(np.concatenate(widths)))
    m.residual_rms = float(np.sqrt(np.mean(np.concatenate(resid) ** 2)))
    m.ok = bool(np.isfinite(m.size_x_px) and np.isfinite(m.size_y_px))
    if not m.ok:
        m.reason = "corner size undefined (edge contrast never reaches half)"
        return
