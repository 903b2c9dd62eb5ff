"""Where the main lens's mechanical vignetting starts, from the micro-images of a white image.

A micro-image is the main aperture seen through its microlens: a disc, the same size
everywhere (f-number matching, OPTICS.md §1). Far from the axis a real main lens
vignets: a rim other than the aperture stop (a lens barrel, a front or rear element)
cuts the oblique beams, and the micro-images there become "cat's eyes", the disc cut by
the image of that rim. Such a disc is no longer centred on the projection of the
main-lens centre through its lens: its centroid moves by about the cut area's fraction
times the disc radius (a cut of 0.1 % of a 26 px disc: 0.03 px), which grows with the
distance from the axis and so reads as a wrong lattice pitch, i.e. a wrong ``(L+b)/L``
and ``b``; inside it the pixels see a clipped microlens aperture, so the shading and the
defocus kernels there are not those of the rest of the sensor.

The vignetting of a lens centred on the axis grows with the distance from the axis and
is zero on it. :func:`vignetting_onset` compares each micro-image's lit area (the sum of
its normalised, clipped intensity, :mod:`calibration.mla_centroids`) with the median of
the micro-images nearest the principal point (up to 64), takes that deficit's median in rings about the
principal point, and returns where the first ring loses more than
``AREA_TOLERANCE`` (or three of its standard errors). The lattice, the shading and
the plateau are measured inside that radius only (:mod:`calibration.mla_grid`,
:mod:`calibration.shading`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

AREA_TOLERANCE = 2e-3
"""A ring of micro-images is vignetted when it has lost this fraction of its lit area (its
median micro-image; a cut of 0.2 % moves a disc's centroid by ~0.05 px at 23 px radius,
and only the first ring's: the pitch moves by a few 1e-6). Below that the deficit is
hard to tell from the scatter of a Monte-Carlo white image's areas (sd 0.17 % per
micro-image, ring medians within ±0.1 % of the centre's without vignetting)."""

RING_PITCHES = 2.0
"""Width of the rings the area deficit is averaged over (micro-image pitches)."""

REFERENCE_MICRO_IMAGES = 64
"""The micro-images nearest the principal point whose median area is the unvignetted one
(at most this many, and at most ``REFERENCE_FRACTION`` of them, at least
``MIN_REFERENCE_MICRO_IMAGES``: in a narrow window 64 reach far from the axis)."""

REFERENCE_FRACTION = 0.1
MIN_REFERENCE_MICRO_IMAGES = 9

MIN_RING_MICRO_IMAGES = 6
"""A ring with fewer micro-images is not judged (it is merged with the next)."""

MARGIN_PITCHES = 1.0
"""Micro-images this far inside the first vignetted ring are left out as well: the ring's
inner edge is only where its median deficit shows."""


def area_deficit(
    radius_px: NDArray[np.float64], area_px2: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``1 - area/reference`` of every micro-image, the reference the median area of the
    ``REFERENCE_MICRO_IMAGES`` nearest the principal point (``radius_px``: distance of each
    micro-image centre from it; NaN where the area is not finite)."""
    finite = np.isfinite(area_px2) & np.isfinite(radius_px)
    out = np.full(area_px2.shape, np.nan)
    if not finite.any():
        return out
    order = np.argsort(np.where(finite, radius_px, np.inf))[: _reference_count(int(finite.sum()))]
    reference = float(np.median(area_px2[order]))
    if not reference > 0:
        return out
    out[finite] = 1.0 - area_px2[finite] / reference
    return out


def _reference_count(n: int) -> int:
    """How many of ``n`` micro-images (nearest the principal point) are the reference."""
    wanted = min(REFERENCE_MICRO_IMAGES, int(REFERENCE_FRACTION * n))
    return min(n, max(MIN_REFERENCE_MICRO_IMAGES, wanted))


def vignetting_onset(
    radius_px: NDArray[np.float64],
    area_px2: NDArray[np.float64],
    pitch_px: float,
    *,
    tolerance: float = AREA_TOLERANCE,
) -> float:
    """The distance from the principal point (px) beyond which the micro-images are cut
    by the main lens's vignetting (``inf``: nowhere on the sensor), less
    ``MARGIN_PITCHES``.

    ``radius_px``: each micro-image centre's distance from the principal point;
    ``area_px2``: its lit area (any consistent measure); ``pitch_px``: the micro-image
    pitch. Rings ``RING_PITCHES`` wide, outwards from the reference micro-images; the
    first whose median deficit exceeds that of every micro-image inside it by
    ``max(tolerance, 3·standard error)`` is vignetted. The cut grows from zero inside
    that ring: the onset is where the line through its and the next ring's excess
    deficits (against their median radii) reaches zero, if that lies further in.
    """
    deficit = area_deficit(radius_px, area_px2)
    ok = np.isfinite(deficit)
    n_reference = _reference_count(int(ok.sum()))
    if ok.sum() < n_reference + MIN_RING_MICRO_IMAGES:
        return math.inf
    r, d = radius_px[ok], deficit[ok]
    order = np.argsort(r)
    r, d = r[order], d[order]
    rings = _rings(r, float(r[n_reference - 1]), RING_PITCHES * pitch_px)
    for k, (inner, outer) in enumerate(rings):
        excess, se, centre = _excess(r, d, inner, outer)
        if excess <= max(tolerance, 3.0 * se):
            continue
        onset = inner
        if k + 1 < len(rings):
            nxt, _, nxt_centre = _excess(r, d, *rings[k + 1])
            if nxt > excess and nxt_centre > centre:
                onset = min(onset, centre - excess * (nxt_centre - centre) / (nxt - excess))
        return max(0.0, onset - MARGIN_PITCHES * pitch_px)
    return math.inf


def _rings(r: NDArray[np.float64], start: float, width: float) -> list[tuple[float, float]]:
    """``(inner, outer]`` radii of rings ``width`` wide from ``start`` outwards, each widened
    until it holds ``MIN_RING_MICRO_IMAGES`` (``r`` sorted)."""
    rings, edge = [], start
    while edge < r[-1]:
        outer = edge + width
        while np.sum((r > edge) & (r <= outer)) < MIN_RING_MICRO_IMAGES and outer < r[-1]:
            outer += width
        if np.sum((r > edge) & (r <= outer)) < MIN_RING_MICRO_IMAGES:
            break
        rings.append((edge, outer))
        edge = outer
    return rings


def _excess(
    r: NDArray[np.float64], d: NDArray[np.float64], inner: float, outer: float
) -> tuple[float, float, float]:
    """The ring's median deficit over that of every micro-image inside it, the standard
    error of that difference (of two medians), and the ring's median radius."""
    ring, inside = d[(r > inner) & (r <= outer)], d[r <= inner]

    def median_se(v: NDArray[np.float64]) -> float:
        return 1.2533 * float(np.std(v, ddof=1) / np.sqrt(v.size)) if v.size > 1 else 0.0

    se = float(np.hypot(median_se(ring), median_se(inside)))
    centre = float(np.median(r[(r > inner) & (r <= outer)]))
    return float(np.median(ring) - np.median(inside)), se, centre
