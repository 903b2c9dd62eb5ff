"""The fully lit plateau of the micro-images of a white image, and the fall beyond it.

A pixel sees its whole microlens aperture only while the aperture's footprint on the main
lens fits inside the main aperture; beyond that radius the white image falls off, and a
defocused edge there is blurred by a clipped aperture (a smaller, lopsided kernel). For
f-number-matched optics that radius is about ``1 - √2·(Q0 - b/L)`` of the half pitch for
square lenses, 0.6-0.8 for the cameras of the benchmarks; the edge spread
(:mod:`calibration.edge_spread`) uses only profiles inside it (:func:`measure_plateau`).
Beyond it the white's fall is measured ring by ring (:meth:`WhiteRings.bowl`): the flat
field (:mod:`calibration.flat_field`) divides a corner's profiles by it where they reach
past the plateau.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid
from .white_samples import micro_image_samples, per_image_fit

PLATEAU_INNER_FRACTION = 0.45
"""The part of a micro-image (fraction of half its pitch) taken as lit for certain: the
smooth shading fitted there is extrapolated outwards to find where the plateau ends."""

PLATEAU_MAX_FRACTION = 0.95
"""The plateau is searched out to this fraction of half the micro-image pitch."""

PLATEAU_TOLERANCE = 1e-3
"""The plateau ends where the white image falls this far (relative) below its smooth
shading: an aperture clipped by 0.1 % changes a defocus kernel's variance by ~0.3 %
in the few profiles that reach there."""

PLATEAU_BIN_PX = 0.5
"""Radial bin of the plateau search (pixels)."""

RADIAL_MIN_PIXELS = 100
"""Fewest white-image pixels a ring of the radial shading profile needs (a ring of 0.5 px
holds ~1-2 pixels per micro-image near the centre, ~50 at 16 px: the profile is noisy
only where its slope is small)."""

RADIAL_LIT_FRACTION = 0.9
"""A ring of the radial profile must have at least this fraction of its area measured."""

RADIAL_CENTRE_PX = 2.0
"""The radial profile's first bin is the disc of about this radius (px) about the centres."""

PLATEAU_MAX_MICRO_IMAGES = 200
"""The plateau is measured on at most this many micro-images (evenly spread): a 0.5 px
ring of 200 micro-images of 20 px radius holds ~12 000 pixels, enough to see 1e-3."""


def measure_plateau(
    white: NDArray[Any],
    image_grid: LensGrid,
    *,
    background: float = 0.0,
    unvignetted: tuple[tuple[float, float], float] | None = None,
) -> float:
    """Radius where the micro-images of a white image stop being fully lit (fraction of
    half the micro-image pitch; NaN when it cannot be measured).

    Each micro-image's ``log W`` is fitted with a level, a gradient and a
    curvature inside ``PLATEAU_INNER_FRACTION``; the ratio of the image to that
    smooth shading, averaged over the micro-images in radial bins of
    ``PLATEAU_BIN_PX``, stays at 1 on the plateau. The plateau ends at the
    inner edge of the first bin whose mean falls more than ``PLATEAU_TOLERANCE``
    (or three of its standard errors, in a noisy white image) below 1;
    ``PLATEAU_MAX_FRACTION`` when none does. ``unvignetted``: as for
    :func:`measure_shading`.
    """
    rings = white_rings(white, image_grid, background, unvignetted)
    return float("nan") if rings is None else rings.plateau_fraction()


@dataclass(frozen=True)
class WhiteRings:
    """The white's pixels out to ``PLATEAU_MAX_FRACTION`` of half the pitch, in radial bins
    of ``PLATEAU_BIN_PX`` from the centre: per bin its pixel count and the sums of the
    pixels' ratio to their micro-image's inner paraboloid (and of its square), their mean
    radius and mean ``log W`` less the micro-image's level and gradient. ``half``: half the
    pitch. The first bin is the whole disc inside the second."""

    edges: NDArray[np.float64]
    count: NDArray[np.int64]
    ratio_sum: NDArray[np.float64]
    ratio_sum2: NDArray[np.float64]
    radius_mean: NDArray[np.float64]
    log_mean: NDArray[np.float64]
    half: float
    micro_images: int

    def plateau_fraction(self) -> float:
        """See :func:`measure_plateau`."""
        start = int(np.searchsorted(self.edges, PLATEAU_INNER_FRACTION * self.half - 1e-9))
        for b in range(start, self.count.size):
            if self.count[b] < 10:
                continue
            mean = self.ratio_sum[b] / self.count[b]
            var = max(0.0, self.ratio_sum2[b] / self.count[b] - mean * mean)
            se = float(np.sqrt(var / self.count[b]))
            if float(mean) < 1.0 - max(PLATEAU_TOLERANCE, 3.0 * se):
                return float(self.edges[b] / self.half)
        return PLATEAU_MAX_FRACTION

    def bowl(self, curvature_px2: float, plateau_px: float) -> tuple[tuple[float, ...], ...]:
        """``(radii, log W)`` of the flat field's bowl: the paraboloid of ``curvature_px2``
        (px⁻², fitted to every pixel of the plateau, so less noisy than its rings) out to
        ``plateau_px``, and beyond it the rings' measured fall (:meth:`radial_profile`)
        continuing from there; empty (the paraboloid everywhere) when the rings do not
        reach beyond the plateau or either is not measured."""
        radii, logs = self.radial_profile()
        if not (radii and np.isfinite(curvature_px2) and np.isfinite(plateau_px)):
            return (), ()
        if radii[-1] <= plateau_px:
            return (), ()
        ring_r, ring_log = np.array(radii), np.array(logs)
        on = (ring_r > 0) & (ring_r <= plateau_px)
        r = np.concatenate([[0.0], ring_r[on], [plateau_px], ring_r[ring_r > plateau_px]])
        fall = np.interp(r, ring_r, ring_log) - np.interp(plateau_px, ring_r, ring_log)
        paraboloid = -0.5 * curvature_px2 * r * r
        bowl = np.where(r <= plateau_px, paraboloid, -0.5 * curvature_px2 * plateau_px**2 + fall)
        return tuple(float(v) for v in r), tuple(float(v) for v in bowl)

    def radial_profile(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """``(radii, log W)``: the micro-images' mean ``log W`` (level and gradient removed,
        the centre's value subtracted) at the mean radius of each ring of at least
        ``RADIAL_MIN_PIXELS`` pixels, out to the first ring with fewer or with more than
        ``1 - RADIAL_LIT_FRACTION`` of its area too dark to measure (the rim: a mean over its
        brighter pixels only would be biased); empty when fewer than two rings qualify."""
        area = np.pi * np.diff(self.edges**2) * self.micro_images
        full = (self.count >= RADIAL_MIN_PIXELS) & (self.count >= RADIAL_LIT_FRACTION * area)
        n = int(np.argmin(full)) if not full.all() else full.size
        if n < 2:
            return (), ()
        log_w = self.log_mean[:n] - self.log_mean[0]
        return tuple(float(r) for r in self.radius_mean[:n]), tuple(float(v) for v in log_w)


def white_rings(
    white: NDArray[Any],
    image_grid: LensGrid,
    background: float,
    unvignetted: tuple[tuple[float, float], float] | None,
) -> WhiteRings | None:
    """:class:`WhiteRings` of up to ``PLATEAU_MAX_MICRO_IMAGES`` micro-images (None: none lit)."""
    samples = micro_image_samples(
        white,
        image_grid,
        background,
        PLATEAU_MAX_FRACTION,
        max_images=PLATEAU_MAX_MICRO_IMAGES,
        unvignetted=unvignetted,
    )
    if samples is None:
        return None
    dx, dy, good = samples.dx, samples.dy, samples.good
    half = 0.5 * image_grid.pitch_px
    rr = dx * dx + dy * dy
    inner = good & (rr <= (PLATEAU_INNER_FRACTION * half) ** 2)
    logv = samples.log_values()
    regs = [np.ones_like(dx), dx, dy, rr]
    n = samples.n_images
    coef, _ = per_image_fit(logv, regs, inner)
    full = np.stack([r.reshape(n, -1) for r in regs], axis=2)
    ratio = np.exp(logv.reshape(n, -1) - (full @ coef)[:, :, 0])
    # log W less the level and gradient only: the bowl itself
    bowl = logv.reshape(n, -1) - (full[:, :, :3] @ coef[:, :3])[:, :, 0]
    use = good.reshape(n, -1)
    # the bins' edges fall on PLATEAU_INNER_FRACTION of the half pitch; the first is the disc
    first = PLATEAU_INNER_FRACTION * half % PLATEAU_BIN_PX
    edges = np.arange(first, PLATEAU_MAX_FRACTION * half, PLATEAU_BIN_PX)
    edges = np.concatenate([[0.0], edges[edges >= RADIAL_CENTRE_PX]])
    radius = np.sqrt(rr).reshape(n, -1)[use]
    which = np.digitize(radius, edges) - 1
    inside = (which >= 0) & (which < edges.size - 1)
    which = which[inside]
    vals, logs = ratio[use][inside], bowl[use][inside]
    bins = edges.size - 1
    count = np.bincount(which, minlength=bins)

    def per_bin(weights: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(np.bincount(which, weights=weights, minlength=bins), dtype=np.float64)

    per_pixel = 1.0 / np.maximum(count, 1)
    return WhiteRings(
        edges=edges,
        count=count,
        ratio_sum=per_bin(vals),
        ratio_sum2=per_bin(vals * vals),
        radius_mean=per_bin(radius[inside]) * per_pixel,
        log_mean=per_bin(logs) * per_pixel,
        half=half,
        micro_images=n,
    )
