"""How far a frame's edge profiles reach: where their flat tails start, how long they are
cut and how far from the corner they must stay, from the width of the frame's edges.

Used by :mod:`calibration.frame_analysis` (cutting the profiles) and
:mod:`calibration.edge_spread` (reading their levels off the tails). Distances in pixels.
"""

from __future__ import annotations

import numpy as np

ESF_HALF_PX = 10.0
"""Half width of the binned edge-spread function (pixels): the longest profile
(:func:`profile_half_px`)."""

FLAT_SIGMAS = 4.0
"""The tails start this many sigmas of the edge's blur (pixel included) from the edge, plus
``FLAT_MARGIN_PX``: a blur that is not Gaussian (a defocus box) reaches farther than three
of its sigmas."""

FLAT_MARGIN_PX = 0.25
"""Added to the tails' distance from the edge (px): half a sample of point-sampled pixels."""

FLAT_RANGE_PX = (2.0, 8.0)
"""Bounds of the tails' distance from the edge (px); the profile reaches 2 samples past it
(:func:`profile_half_px`)."""

TAIL_SAMPLES = 2
"""Samples of each tail beyond the flat distance (at least)."""


def flat_distance(width_px: float) -> float:
    """Distance from the edge (px) beyond which a profile is taken as flat.

    ``width_px``: the blurred-step width (Gaussian sigma before pixel integration,
    :mod:`calibration.edge_fit`) of the frame's edges; ``FLAT_SIGMAS`` of the edge's
    whole sigma (the pixel's ``1/√12`` added) plus ``FLAT_MARGIN_PX``, within
    ``FLAT_RANGE_PX``.
    """
    lo, hi = FLAT_RANGE_PX
    if not np.isfinite(width_px):
        return hi
    sigma = float(np.sqrt(width_px**2 + 1.0 / 12.0))
    return float(np.clip(FLAT_SIGMAS * sigma + FLAT_MARGIN_PX, lo, hi))


def corner_clearance_px(width_px: float, *, minimum_px: float) -> float:
    """Least distance (px) from the corner, along an edge, of a profile across it: the
    edges' :func:`flat_distance`, at least ``minimum_px``.

    The corner's other edge is blurred as this one is; within its flat distance its blur
    reaches into the profile (a defocus disk, a diffraction pattern's lobes), and its
    light is then not a level the profile's tails can take. A fixed 3 px was less than a
    diffraction-limited microlens's first zero (3.4 px at f/15.6) and than the defocus
    disk's radius of most blurred frames.
    """
    return max(minimum_px, flat_distance(width_px))


def profile_half_px(width_px: float, *, minimum: int, maximum: int) -> int:
    """Half length (samples) of the profiles cut across a frame's edges: twice
    :func:`flat_distance` of the edges' width plus ``TAIL_SAMPLES`` (tails as long as the
    blurred part), at least ``minimum`` and at most ``maximum`` (what fits in the
    micro-images' plateau) and ``ESF_HALF_PX``.

    Blurred edges get longer profiles, so that their levels come from long tails: a
    diffraction-limited microlens (first zero of its pattern 2.75 px at f/12.5 in green
    light) still has a lobe 4-6 px from the edge, and levels read from ±6 px profiles put
    ``Q0`` 0.13 % low on a Monte-Carlo sweep with that diffraction, with the renderer's
    true ``Q`` (0.01 % with ±10 px profiles). Edges with σ ≤ 0.33 px keep the minimum.
    """
    wanted = int(np.ceil(2.0 * flat_distance(width_px))) + TAIL_SAMPLES
    return int(max(minimum, min(wanted, maximum, int(ESF_HALF_PX))))
