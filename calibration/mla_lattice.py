"""The micro-image lattice of a white image as least squares over lens centres.

Pure functions used by :func:`calibration.mla_grid.fit_mla_grid` (pixels; pixel centres at
integer coordinates; lens ``(i, j)`` at ``x = ox + a·i - b·j``, ``y = oy + b·i + a·j``):
the similarity fit and its robust version, the dead-lens screen, which lenses are in
view, the sparse subset of the early rounds, how far a fit moved the lattice and the
lattice re-indexed about the principal point.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .mla_spectrum import Lattice

MIN_LENSES = 9
"""The fewest micro-images a lattice is fitted to."""


def fit_lattice(
    i: NDArray[np.int64], j: NDArray[np.int64], x: NDArray[np.float64], y: NDArray[np.float64]
) -> Lattice:
    """Least-squares similarity lattice ``x = ox + a·i - b·j``, ``y = oy + b·i + a·j``."""
    n = i.size
    fi, fj = i.astype(np.float64), j.astype(np.float64)
    A = np.zeros((2 * n, 4))
    A[:n, 0] = 1.0
    A[:n, 2] = fi
    A[:n, 3] = -fj
    A[n:, 1] = 1.0
    A[n:, 2] = fj
    A[n:, 3] = fi
    sol, *_ = np.linalg.lstsq(A, np.concatenate([x, y]), rcond=None)
    return Lattice((float(sol[0]), float(sol[1])), float(sol[2]), float(sol[3]))


def robust_fit(
    i: NDArray[np.int64],
    j: NDArray[np.int64],
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    use: NDArray[np.bool_],
    *,
    outlier_sigma: float,
    outlier_floor_px: float,
) -> tuple[Lattice, NDArray[np.bool_]]:
    """Fit with iterative rejection of centres farther than ``max(k·σ, floor)`` from the lattice."""
    keep = use.copy()
    lat = fit_lattice(i[keep], j[keep], x[keep], y[keep])
    for _ in range(8):
        px, py = lat.centre(i, j)
        res = np.hypot(x - px, y - py)
        sigma = float(np.median(res[keep])) / 1.1774  # median of a 2-D Gaussian's radius
        limit = max(outlier_sigma * sigma, outlier_floor_px)
        new = use & (res <= limit)
        if new.sum() < MIN_LENSES:
            raise ValueError(
                f"white image: only {int(new.sum())} micro-images agree with a common lattice"
            )
        if np.array_equal(new, keep):
            break
        keep = new
        lat = fit_lattice(i[keep], j[keep], x[keep], y[keep])
    return lat, keep


def dead_lenses(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    level: NDArray[np.float64],
    dead_fraction: float,
) -> NDArray[np.bool_]:
    """Lenses darker than ``dead_fraction`` × a robust quadratic trend of the plateau levels."""
    ok = np.isfinite(x) & (level > 0)
    dead = ~ok
    if ok.sum() < 12:
        return dead
    s = max(float(np.ptp(x[ok])), float(np.ptp(y[ok])), 1.0)
    xn, yn = (x - np.mean(x[ok])) / s, (y - np.mean(y[ok])) / s
    xn, yn = np.where(ok, xn, 0.0), np.where(ok, yn, 0.0)
    basis = np.stack([np.ones_like(xn), xn, yn, xn * xn, xn * yn, yn * yn], axis=1)
    logl = np.log(np.where(ok, level, 1.0))
    fit = ok.copy()
    model = np.zeros_like(logl)
    for _ in range(6):
        coef, *_ = np.linalg.lstsq(basis[fit], logl[fit], rcond=None)
        model = basis @ coef
        res = logl - model
        sigma = 1.4826 * float(np.median(np.abs(res[fit])))
        new = ok & (np.abs(res) <= max(3.0 * sigma, 0.05))
        if np.array_equal(new, fit) or new.sum() < 12:
            break
        fit = new
    return dead | (level < dead_fraction * np.exp(model))


def candidate_lenses(
    lat: Lattice, shape: tuple[int, int], margin: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], int]:
    """Lenses whose centre is on the sensor, those at least ``margin`` inside, and the count of the rest."""
    h, w = shape
    g = lat.grid()
    ii, jj = g.indices_in(w, h, margin_px=0.0)
    x, y = lat.centre(ii, jj)
    inside = (x >= margin) & (x <= w - 1 - margin) & (y >= margin) & (y <= h - 1 - margin)
    return ii[inside], jj[inside], int((~inside).sum())


def sparse_subset(i: NDArray[np.int64], j: NDArray[np.int64], max_n: int) -> NDArray[np.bool_]:
    """Every k-th lens along i and j (k chosen so that at most about ``max_n`` remain)."""
    k = max(1, int(math.ceil(math.sqrt(i.size / max_n))))
    return ((i % k) == 0) & ((j % k) == 0)


def max_move_px(old: Lattice, new: Lattice, w: int, h: int) -> float:
    """Largest displacement (px) between two lattices' nodes at the sensor corners."""
    g_old, g_new = old.grid(), new.grid()
    fi, fj = g_old.fractional_index(
        np.array([0.0, w - 1.0, 0.0, w - 1.0]), np.array([0.0, 0.0, h - 1.0, h - 1.0])
    )
    ox, oy = g_old.centre(fi, fj)
    nx, ny = g_new.centre(fi, fj)
    return float(np.max(np.hypot(nx - ox, ny - oy)))


def recentre(lat: Lattice, pp: tuple[float, float]) -> tuple[Lattice, int, int]:
    """The same lattice with node (0, 0) moved to the node nearest the principal point.

    Returns the new lattice and the old index ``(di, dj)`` of the new origin
    (subtract it from old indices).
    """
    ni, nj = lat.grid().nearest(np.array([pp[0]]), np.array([pp[1]]))
    ox, oy = lat.centre(ni, nj)
    return Lattice((float(ox[0]), float(oy[0])), lat.a, lat.b), int(ni[0]), int(nj[0])
