"""Edge profiles of a board corner's four half-edges, in every micro-image that shows them.

A corner's disparity fit (:mod:`calibration.frame_analysis`) gives its lattice:
in the micro-image of lens ``m`` the corner is imaged at ``s = (1+Q)·m + c``
(OPTICS.md §1, sensor pixels), whether or not that point lies inside the
micro-image. The board's edges through the corner are straight lines through
that point, so the lattice predicts where every micro-image shows them: the
vertical edge (board ``X`` constant) at ``x = s_x + slope·(y - s_y)``, the
horizontal one at ``y = s_y + slope·(x - s_x)``, the two halves of each apart by
the reference corner's gap (``±Cr/2`` imaged; none for the standard corner).

This module cuts a profile of ``2·h + 1`` samples across an edge at every
pixel row (vertical edge) or column (horizontal edge) of every micro-image
where the whole profile lies in the fully lit plateau (:mod:`calibration.shading`,
where the defocus kernel is the whole microlens aperture), at least a clearance
from the corner (the other edge does not reach into it) and no farther along
the edge than ``reach`` (short of the next corner of the board). That is many
more micro-images than those in which the corner itself can be measured: the
half-edges run on through the micro-images next to them.

Samples are placed at their signed distance from the predicted edge (dark
side negative). Placing them by the lattice, not by a fit in each micro-image,
matters when edges are sharp and sampled by few points per pixel: one
micro-image then locates its edge only to the sample spacing (it locks to the
pixel grid), the lattice averages that over every micro-image of the corner.
Each profile also carries its half-edge: the lattice's offset moves the two
halves of an edge by opposite amounts, so the pooled function centres each
half-edge on its own edge (:mod:`calibration.edge_centres`). The prediction's
error, from the fit's covariance, is returned as the RMS
placement jitter the defocus model convolves with, with and without the part
of the lattice's scale ``1+Q``: one frame measures its scale only to ~1e-3 on
a sharp, point-sampled corner, which moves a profile by the scale error times
its lens's distance from the others (its lever, up to ~100 px), so every
profile carries its lever and the sweep can place them again with a scale
smoothed over all frames (:meth:`calibration.edge_spread.BinnedEsf.replaced`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from .aperture_mask import ApertureMask
from .clipping import clipped_at
from .edge_slope import MIN_CONTRAST, refine_slope, typical_contrast
from .edge_spread import EdgeProfiles
from .edge_window import TAIL_SAMPLES
from .flat_field import FlatField
from .lens_grid import LensGrid
from .placement_error import PlacementError


@dataclass(frozen=True)
class CornerLattice:
    """A corner's images ``s = (1+Q)·m + c`` in sensor pixels, and its edges' geometry.

    ``coef``: ``(1+Q, c_x, c_y)``; ``covariance``: their 3×3 covariance (at the
    fit's residual scatter); ``slope_v``: ``dx/dy`` of the vertical edge,
    ``slope_h``: ``dy/dx`` of the horizontal edge (a board turned about the
    axis); ``half_px``: half the offset between the two halves of each edge
    ``(x_A - x_D, y_B - y_C)/2`` and ``half_var_px2`` its variance.
    """

    coef: tuple[float, float, float]
    covariance: NDArray[np.float64]
    slope_v: float = 0.0
    slope_h: float = 0.0
    half_px: tuple[float, float] = (0.0, 0.0)
    half_var_px2: tuple[float, float] = (0.0, 0.0)
    slope_var: tuple[float, float] = (float("inf"), float("inf"))


@dataclass(frozen=True)
class ProfileWindow:
    """Where profiles may be cut (pixels): ``plateau_px`` the radius of each
    micro-image's fully lit interior, ``clearance_px`` the least distance from
    the corner along the edge, ``reach_px`` the largest, ``half_px`` the
    profile's half length (``2·half_px + 1`` samples); ``flat_field`` the white image's
    smooth shading every sample is divided by (:class:`~calibration.flat_field.FlatField`;
    none by default); ``clip_count`` the count at which the sensor clips (its full scale):
    a half-edge with a clipped sample is left out, its edge's shape is lost (none by
    default); ``aperture_mask`` the pixels of vignetted micro-images that see their whole
    microlens aperture: a profile with a sample elsewhere in them is left out
    (:mod:`calibration.aperture_mask`; none by default)."""

    plateau_px: float
    clearance_px: float
    reach_px: float
    half_px: int = 6
    flat_field: FlatField = FlatField()
    clip_count: float = float("inf")
    aperture_mask: ApertureMask | None = None


@dataclass(frozen=True)
class PlacedProfiles:
    """Profiles and their placement error: ``placement`` per profile
    (:class:`~calibration.placement_error.PlacementError`, whose spread the pooled
    function takes with its own weights), ``jitter_px`` its RMS spread about the common
    shift over all profiles alike (px), ``jitter_fixed_scale_px`` the same with the
    lattice's scale known (its other parameters conditioned on it). Each profile's lever
    is how far it moves per unit error of the scale ``1+Q``, the offset ``c`` erring with
    it as the fit's covariance says (``δc = Σ_c,scale/Σ_scale·δ``): for the vertical edge
    ``∓(m_x - p_x)``, ``p`` the point the fit pivots about."""

    profiles: EdgeProfiles
    placement: PlacementError
    slope_corrections: tuple[float, float] = (0.0, 0.0)
    """What the profiles changed the lattice's slopes by: (vertical edge ``dx/dy``,
    horizontal edge ``dy/dx``; :mod:`calibration.edge_slope`)."""
    clipped_half_edges: int = 0
    """Half-edges (micro-image and half) left out because the sensor clipped them."""

    @property
    def jitter_px(self) -> float:
        return self.placement.jitter_px()

    @property
    def jitter_fixed_scale_px(self) -> float:
        return self.placement.jitter_px(scale_known=True)


def half_edge_profiles(
    image: NDArray[np.floating] | NDArray[np.integer],
    lattice: CornerLattice,
    lens_grid: LensGrid,
    image_grid: LensGrid,
    window: ProfileWindow,
) -> PlacedProfiles:
    """Every clean profile across the corner's four half-edges, with its lever, and the
    placement jitter (px).

    Block labels: one per micro-image and half-edge (A above the corner, D
    below, on the vertical edge; B left, C right, on the horizontal edge); half-edge
    labels ``2·edge + half`` (edge 0 vertical, 1 horizontal; half 0 before the corner,
    1 after it).
    """
    height, width = image.shape
    radius = window.plateau_px
    none = PlacedProfiles(EdgeProfiles.empty(), PlacementError.none())
    ii, jj = image_grid.indices_in(width, height, margin_px=radius + 1.0)
    if ii.size == 0:
        return none
    mx, my = lens_grid.centre(ii, jj)
    cx, cy = image_grid.centre(ii, jj)
    a, ox, oy = lattice.coef
    sx, sy = a * mx + ox, a * my + oy  # the corner's image in each micro-image
    # the placement error of a profile is linear in the lattice's errors and the halves'
    # gap: parameters (1+Q, c_x, c_y, half_x, half_y) with this covariance
    sigma = np.zeros((5, 5))
    sigma[:3, :3] = lattice.covariance
    sigma[3, 3], sigma[4, 4] = lattice.half_var_px2
    parts = []
    gradients = []
    slope_levers: list[NDArray[np.float64]] = []  # per profile, on its edge's slope
    slope_vars: list[NDArray[np.float64]] = []  # the variance of the slope it was placed with
    axes: list[NDArray[np.int64]] = []
    corrections = [0.0, 0.0]
    # the white image's shading gradient at each micro-image centre (the flat field's tilt)
    tilt = window.flat_field.gradients((cx, cy), (mx, my))
    cuts = (
        _cut(image, cx, cy, sx, sy, lattice.slope_v, lattice.half_px[0], window, False, tilt),
        _cut(image, cy, cx, sy, sx, lattice.slope_h, lattice.half_px[1], window, True, tilt[::-1]),
    )
    clipped = 0
    if np.isfinite(window.clip_count):
        cuts, clipped = _unclipped(cuts)
    for axis, cut in enumerate(cuts):  # 0: the vertical edge (row profiles), 1: the horizontal
        if cut is None:
            continue
        x, y, lens, half, sign, along = cut.x, cut.y, cut.lens, cut.half, cut.sign, cut.along
        # the edge's slope from every profile across it (the lattice's is a median of a few
        # micro-images' own: :mod:`calibration.edge_slope`)
        lever_along = sign * along
        measured = refine_slope(x, y, along, sign, lens * 2 + half, half)
        delta, var = measured.combined(lattice.slope_var[axis])
        x = x - delta * lever_along[:, None]
        corrections[axis] = delta
        slope_levers.append(lever_along)
        slope_vars.append(np.full(lens.size, var if np.isfinite(var) else 0.0))
        axes.append(np.full(lens.size, axis, dtype=np.int64))
        parts.append((x, y, lens * 4 + 2 * axis + half))
        # d(sample position)/d(parameters): x = sign·(column - edge), the edge moving with
        # m·δ(1+Q) + δc and by +δhalf before the corner, -δhalf after it
        grad = np.zeros((lens.size, 5))
        grad[:, 0] = mx[lens] if axis == 0 else my[lens]
        grad[:, 1 + axis] = 1.0
        grad[:, 3 + axis] = np.where(half == 1, -1.0, 1.0)
        gradients.append(-sign[:, None] * grad)
    if not parts:
        return PlacedProfiles(
            EdgeProfiles.empty(), PlacementError.none(), clipped_half_edges=clipped
        )
    x = np.concatenate([p[0] for p in parts])
    y = np.concatenate([p[1] for p in parts])
    label = np.concatenate([p[2] for p in parts])
    _, block = np.unique(label, return_inverse=True)
    grads = np.concatenate(gradients)
    # the lever: how a profile moves per unit error of the scale, with the offset's error
    # that comes with it in the fit (its regression on the scale's: the fit pivots about
    # the micro-images it measured)
    direction = np.zeros(5)
    direction[0] = 1.0
    if sigma[0, 0] > 0:
        direction[1:3] = sigma[1:3, 0] / sigma[0, 0]
    placement = PlacementError(
        grads,
        sigma,
        np.concatenate(slope_levers),
        np.concatenate(slope_vars),
        np.concatenate(axes),
    )
    return PlacedProfiles(
        EdgeProfiles(x, y, block.astype(np.int64), grads @ direction, label % 4),
        placement,
        (corrections[0], corrections[1]),
        clipped,
    )


class _Cut(NamedTuple):
    """One edge's profiles (see :func:`_cut`); ``clipped`` whether a profile has a sample
    the sensor clipped (:func:`~calibration.clipping.clipped_at`), ``raw_ends`` the mean
    raw counts of its first and last ``TAIL_SAMPLES``."""

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    lens: NDArray[np.int64]
    half: NDArray[np.int64]
    sign: NDArray[np.float64]
    along: NDArray[np.float64]
    clipped: NDArray[np.bool_]
    raw_ends: NDArray[np.float64]

    def subset(self, keep: NDArray[np.bool_]) -> _Cut | None:
        return _Cut._make(field[keep] for field in self) if keep.any() else None


def _cut(
    image: NDArray[np.floating] | NDArray[np.integer],
    centre_across: NDArray[np.float64],
    centre_along: NDArray[np.float64],
    corner_across: NDArray[np.float64],
    corner_along: NDArray[np.float64],
    slope: float,
    half_offset: float,
    window: ProfileWindow,
    transposed: bool,
    gradient: tuple[NDArray[np.float64], NDArray[np.float64]],
) -> _Cut | None:
    """Profiles across one edge of every micro-image (coordinates named across/along the edge).

    For the vertical edge ``across`` is x and ``along`` is y (row profiles);
    ``transposed`` swaps them for the horizontal edge. Returns the samples'
    signed distances from the edge, their values, the micro-image (index into
    the inputs), the half (0 before the corner along the edge, 1 after), the
    sign that made the dark side negative and each profile's distance along the edge
    from its micro-image's corner image, whether it has a clipped sample and its raw
    counts' ends (none when no profile can be cut).
    """
    height, width = image.shape
    r = window.plateau_px
    h = window.half_px
    offsets = np.arange(-h, h + 1, dtype=np.float64)
    span = int(np.ceil(r))
    steps = np.arange(-span, span + 1, dtype=np.float64)
    # candidate lines (along coordinate) of every micro-image
    along = np.rint(centre_along)[:, None] + steps[None, :]
    dist = along - corner_along[:, None]
    after = (dist > 0).astype(np.int64)
    # the two halves of the edge are offset by the gap: +half before the corner, -half after
    edge = corner_across[:, None] + slope * dist + np.where(after == 1, -half_offset, half_offset)
    start = np.rint(edge) - h
    lo, hi = start - centre_across[:, None], start + 2 * h - centre_across[:, None]
    dy = along - centre_along[:, None]
    far = np.maximum(lo * lo, hi * hi) + dy * dy
    limit_across = width if not transposed else height
    limit_along = height if not transposed else width
    keep = (
        (far <= r * r)
        & (np.abs(dist) >= window.clearance_px)
        & (np.abs(dist) <= window.reach_px)
        & (start >= 0)
        & (start + 2 * h <= limit_across - 1)
        & (along >= 0)
        & (along <= limit_along - 1)
    )
    lens, line = np.nonzero(keep)
    if lens.size == 0:
        return None
    across_idx = (start[lens, line][:, None] + h + offsets[None, :]).astype(np.int64)
    along_idx = np.broadcast_to(along[lens, line][:, None], across_idx.shape).astype(np.int64)
    if window.aperture_mask is not None:
        # the whole aperture seen at every sample (vignetting clips the defocus kernel)
        rows_idx, cols_idx = (across_idx, along_idx) if transposed else (along_idx, across_idx)
        whole = window.aperture_mask.at(rows_idx, cols_idx).all(axis=1)
        lens, line = lens[whole], line[whole]
        across_idx, along_idx = across_idx[whole], along_idx[whole]
        if lens.size == 0:
            return None
    if transposed:
        values = image[across_idx, along_idx]
    else:
        values = image[along_idx, across_idx]
    x = across_idx - edge[lens, line][:, None]
    values = np.asarray(values, dtype=np.float64)
    clipped = np.zeros(lens.size, dtype=bool)
    if np.any(values >= window.clip_count):  # only then look at the samples' neighbours
        rows_idx, cols_idx = (across_idx, along_idx) if transposed else (along_idx, across_idx)
        clipped = np.asarray(clipped_at(image, rows_idx, cols_idx, window.clip_count).any(axis=1))
    raw_ends = np.stack(
        [values[:, :TAIL_SAMPLES].mean(axis=1), values[:, -TAIL_SAMPLES:].mean(axis=1)], axis=1
    )
    if window.flat_field.active:
        # flat field: the white image's smooth shading about the micro-image centre
        da = across_idx - centre_across[lens][:, None]
        db = dy[lens, line][:, None]
        grad = (gradient[0][lens][:, None], gradient[1][lens][:, None])
        values = window.flat_field.divide(values, (da, db), grad)
    lens = lens.astype(np.int64)
    # dark side negative: the sign of each half-edge from its profiles' ends
    half = after[lens, line]
    key = lens * 2 + half
    rise = values[:, -3:].mean(axis=1) - values[:, :3].mean(axis=1)
    _, group = np.unique(key, return_inverse=True)
    total = np.bincount(group, rise)
    sign = np.where(total[group] >= 0, 1.0, -1.0)
    return _Cut(
        np.asarray(sign[:, None] * x, dtype=np.float64),
        values,
        lens,
        np.asarray(half, dtype=np.int64),
        np.asarray(sign, dtype=np.float64),
        np.asarray(dist[lens, line], dtype=np.float64),
        clipped,
        raw_ends,
    )


def _unclipped(
    cuts: tuple[_Cut | None, _Cut | None],
) -> tuple[tuple[_Cut | None, _Cut | None], int]:
    """The profiles of both edges that belong to a half-edge (one per micro-image, edge and
    half) the sensor's clip left whole and that shows an edge; and how many half-edges
    were clipped.

    A clipped sample flattens the edge's bright side, and the profile reads sharper (as in
    ISO 12233, a clipped edge is not measured). A half-edge goes whole when one of its
    samples is clipped (:func:`~calibration.clipping.clipped_at`: a lone defective pixel
    at full scale is not): dropping single profiles would keep, where the bright level
    is just below the clip, those whose noise fell low. Of the rest, only half-edges whose
    contrast is at least :data:`~calibration.edge_slope.MIN_CONTRAST` of the typical
    contrast of all of them, or of the clipped ones' median contrast if that is larger,
    are kept: when every edge is clipped, what is left (micro-images that show no edge,
    however many, on either edge) must not stand in for it.
    """
    present = [(axis, c) for axis, c in enumerate(cuts) if c is not None]
    if not present:
        return cuts, 0
    key = np.concatenate([c.lens * 4 + 2 * axis + c.half for axis, c in present])
    clipped_row = np.concatenate([c.clipped for _, c in present])
    ends = np.concatenate([c.raw_ends for _, c in present])
    _, group = np.unique(key, return_inverse=True)
    n_groups = int(group.max()) + 1
    clipped = np.bincount(group, clipped_row, n_groups) > 0
    if not clipped.any():
        return cuts, 0
    rows = np.bincount(group, minlength=n_groups)
    first = np.bincount(group, ends[:, 0], n_groups) / rows
    last = np.bincount(group, ends[:, 1], n_groups) / rows
    contrast = np.abs(last - first)
    # a clipped edge shows less contrast than it has: the least a real edge shows
    reference = max(typical_contrast(contrast), float(np.median(contrast[clipped])))
    keep = ((contrast >= MIN_CONTRAST * reference) & ~clipped)[group]
    kept: list[_Cut | None] = [None, None]
    start = 0
    for axis, c in present:
        kept[axis] = c.subset(keep[start : start + c.lens.size])
        start += c.lens.size
    return (kept[0], kept[1]), int(clipped.sum())
