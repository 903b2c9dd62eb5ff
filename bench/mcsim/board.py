"""The analytic double-checkerboard board of OPTICS.md §3.

Board coordinates (X, Y) mm, X along the sensor's x axis, Y along its y axis.
Square (c, r) covers ``c·s <= X < (c+1)·s``, ``r·s <= Y < (r+1)·s`` and is dark
when ``c + r`` is even. Columns ``c <= 0`` are the standard checkerboard (corner
size 0); in columns ``c >= 1`` every dark square is shrunk by ``Cr/2`` on all four
sides (reference checkerboard). Dark reflectance 0.05, light 0.95; the board is
light outside ``|X|, |Y| <= 150``.

The board is mounted so that board point (X, Y) sits at lateral position
``(X + offset_x, Y + offset_y)`` mm from the optical axis: a zero offset puts the
standard corner (0, 0) on the axis (OPTICS.md §3: the XY stage does that).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

DARK = 0.05
LIGHT = 0.95
HALF_EXTENT_MM = 150.0


@dataclass(frozen=True)
class Board:
    square_mm: float = 10.0
    gap_mm: float = 0.1
    offset_mm: tuple[float, float] = (0.0, 0.0)

    def corner_positions_mm(self, names: tuple[str, ...]) -> dict[str, tuple[float, float]]:
        """Lateral positions (mm from the axis) of the named corners (standard, reference)."""
        board_xy = {"standard": (0.0, 0.0), "reference": (2.0 * self.square_mm, 0.0)}
        ox, oy = self.offset_mm
        return {n: (board_xy[n][0] + ox, board_xy[n][1] + oy) for n in names}

    def reflectance(
        self, X: npt.NDArray[np.float32], Y: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.float32]:
        """Reflectance at board coordinates (X, Y) (same-shape float32 arrays)."""
        dark = self.dark_mask(X, Y)
        return np.where(dark, np.float32(DARK), np.float32(LIGHT))

    def dark_mask(
        self, X: npt.NDArray[np.float32], Y: npt.NDArray[np.float32]
    ) -> npt.NDArray[np.bool_]:
        """True where board coordinates (X, Y) fall on a dark area.

        X and Y are board coordinates (the mount offset already removed).
        """
        inv = np.float32(1.0 / self.square_mm)
        xs = X * inv
        ys = Y * inv
        cf = np.floor(xs)
        rf = np.floor(ys)
        xs -= cf  # fractional position inside the square, [0, 1)
        ys -= rf
        parity = cf + rf
        dark = np.floor(parity * np.float32(0.5)) * np.float32(2.0) == parity  # c + r even
        if self.gap_mm > 0:
            half = np.float32(0.5 - 0.5 * self.gap_mm / self.square_mm)
            reference = cf >= 1
            if reference.any():
                xs -= np.float32(0.5)
                ys -= np.float32(0.5)
                np.abs(xs, out=xs)
                np.abs(ys, out=ys)
                in_gap = np.maximum(xs, ys, out=xs) > half
                in_gap &= reference
                dark &= ~in_gap
        lim = np.float32(HALF_EXTENT_MM)
        if not (X.max(initial=-np.inf) <= lim and X.min(initial=np.inf) >= -lim):
            dark &= np.abs(X) <= lim
        if not (Y.max(initial=-np.inf) <= lim and Y.min(initial=np.inf) >= -lim):
            dark &= np.abs(Y) <= lim
        return dark
