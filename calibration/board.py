"""The double-checkerboard calibration board (``shared/OPTICS.md`` §3).

Board coordinates ``(X, Y)`` are in mm, seen from the camera, X parallel to the
sensor's x axis. Square ``(c, r)`` covers ``c·s <= X < (c+1)·s``,
``r·s <= Y < (r+1)·s`` and is dark when ``c + r`` is even. Columns ``c >= 1``
form the reference checkerboard: their dark squares are shrunk by ``Cr/2`` on
all four sides. Outside ``|X|, |Y| <= half_extent`` the board is light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


_G_TAIL = 7.0
"""Beyond ``|z| = 7``, ``G(z) = max(z, 0)`` to within 1e-11 (``φ(7) ≈ 9e-12``)."""


def _g(z: NDArray[np.floating]) -> NDArray[np.floating]:
    """``G(z) = z Φ(z) + φ(z)``, the antiderivative of the normal CDF.

    The normal CDF is evaluated only where ``|z| < 7``: most footprints are many
    σ away from most square edges, where ``G`` is ``max(z, 0)``.
    """
    out = np.maximum(z, 0).astype(np.float64)  # the float32 z's sums are formed in float64
    near = np.flatnonzero(np.abs(z) < _G_TAIL)
    if near.size:
        zn = z.ravel()[near]
        out.ravel()[near] = zn * ndtr(zn) + np.exp(-0.5 * zn * zn) * _INV_SQRT_2PI
    return out


def _interval_cover(
    lo_f: NDArray[np.floating],
    hi_f: NDArray[np.floating],
    lo: NDArray[np.floating],
    hi: NDArray[np.floating],
    sigma: float,
) -> NDArray[np.floating]:
    """Length-weighted cover of ``[lo, hi]`` over the footprint ``[lo_f, hi_f]`` (mm).

    With ``sigma > 0`` the indicator of ``[lo, hi]`` is first blurred by a
    Gaussian of standard deviation ``sigma`` (mm): the integral over the
    footprint of ``Φ((t-lo)/σ) - Φ((t-hi)/σ)``.
    """
    if sigma <= 0:
        return np.clip(np.minimum(hi_f, hi) - np.maximum(lo_f, lo), 0.0, None)
    inv = 1.0 / sigma
    # float32 halves the cost of the normal CDF; the differences are formed in float64
    z = [
        ((a - b) * inv).astype(np.float32)
        for a, b in ((hi_f, lo), (lo_f, lo), (hi_f, hi), (lo_f, hi))
    ]
    return sigma * (_g(z[0]) - _g(z[1]) - _g(z[2]) + _g(z[3]))


@dataclass(frozen=True)
class Board:
    """Board geometry and reflectances (mm; reflectances in [0, 1])."""

    square_mm: float = 10.0
    reference_gap_mm: float = 0.1
    dark: float = 0.05
    light: float = 0.95
    half_extent_mm: float = 150.0

    def __post_init__(self) -> None:
        if not self.square_mm > 0:
            raise ValueError(f"board square size must be positive, got {self.square_mm} mm")
        if not 0 <= self.reference_gap_mm < self.square_mm:
            raise ValueError(
                f"reference gap Cr = {self.reference_gap_mm} mm must be in [0, square size)"
            )
        if not 0 <= self.dark < self.light <= 1:
            raise ValueError("board reflectances need 0 <= dark < light <= 1")

    @property
    def standard_corner_mm(self) -> tuple[float, float]:
        """The standard corner (0, 0): four squares meet at a point."""
        return (0.0, 0.0)

    @property
    def reference_corner_mm(self) -> tuple[float, float]:
        """The reference corner (2s, 0): the dark squares are separated by a gap Cr."""
        return (2.0 * self.square_mm, 0.0)

    def distance_to_edge_mm(
        self, X: NDArray[np.floating], Y: NDArray[np.floating]
    ) -> NDArray[np.floating]:
        """A lower bound on the distance from (X, Y) to the nearest reflectance edge (mm)."""
        s = self.square_mm
        g = 0.5 * self.reference_gap_mm
        dx = np.abs(X - s * np.round(X / s))
        dy = np.abs(Y - s * np.round(Y / s))
        return np.minimum(dx, dy) - g

    def box_reflectance(
        self,
        X: NDArray[np.floating],
        Y: NDArray[np.floating],
        half_width_mm: float,
        blur_sigma_mm: float = 0.0,
    ) -> NDArray[np.floating]:
        """Mean reflectance over the axis-aligned square ``[X±h] × [Y±h]`` (exact, analytic).

        With ``blur_sigma_mm`` > 0 the board is first blurred by an isotropic
        Gaussian (a PSF mapped onto the board). ``h`` plus 5σ must stay below
        ``(s - Cr)/2``, so that a footprint touches at most two columns and two
        rows of squares.
        """
        s = self.square_mm
        g = 0.5 * self.reference_gap_mm
        h = float(half_width_mm)
        if not 0 < h + 5 * blur_sigma_mm < 0.5 * (s - 2 * g):
            raise ValueError(f"footprint half width {h} mm is out of range for squares of {s} mm")
        n_half = int(round(self.half_extent_mm / s))
        kx = np.round(X / s)
        ky = np.round(Y / s)
        x_lo, x_hi = X - h, X + h
        y_lo, y_hi = Y - h, Y + h
        inv_area = 1.0 / (4.0 * h * h)
        shape = np.broadcast_shapes(np.shape(X), np.shape(Y))
        kx, ky = np.broadcast_to(kx, shape), np.broadcast_to(ky, shape)
        x_lo, x_hi = np.broadcast_to(x_lo, shape), np.broadcast_to(x_hi, shape)
        y_lo, y_hi = np.broadcast_to(y_lo, shape), np.broadcast_to(y_hi, shape)
        # The row intervals depend on the column only through its shrink (c >= 1):
        # columns kx - 1 and kx shrink alike except where kx == 1, so the row covers
        # are computed once and redone for column kx - 1 only there.
        shrink_at = {dc: np.where(kx + dc >= 1, g, 0.0).astype(X.dtype) for dc in (-1.0, 0.0)}
        differs = np.flatnonzero(shrink_at[-1.0] != shrink_at[0.0])
        over_y_at: dict[tuple[float, float], NDArray[np.floating]] = {}
        for dr in (-1.0, 0.0):
            r = ky + dr
            shrink = shrink_at[0.0]
            cover = _interval_cover(y_lo, y_hi, r * s + shrink, (r + 1) * s - shrink, blur_sigma_mm)
            over_y_at[(0.0, dr)] = cover
            if differs.size:
                cover = cover.copy()
                sub = np.unravel_index(differs, shape)
                shrink_m = shrink_at[-1.0][sub]
                cover[sub] = _interval_cover(
                    y_lo[sub],
                    y_hi[sub],
                    r[sub] * s + shrink_m,
                    (r[sub] + 1) * s - shrink_m,
                    blur_sigma_mm,
                )
            over_y_at[(-1.0, dr)] = cover
        # square (kx + dc, ky + dr) is dark when its index sum is even; outside the
        # board's extent everything is light
        even = ((kx + ky) % 2) == 0
        in_rows = {dr: (ky + dr >= -n_half) & (ky + dr < n_half) for dr in (-1.0, 0.0)}
        dark_cover = np.zeros(shape, dtype=X.dtype)
        for dc in (-1.0, 0.0):
            c = kx + dc
            shrink = shrink_at[dc]
            over_x = _interval_cover(
                x_lo, x_hi, c * s + shrink, (c + 1) * s - shrink, blur_sigma_mm
            )
            over_x *= (c >= -n_half) & (c < n_half)
            for dr in (-1.0, 0.0):
                dark = (even if dc == dr else ~even) & in_rows[dr]
                dark_cover += over_x * over_y_at[(dc, dr)] * dark
        return (self.light - (self.light - self.dark) * dark_cover * inv_area).astype(X.dtype)
