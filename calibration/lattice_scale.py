"""Each corner's lattice scale smoothed over the sweep, and its profiles placed again with it.

One frame measures a corner's ``Q`` (its lattice scale ``1+Q``) from a handful of
micro-images: to ~2e-4 of ``Q`` when the corner is blurred, but only to 1e-3 or
worse near the focus plane, where a sharp corner sampled at a few points per
pixel locks to the pixel grid. The frame's edge profiles are placed by that
lattice, and a scale error ``δ`` moves each profile by ``δ·lever`` (its lens's
coordinate across the edge, :mod:`calibration.edge_profiles`): the profiles of
one corner, pooled, are blurred by ``|δ|`` times the spread of their levers
(~60 px), 0.03-0.05 px on the frames nearest focus of a Monte-Carlo sweep —
exactly where the defocus fit reads the focus plane, and more than the recorded
placement jitter (measured against a renderer's truth: 2-4x). Over 20 seeded
sweeps that scatter cost a third of the focus plane's precision
(sd of ``Q0`` 0.031 % instead of 0.019 % with the true scale).

Across the sweep ``Q`` is smooth: ``1/Q = (L - v)/b`` is linear in the main-image
distance ``v(u) = uF/(u - F)`` (OPTICS.md §1), and quadratic in ``v`` absorbs a
data-sheet ``F`` or rail zero that is off by 2 % or 2 mm (5e-8 of ``Q``) and the
disparity's smooth shading bias. :func:`smooth_corner_q` fits that per corner (the
corners' ``Q`` may differ by field curvature or MLA tilt), and
:func:`replace_profiles` moves every corner's lever groups back by its frame's
scale error against the fit (:meth:`calibration.edge_spread.BinnedEsf.replaced`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .defocus_problem import EdgeObservation
from .optics import image_distance

MIN_FRAMES = 6
"""Fewest frames of a corner for a smoothed scale (else its profiles stay as placed)."""

OUTLIER_SIGMAS = 4.0
"""Frames whose ``Q`` lies farther from the smooth curve (in robust sigmas) do not shape it."""


@dataclass(frozen=True)
class SmoothQ:
    """One corner's ``Q`` per frame as measured and as smoothed over the sweep."""

    measured: NDArray[np.float64]
    smooth: NDArray[np.float64]
    smooth_se: NDArray[np.float64]


def smooth_corner_q(
    object_distance_mm: NDArray[np.float64] | Sequence[float],
    q: NDArray[np.float64] | Sequence[float],
    q_se: NDArray[np.float64] | Sequence[float],
    *,
    main_focal_mm: float,
) -> SmoothQ | None:
    """``Q`` of one corner smoothed over the sweep: ``1/Q`` quadratic in ``v(u)``.

    ``object_distance_mm``: each frame's ``u`` from the rail and the data sheet;
    ``main_focal_mm``: the data-sheet ``F`` (its error is absorbed by the
    quadratic). Weighted by ``Q_se``, frames beyond ``OUTLIER_SIGMAS`` robust
    sigmas left out of the fit; the prediction's standard error from the fit's
    covariance (scaled by the reduced chi-square when above 1). None with fewer
    than ``MIN_FRAMES`` usable frames.
    """
    u = np.asarray(object_distance_mm, dtype=np.float64)
    qv = np.asarray(q, dtype=np.float64)
    qse = np.asarray(q_se, dtype=np.float64)
    ok = np.isfinite(u) & np.isfinite(qv) & (qv > 0) & np.isfinite(qse) & (qse > 0)
    ok &= u > main_focal_mm
    if ok.sum() < MIN_FRAMES:
        return None
    v = np.asarray(image_distance(np.where(ok, u, 2 * main_focal_mm), main_focal_mm))
    span = float(np.ptp(v[ok])) or 1.0
    t = (v - float(np.mean(v[ok]))) / span
    design = np.stack([np.ones_like(t), t, t * t], axis=1)
    y = 1.0 / np.where(ok, qv, 1.0)
    sy = qse / np.where(ok, qv, 1.0) ** 2
    use = ok.copy()
    for _ in range(4):
        if use.sum() < MIN_FRAMES:
            return None
        w = 1.0 / sy[use] ** 2
        normal = (design[use] * w[:, None]).T @ design[use]
        coef = np.linalg.solve(normal, (design[use] * w[:, None]).T @ y[use])
        z = (y - design @ coef) / sy
        scale = max(1.4826 * float(np.median(np.abs(z[use]))), 1.0)
        new_use = ok & (np.abs(z) <= OUTLIER_SIGMAS * scale)
        if np.array_equal(new_use, use):
            break
        use = new_use
    chi2 = float(np.sum(z[use] ** 2) / max(int(use.sum()) - 3, 1))
    cov = np.linalg.inv(normal) * max(chi2, 1.0)
    fitted = design @ coef
    fitted_se = np.sqrt(np.maximum(np.einsum("fi,ij,fj->f", design, cov, design), 0.0))
    smooth = np.where(np.isfinite(u) & (u > main_focal_mm), 1.0 / fitted, np.nan)
    return SmoothQ(qv, smooth, fitted_se * smooth**2)


def replace_profiles(
    observations: Sequence[EdgeObservation],
    object_distance_mm: dict[int, float],
    q_se: dict[tuple[int, str], float],
    *,
    main_focal_mm: float,
) -> list[EdgeObservation]:
    """Every observation's function with its profiles placed by its corner's smoothed scale.

    ``object_distance_mm``: ``u`` per frame; ``q_se``: each (frame, corner)'s
    standard error of ``Q``. Observations of a corner seen in fewer than
    ``MIN_FRAMES`` frames, or without lever groups, are returned as they are.
    """
    out = list(observations)
    for corner in sorted({o.corner for o in observations}):
        idx = [k for k, o in enumerate(out) if o.corner == corner]
        frames = [out[k].frame for k in idx]
        fit = smooth_corner_q(
            [object_distance_mm.get(f, np.nan) for f in frames],
            [out[k].Q for k in idx],
            [q_se.get((f, corner), np.nan) for f in frames],
            main_focal_mm=main_focal_mm,
        )
        if fit is None:
            continue
        for n, k in enumerate(idx):
            error = float(fit.measured[n] - fit.smooth[n])
            if np.isfinite(error):
                out[k] = replace(out[k], esf=out[k].esf.replaced(error, float(fit.smooth_se[n])))
    return out
