"""The corners whose edge-spread functions the whole-sweep defocus fit uses (:mod:`calibration.defocus`).

One observation per frame, of the same corners throughout the sweep: both corners merged
in each frame when every frame has both (:func:`merge_corners`, corner ``both``), else the
corner seen in most frames (:func:`sweep_corners`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .defocus_problem import EdgeObservation
from .edge_spread import BinnedEsf

__all__ = ["merge_corners", "sweep_corners"]


def sweep_corners(observations: Sequence[EdgeObservation]) -> list[EdgeObservation]:
    """One observation per frame, of the same corners throughout the sweep: both corners'
    functions merged in every frame (:func:`merge_corners`) when every frame has both, else
    the corner with edge-spread functions in the most frames (the standard corner on a tie)
    alone, the frames without it left out.

    The two corners' functions are not the same function. The reference corner's
    half-edges are offset by the board's gap (OPTICS.md): any blur that reaches along an
    edge past the corner (a defocus disk wider than the profiles' clearance, diffraction's
    1/x² tails at any distance) mixes two steps the gap apart into its profiles; the
    standard corner's edges run straight through it. Merged in every frame, the mixture is
    the same along the sweep and the fit's static kernel takes up the difference; but where
    one corner's micro-images enter or leave the windows along the sweep, the share of the
    reference corner changes with ``Q`` as a defocus would: on wave-optical sweeps whose
    far half alone showed it, the wave-optical fit put ``Q0`` 0.3 % low on average (1.2σ,
    15 of 16 seeds low), with the standard corner alone 0.03 %. Where both corners are in
    every frame the standard corner alone threw half the data away (a ray-traced sweep
    with diffraction: ``Q0`` +0.5 %, 1.8σ, merged -0.1 %).
    """
    by_corner: dict[str, dict[int, EdgeObservation]] = {}
    for o in observations:
        by_corner.setdefault(o.corner, {})[o.frame] = o
    if not by_corner:
        return []
    frames = {f for seen in by_corner.values() for f in seen}
    if len(by_corner) > 1 and all(len(seen) == len(frames) for seen in by_corner.values()):
        return [
            merge_corners([seen[f] for _, seen in sorted(by_corner.items())])
            for f in sorted(frames)
        ]
    corner = max(by_corner, key=lambda c: (len(by_corner[c]), c == "standard"))
    return [o for _, o in sorted(by_corner[corner].items())]


def merge_corners(parts: Sequence[EdgeObservation]) -> EdgeObservation:
    """One frame's corners' functions, each centred on its own edge, merged (corner ``both``).

    The corners of a frame see the same defocus (their ``Q`` agree to ~1e-4, which the
    result checks) but each corner's function is placed by its own lattice, so their
    origins may differ by a fraction of the placement error: each is centred on the
    centroid of its line spread (:meth:`BinnedEsf.centre_px`; a symmetric blur's centroid
    is the edge) before merging. ``Q`` is the profile-weighted mean of the corners'.
    """
    if len(parts) == 1:
        return parts[0]
    centres = [p.esf.centre_px() for p in parts]
    esfs = [
        p.esf.shifted(-c) if np.isfinite(c) else p.esf for p, c in zip(parts, centres, strict=True)
    ]
    weights = np.array([p.esf.profiles for p in parts], dtype=np.float64)
    q = float(np.sum(weights * np.array([p.Q for p in parts])) / np.sum(weights))
    return EdgeObservation(parts[0].frame, "both", q, BinnedEsf.merge(esfs))
