"""Edge shapes the edge-spread and defocus tests share."""

from __future__ import annotations

import numpy as np


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
