"""The main-lens magnification of every frame from the two corners' main images, with a given ``Q``.

A corner's micro-image positions ``s`` follow ``s = m + (m - r)·Q`` (OPTICS.md §1: ``m``
the lens centres, ``r`` the corner's main image, pixels). The frame analysis fits
``Q`` and ``r`` of each corner together from its 3-10 micro-images; but the
micro-images that see an off-axis corner all lie on one side of it (on the chief ray
through the main-lens centre, about 60 px for the reference corner (2s, 0) of a 50 px
lens camera), so ``r = m̄ + (m̄ - s̄)/Q`` is extrapolated over that lever arm and
each frame's ``Q`` error moves it by ``|m̄ - s̄|·δQ/Q²``: ±5e-4 in ``Q`` is 0.1 px,
and a ``Q`` error that trends along the sweep (the disparity's bias) tilts ``1/M``
against the rail and biases F and the rail zero (on an independent renderer's sweep
F −0.059 % at 4σ, with the micro-image positions right to 0.003 px).

:func:`lever_arm_inverse_magnification` recomputes both corners' main images with a
``Q`` per frame given by the caller (the calibrated camera's ``Q(u)``, far more precise
than one corner's), with its uncertainty propagated through each corner's lever arm into the corners' distance; ``1/M = 2s/(|r_ref -
r_std|·δ)``.

A corner's micro-images are weighed by their fits' errors plus the variance they share
beyond them (:func:`calibration.random_effects.paule_mandel`): where the pixels do not
resolve the corners' edges (point samples, very sharp micro-images) the positions lock
to the pixel grid, tenths of a pixel off where each fit claims thousandths, and the
sharpest, most locked one claims the least. Weighed by the claims alone (scaled by the
scatter's Birge ratio, until session 48) a renderer with one sample per pixel put F,
the rail zero and b 3-4σ off.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid
from .random_effects import paule_mandel

CORNER_SE_FLOOR_PX = 0.003
"""Smallest standard error of a micro-image corner position (px), here and in the
frame's disparity fit (:mod:`calibration.frame_analysis`)."""


def inverse_magnification_from_distance(
    dist_px: float, dist_se_px: float, *, square_mm: float, pixel_pitch_mm: float
) -> tuple[float, float]:
    """``1/M = 2s/(d·δ)`` and its 1σ from the distance ``d`` (px) between the two corners'
    main images, ``2s`` apart on the board (the main image of board point X lies at
    ``-X·M``, OPTICS.md §3)."""
    inv = 2.0 * square_mm / (dist_px * pixel_pitch_mm)
    return inv, inv * dist_se_px / dist_px


def _main_image(
    rows: NDArray[np.float64], lens_grid: LensGrid, q: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """``(r, lever, se)`` of one corner for a known ``Q``: its main image (px), the lever
    arm ``m̄ - s̄`` (px) and the statistical 1σ of each coordinate of ``r`` (px).

    ``rows``: per micro-image ``[i, j, x, y, x_se, y_se, ...]`` (the frame summary's
    ``corners``). With ``Q`` known, ``c = s - (1+Q)·m`` is the same for every
    micro-image (``-Q·r``): its weighted mean gives ``r = -c/Q``.
    """
    mx, my = lens_grid.centre(rows[:, 0], rows[:, 1])
    centres = np.column_stack([mx, my])
    positions = rows[:, 2:4]
    var = np.maximum(np.maximum(rows[:, 4], rows[:, 5]), CORNER_SE_FLOOR_PX) ** 2
    # each micro-image's offset c = s - (1+Q)·m; their scatter beyond the fits' errors
    # (positions locked to the pixel grid) is a variance every micro-image shares
    offsets = positions - (1.0 + q) * centres
    w = 1.0 / (var + paule_mandel(offsets, var))
    total = float(np.sum(w))
    m_bar = w @ centres / total
    s_bar = w @ positions / total
    lever = m_bar - s_bar
    r = m_bar + lever / q
    return r, lever, float(np.sqrt(1.0 / total) / q)


def lever_arm_inverse_magnification(
    corners: Sequence[dict[str, Any]],
    lens_grid: LensGrid,
    *,
    q: NDArray[np.float64],
    q_se: NDArray[np.float64],
    square_mm: float,
    pixel_pitch_mm: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``1/M`` per frame and its 1σ from both corners' main images at ``Q = q[k]``.

    ``corners[k]``: frame ``k``'s ``{"standard": rows, "reference": rows}`` (the frame
    summary's ``corners``; empty or missing when the corner was not found).
    ``q_se``: the 1σ of ``q`` per frame (the caller's; a systematic common to every
    frame belongs in a refit, not here); it moves the
    two main images by their lever arms, and their distance by the difference of the
    lever arms along the line joining them. NaN where either corner is missing.
    """
    n = len(corners)
    inv = np.full(n, np.nan)
    se = np.full(n, np.nan)
    for k, frame in enumerate(corners):
        parts = []
        for name in ("standard", "reference"):
            rows = np.asarray(frame.get(name) or [], dtype=np.float64)
            if rows.ndim != 2 or rows.shape[0] < 1 or rows.shape[1] < 6:
                break
            parts.append(_main_image(rows, lens_grid, float(q[k])))
        if len(parts) != 2 or not np.isfinite(q[k]) or q[k] <= 0:
            continue
        (r_std, lever_std, se_std), (r_ref, lever_ref, se_ref) = parts
        delta = r_ref - r_std
        dist = float(np.hypot(*delta))
        if not dist > 0:
            continue
        direction = delta / dist
        # d r / d Q = -lever / Q²: the distance moves by the lever arms' difference
        lever_along = float(np.dot(lever_ref - lever_std, direction))
        dist_se = float(
            np.sqrt(se_std**2 + se_ref**2 + (lever_along * float(q_se[k]) / q[k] ** 2) ** 2)
        )
        inv[k], se[k] = inverse_magnification_from_distance(
            dist, dist_se, square_mm=square_mm, pixel_pitch_mm=pixel_pitch_mm
        )
    return inv, se
