"""Each half-edge's profiles centred on its own edge before a frame's profiles are pooled.

The corner lattice places every profile at its signed distance from the edge, dark side
negative (:mod:`calibration.edge_profiles`). An error of the lattice's offset ``c`` moves
the two halves of an edge by opposite amounts in that distance: the dark side is on
opposite sides of the edge above and below the corner (left and right of it). An error
of the reference corner's gap does the same. So the four half-edges of one frame are
copies of the edge spread moved apart by their own placement errors, common to every
profile of a half-edge: pooled, a blur that no later shift of the whole function undoes.
The lattice's covariance gives the spread such errors have on average, but a frame
carries one draw of them, and on sharp, point-sampled edges not even a random one: the
corners the lattice is fitted to lock to the pixel grid, so its offset errs by 0.02-0.14
px, the same way over neighbouring frames, where its covariance expected 0.05 px. The
defocus fit then read that spread as blur (a point-sampled Monte-Carlo sweep: the focus
plane 1.6 mm, 3.8σ, off; frames near focus described 5-100 times worse than their noise).

Each half-edge's own pooled profiles (hundreds, at every sub-pixel phase) locate its edge
far better: the centroid of its line spread, which for the symmetric blur of the model
(:mod:`calibration.defocus`) is the edge. :func:`centre_half_edges` moves each half-edge
onto it. What stays of the placement error is what varies within a half-edge (the
lattice's scale and the edge's slope, :meth:`calibration.placement_error.PlacementError.jitter_px`
with the half-edges as groups) and the centroids' own statistical errors
(:attr:`HalfEdgeCentres.spread_px2`). Positions in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .edge_bins import bin_means
from .edge_window import ESF_HALF_PX

CENTRE_BIN_PX = 0.05
"""Bin width (px) of a half-edge's pooled function, whose line spread's centroid is taken."""

CENTRE_ROUNDS = 3
"""Centroids taken in turn, each in a window about the last (the samples binned about
it): a window off the edge cuts the line spread unevenly and pulls the centroid toward
the window's centre."""


@dataclass(frozen=True)
class HalfEdgeCentres:
    """Per profile (rows of the samples): ``shift_px``, where its half-edge's edge lies in
    the lattice's placement (subtract it from the positions), and ``kept``, whether its
    half-edge could be centred (enough profiles, a line spread in the window);
    ``spread_px2``: the expected weighted spread (px²) the centroids' errors leave
    between the half-edges, about their common shift."""

    shift_px: NDArray[np.float64]
    kept: NDArray[np.bool_]
    spread_px2: float


def lsf_centroid(
    x: NDArray[np.float64],
    value: NDArray[np.float64],
    *,
    half_window_px: float,
    se: NDArray[np.float64] | None = None,
) -> tuple[float, float]:
    """Centroid (px) of the line spread of a sampled edge-spread function within
    ``±half_window_px``, and its standard error from the values' ``se`` (0 without).

    ``x`` ascending, ``value`` 0 dark and 1 light. With the levels ``lo`` and ``hi`` the
    means of the points beyond each end of the window (the end points themselves when
    none lie beyond), the edge is ``t = x_last - ∫(E - lo)dx/(hi - lo)`` over the points in
    the window (trapezoids): exact for a step, and for any blur symmetric about ``t``
    whose tails are symmetric too, and the levels averaged over the tails rather than
    read off one point each (which would move ``t`` by the window's half-width times
    their noise). NaN when fewer than 10 points lie in the window or the function does
    not rise across it.
    """
    inside = np.abs(x) <= half_window_px
    if inside.sum() < 10:
        return float("nan"), float("nan")
    index = np.flatnonzero(inside)
    below = np.flatnonzero(x < -half_window_px)
    above = np.flatnonzero(x > half_window_px)
    below = below if below.size else index[:1]
    above = above if above.size else index[-1:]
    lo, hi = float(np.mean(value[below])), float(np.mean(value[above]))
    rise = hi - lo
    if not rise > 0:
        return float("nan"), float("nan")
    xs, e = x[index], value[index]
    dx = np.diff(xs)
    d_area = 0.5 * (np.concatenate([[0.0], dx]) + np.concatenate([dx, [0.0]]))
    area = float(np.sum(d_area * (e - lo)))
    span = float(xs[-1] - xs[0])
    centre = float(xs[-1]) - area / rise
    if se is None:
        return centre, 0.0
    # linearised in the values: the window's points through the area, the tails' through
    # the levels (each level the mean of its points)
    gradient = np.zeros(x.size)
    gradient[index] = -d_area / rise
    gradient[below] += (span / rise - area / rise**2) / below.size
    gradient[above] += (area / rise**2) / above.size
    return centre, float(np.sqrt(np.sum((gradient * se) ** 2)))


def centre_half_edges(
    x: NDArray[np.float64],
    value: NDArray[np.float64],
    weight: NDArray[np.float64],
    half_edge: NDArray[np.int64],
    *,
    usable: NDArray[np.bool_],
    half_window_px: float,
    min_profiles: int,
) -> HalfEdgeCentres:
    """Where each half-edge's edge lies among its profiles' samples.

    ``x``, ``value``, ``weight``: the profiles' samples (rows), their signed distances from
    the lattice's edge (px), normalised values (0 dark, 1 light) and weights;
    ``half_edge``: each profile's half-edge label; ``usable``: the profiles to pool.
    Each half-edge with at least ``min_profiles`` usable profiles is centred on the
    centroid of its pooled line spread within ``±half_window_px`` (the blur's reach),
    ``CENTRE_ROUNDS`` times, each about the last; the others are not kept. The centroids'
    standard errors give ``spread_px2`` with the half-edges weighted by their profiles'
    summed weights.
    """
    rows = x.shape[0]
    shift = np.zeros(rows)
    kept = np.zeros(rows, dtype=np.bool_)
    group_weight: list[float] = []
    group_var: list[float] = []
    for label in np.unique(half_edge):
        member = half_edge == label
        sel = member & usable
        if sel.sum() < min_profiles:
            continue
        xs, vs, ws = x[sel].ravel(), value[sel].ravel(), weight[sel].ravel()
        centre, se = 0.0, float("nan")
        for _ in range(CENTRE_ROUNDS):
            bins = bin_means(xs - centre, vs, ws, bin_px=CENTRE_BIN_PX, half_px=ESF_HALF_PX)
            step, se = lsf_centroid(bins.x, bins.value, half_window_px=half_window_px, se=bins.se)
            if not np.isfinite(step):
                break
            centre += step
        if not (np.isfinite(step) and np.isfinite(se)):
            continue
        shift[member] = centre
        kept[member] = True
        group_weight.append(float(np.sum(ws)))
        group_var.append(se**2)
    spread = 0.0
    if group_weight:
        w = np.asarray(group_weight) / float(np.sum(group_weight))
        var = np.asarray(group_var)
        # E[Σ w_h ε_h² - (Σ w_h ε_h)²] for independent centroid errors ε_h
        spread = float(np.sum(w * var) - np.sum(w**2 * var))
    return HalfEdgeCentres(shift, kept, spread)
