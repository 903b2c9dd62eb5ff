"""An edge's slope from all of a frame's profiles across it, not from a few micro-images.

The corner lattice (:mod:`calibration.edge_profiles`) places every profile across an
edge at ``x = s + slope·t``: ``s`` the corner's image in the profile's micro-image,
``t`` the profile's distance along the edge from it (its *along-lever*, up to about a
hundred pixels: the half-edges run on through many micro-images). Each micro-image's
own edge fit gives the slope only to about 1e-3 on a noisy frame (its edge is a few
tens of pixels long), and the lattice takes the median of a few of them, so a profile
a hundred pixels along the edge lands up to ~0.1 px off: a placement error that
grows with the along-lever, which the pooled edge spread takes as extra width, frame
by frame (larger on the blurrier, noisier frames) and which the defocus model does not
describe.

:func:`refine_slope` measures the slope's error from the profiles themselves: with
the pooled function ``E`` of the profiles as placed (a least-squares cubic spline, too
stiff to follow one micro-image's samples), a slope error ``ε`` changes each sample by
``-E'(x)·sign·ε·t`` to first order: a linear least-squares problem in ``ε``, with a
common shift of each half-edge, over every sample near the edge; the correction is
applied and the pooled function rebuilt, twice. Its standard error takes each
micro-image's profiles as one cluster (on sharp, pixel-locked edges they err together),
and :meth:`SlopeCorrection.combined` weighs it against the lattice's median by inverse
variances. Positions in pixels, values in any linear unit (each block's profiles are
normalised by their own dark and light ends, medians over the block).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from .cluster_robust import clustered_meat

POOL_KNOT_PX = 0.5
"""Knot spacing of the pooled function's spline (pixels)."""

SPLINE_LATTICE = 20
"""Bins per knot spacing in which the samples are summed before the spline is fitted."""

REFINE_ROUNDS = 2
"""Rounds of estimate, correct and rebuild the pooled function (each rebuilt function is
sharper; a third round moves the slope by 0.03-0.2 of its standard error). Always all of
them: a stop on a threshold would make the result depend on the last bits of the
arithmetic (a worker process and the station's own differ in their BLAS threads)."""

FIT_HALF_PX = 3.5
"""Only samples within this distance of the predicted edge are fitted (pixels)."""

MIN_PROFILES = 20
"""Fewer profiles than this keep the lattice's slope (nothing to pool)."""

PROFILE_CONTRAST_TOLERANCE = 0.5
"""A profile's own contrast may differ from its block's by this fraction."""

MIN_CONTRAST = 0.2
"""Blocks whose contrast is below this fraction of the frame's median have no edge to
measure and are left out."""


@dataclass(frozen=True)
class SlopeCorrection:
    """The slope's correction ``delta`` (dimensionless, added to the lattice's slope) and
    its standard error ``se``; ``delta = 0, se = nan`` when it was not measured."""

    delta: float
    se: float

    def combined(self, lattice_var: float) -> tuple[float, float]:
        """The correction weighed against the lattice's own slope (variance
        ``lattice_var``, inf when unknown) by inverse variances, and its variance."""
        if not (np.isfinite(self.se) and self.se > 0):
            return 0.0, float(lattice_var)
        var = self.se**2
        if not np.isfinite(lattice_var):
            return self.delta, var
        weight = lattice_var / (lattice_var + var)
        return weight * self.delta, weight * var


def refine_slope(
    x: NDArray[np.float64],
    values: NDArray[np.float64],
    along_px: NDArray[np.float64],
    sign: NDArray[np.float64],
    block: NDArray[np.int64],
    half: NDArray[np.int64],
    *,
    ends: int = 3,
) -> SlopeCorrection:
    """The error of the slope the profiles were placed with.

    ``x``: each sample's signed distance from the predicted edge (``(P, K)``, dark side
    negative), ``values`` its value; ``along_px``: each profile's distance along the
    edge from its micro-image's corner image (``P``); ``sign``: the sign that made the
    dark side negative (``x = sign·(column - edge)``); ``block``: the profile's block
    (micro-image and half-edge), whose ``ends`` outer samples on each side set its
    dark and light levels; ``half``: 0 before the corner along the edge, 1 after (each
    half's common shift is fitted with the slope). Returns the correction to add to the
    slope (the edge lies at ``s + (slope + delta)·t``) and its block-clustered standard
    error.
    """
    n_prof = x.shape[0]
    if n_prof < MIN_PROFILES or np.ptp(along_px) <= 0:
        return SlopeCorrection(0.0, float("nan"))
    norm, contrast = _normalised(values, sign, block, ends)
    # a profile weighs its block's contrast squared (the pooled edge spread's weights): a
    # block without an edge (a dark gap, an unlit or unrendered part of the frame) none
    typical = typical_contrast(contrast)
    ok = np.isfinite(norm).all(axis=1) & (np.abs(contrast) > MIN_CONTRAST * typical)
    if ok.sum() < MIN_PROFILES or not typical > 0:
        return SlopeCorrection(0.0, float("nan"))
    # the samples near the edge, flattened: the flat ends say nothing of its position
    near = np.abs(x) <= FIT_HALF_PX
    near &= ok[:, None]
    rows = np.nonzero(near)[0]
    x_near, v_near = x[near], norm[near]
    t = (sign * along_px)[rows]
    _, cluster = np.unique(block[rows], return_inverse=True)
    root_w = np.abs(contrast[rows]) / typical  # square root of each sample's weight
    halves = [h for h in (0, 1) if np.any(half[rows] == h)]
    # each half-edge's common shift (the two halves of the reference corner's edges are
    # apart by its gap, whose imaged size the lattice knows only so well) and the slope
    indicator = [(half[rows] == h).astype(np.float64) for h in halves]
    total = 0.0
    for _ in range(REFINE_ROUNDS):
        # placed with slope + total: x moves by -sign·total·t
        pooled, slope_of_pooled = _pooled(x_near - total * t, v_near, root_w**2)
        if not np.all(np.isfinite(pooled)):
            return SlopeCorrection(0.0, float("nan"))
        resid = (v_near - pooled) * root_w
        scaled = -slope_of_pooled * root_w
        design = np.stack([scaled * ind for ind in indicator] + [scaled * t], axis=1)
        normal = design.T @ design
        try:
            inverse = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            return SlopeCorrection(0.0, float("nan"))
        coef = inverse @ (design.T @ resid)
        total += float(coef[-1])
    se = _cluster_se(design, resid - design @ coef, inverse, cluster)
    return SlopeCorrection(total, se)


def _cluster_se(
    design: NDArray[np.float64],
    resid: NDArray[np.float64],
    inverse: NDArray[np.float64],
    cluster: NDArray[np.int64],
) -> float:
    """The slope's standard error with each block's samples as one cluster (sandwich).

    A block's profiles share its micro-image's errors: on a sharp, point-sampled edge
    each micro-image's edge is locked to the pixel grid, so its profiles move together
    by up to a few tenths of a pixel, which samples taken as independent would hide.
    """
    meat = clustered_meat(design * resid[:, None], cluster, parameters_lost=design.shape[1])
    var = float((inverse @ meat @ inverse)[-1, -1])
    return float(np.sqrt(var)) if var > 0 else float("nan")


def typical_contrast(contrast: NDArray[np.float64]) -> float:
    """The contrast of the profiles that cross an edge: the median of those above
    :data:`MIN_CONTRAST` of the 95th percentile of ``|contrast|`` (0 without any).

    Not the median of all: where most of an edge's profiles lie in a part of the frame
    that shows no edge (unlit, or outside the window a renderer drew), that median is the
    noise's, or exactly 0 on a dark level without read noise, and every block would pass
    a threshold set by it."""
    magnitude = np.abs(contrast[np.isfinite(contrast)])
    if magnitude.size == 0:
        return 0.0
    high = float(np.percentile(magnitude, 95))
    edged = magnitude[magnitude > MIN_CONTRAST * high]
    return float(np.median(edged)) if edged.size else 0.0


def _normalised(
    values: NDArray[np.float64], sign: NDArray[np.float64], block: NDArray[np.int64], ends: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each block's profiles scaled to 0 (dark end) .. 1 (light end), and each profile's
    block contrast (light - dark); the samples run along the image axis, so the dark end
    is the first when ``sign > 0``."""
    _, group = np.unique(block, return_inverse=True)
    first, last = values[:, :ends].mean(axis=1), values[:, -ends:].mean(axis=1)
    dark_end = np.where(sign > 0, first, last)
    light_end = np.where(sign > 0, last, first)
    # medians: a block partly outside what the frame shows keeps the levels of its edge
    dark, light = _group_median(dark_end, group), _group_median(light_end, group)
    contrast = light - dark
    with np.errstate(divide="ignore", invalid="ignore"):
        out = (values - dark[group][:, None]) / contrast[group][:, None]
        # a profile whose own ends disagree with its block's (a row or column the frame
        # does not show, a defect) is no edge of that block
        own = (light_end - dark_end) / contrast[group]
    bad = ~(np.abs(contrast[group]) > 0) | ~(np.abs(own - 1.0) <= PROFILE_CONTRAST_TOLERANCE)
    out[bad] = np.nan
    return np.asarray(out, dtype=np.float64), np.asarray(contrast[group], dtype=np.float64)


def _group_median(values: NDArray[np.float64], group: NDArray[np.int64]) -> NDArray[np.float64]:
    """The median of ``values`` in each group ``0..G-1`` (the mean of the middle two of an
    even count)."""
    order = np.lexsort((values, group))
    counts = np.bincount(group)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ranked = values[order]
    low = ranked[starts + (counts - 1) // 2]
    high = ranked[starts + counts // 2]
    return np.asarray(0.5 * (low + high), dtype=np.float64)


def _bspline_basis(
    u: NDArray[np.float64], n_coef: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Uniform cubic B-spline design at positions ``u`` (in knot spacings from the first
    knot): the values' and the derivatives' (per knot spacing) matrices, ``(len(u), n_coef)``."""
    cell = np.clip(np.floor(u).astype(np.int64), 0, n_coef - 4)
    f = u - cell
    value = (
        np.stack(
            [(1 - f) ** 3, 3 * f**3 - 6 * f**2 + 4, -3 * f**3 + 3 * f**2 + 3 * f + 1, f**3], axis=1
        )
        / 6.0
    )
    slope = np.stack(
        [-0.5 * (1 - f) ** 2, 1.5 * f**2 - 2 * f, -1.5 * f**2 + f + 0.5, 0.5 * f**2], axis=1
    )
    rows = np.arange(u.size)[:, None]
    columns = cell[:, None] + np.arange(4)[None, :]
    design, design_slope = np.zeros((u.size, n_coef)), np.zeros((u.size, n_coef))
    design[rows, columns] = value
    design_slope[rows, columns] = slope
    return design, design_slope


@lru_cache(maxsize=64)
def _lattice_basis(n_fine: int, n_coef: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The spline's design on the uniform lattice of :data:`SPLINE_LATTICE` points per knot
    spacing (``n_fine + 2`` points; shared, read-only)."""
    at, slope_at = _bspline_basis(np.arange(n_fine + 2) / SPLINE_LATTICE, n_coef)
    at.flags.writeable = False
    slope_at.flags.writeable = False
    return at, slope_at


@lru_cache(maxsize=64)
def _curvature_penalty(n_coef: int) -> NDArray[np.float64]:
    """``DᵀD`` of the coefficients' second differences (shared, read-only)."""
    second = np.diff(np.eye(n_coef), 2, axis=0)
    penalty = second.T @ second
    penalty.flags.writeable = False
    return penalty


def _pooled(
    x: NDArray[np.float64], value: NDArray[np.float64], weight: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(Flat arrays of samples.) The pooled function, a weighted least-squares uniform
    cubic B-spline with knots every :data:`POOL_KNOT_PX` (too stiff to follow one block's
    samples, so a block's misplacement stays in its residuals), and its derivative at
    every sample. The samples are first summed in bins of a twentieth of the knot spacing
    (at their mean positions) and the spline is read off a lattice of that spacing by
    linear interpolation: exact to ~1e-4 of the contrast, and a fraction of the cost."""
    h = POOL_KNOT_PX
    lo = float(x.min())
    u = (x - lo) / h
    n_coef = int(np.ceil(float(u.max()))) + 3
    fine = np.floor(u * SPLINE_LATTICE).astype(np.int64)
    n_fine = int(fine.max()) + 1
    sum_w = np.bincount(fine, weight, minlength=n_fine)
    filled = sum_w > 0
    mean_u = np.bincount(fine, weight * u, minlength=n_fine)[filled] / sum_w[filled]
    mean_v = np.bincount(fine, weight * value, minlength=n_fine)[filled] / sum_w[filled]
    design, _ = _bspline_basis(mean_u, n_coef)
    weighted = design * sum_w[filled][:, None]
    normal = design.T @ weighted
    # a faint curvature penalty keeps knots without samples (the function's flat ends) tied
    normal += 1e-6 * float(np.trace(normal)) / n_coef * _curvature_penalty(n_coef)
    try:
        coef = np.linalg.solve(normal, weighted.T @ mean_v)
    except np.linalg.LinAlgError:
        return np.full_like(x, np.nan), np.zeros_like(x)
    at, slope_at = _lattice_basis(n_fine, n_coef)
    on_lattice, slope_on_lattice = at @ coef, slope_at @ coef
    frac = u * SPLINE_LATTICE - fine  # linear interpolation on the uniform lattice
    fitted = on_lattice[fine] + frac * (on_lattice[fine + 1] - on_lattice[fine])
    slope = slope_on_lattice[fine] + frac * (slope_on_lattice[fine + 1] - slope_on_lattice[fine])
    return fitted, slope / h
