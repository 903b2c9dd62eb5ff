"""Edge shapes the edge-spread and defocus tests share."""

from __future__ import annotations

import numpy as np
from scipy.special import fresnel


def sinc2_cdf(q: np.ndarray) -> np.ndarray:
    """Cumulative line spread of ``sinc²(q)`` (normalised sinc, unit integral): an edge
    parallel to a side of a square aperture, diffraction-limited, ``q`` in units of the
    pattern's first zero ``λN``; the tails fall as 1/q² (the edge spread's as 1/q)."""
    grid = np.linspace(-400.0, 400.0, 400_001)
    density = np.sinc(grid) ** 2
    cumulative = np.concatenate(([0.0], np.cumsum(0.5 * (density[1:] + density[:-1])))) * (
        grid[1] - grid[0]
    )
    cumulative += 1.0 / (np.pi**2 * 400.0)  # the tail below the grid, ∫ 1/(πq)² dq
    return np.interp(q, grid, cumulative)


def fresnel_slit_line_spread(x: np.ndarray, d: float, s: float) -> np.ndarray:
    """Wave-optical line spread of a defocused slit (a square microlens, the edge parallel
    to a side): ``|∫_{-1/2}^{1/2} exp(iπ(d·t² - 2t·x)/s) dt|²`` at ``x`` px, with ``d`` the
    geometric blur diameter (px, signed) and ``s = λN/δ`` the diffraction pattern's first
    zero (px). Completing the square turns it into Fresnel integrals; unit height at the
    centre when ``d = 0`` (``sinc²(x/s)``)."""
    a = d / s
    if abs(a) < 1e-9:
        return np.sinc(x / s) ** 2
    r = np.sqrt(2.0 * abs(a))
    s1, c1 = fresnel(r * (-0.5 - x / d))
    s2, c2 = fresnel(r * (0.5 - x / d))
    return ((c2 - c1) ** 2 + (s2 - s1) ** 2) / (2.0 * abs(a))


def fresnel_edge(d: float, s: float, *, span_px: float = 80.0, step_px: float = 0.005):
    """The wave-optical edge spread of :func:`fresnel_slit_line_spread` seen through 1 px
    square pixels: a function of position (px), 0 far on the dark side, 1 on the light."""
    grid = np.arange(-span_px, span_px + step_px / 2, step_px)
    density = fresnel_slit_line_spread(grid, d, s)
    cumulative = np.concatenate(([0.0], np.cumsum(0.5 * (density[1:] + density[:-1])))) * step_px
    tail = s * s / (2.0 * np.pi**2 * span_px)  # ∫ beyond the grid of the mean tail s²/(2π²x²)
    cumulative = (cumulative + tail) / (cumulative[-1] + 2.0 * tail)
    offsets = (np.arange(12) + 0.5) / 12 - 0.5
    return lambda x: np.mean([np.interp(x - o, grid, cumulative) for o in offsets], axis=0)
