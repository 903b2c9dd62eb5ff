"""Exact area coverage of the double checkerboard over axis-aligned cells (no aliasing).

Units: board millimetres. Board conventions as :mod:`bench.mcsim.board` (OPTICS.md §3):
square (c, r) covers ``c·s <= X < (c+1)·s``, ``r·s <= Y < (r+1)·s`` and is dark
when c + r is even; in the reference columns (c >= 1) each dark square is shrunk
by Cr/2 on all four sides; the board is light outside |X|, |Y| <= 150.

Inside one micro-image the chief-ray mapping from the sensor to the board is
a scale and a shift (no rotation: the MLA's turn only moves the lens centres),
so the supersampled sensor cells map to a grid of axis-aligned board cells,
``[X_k, X_k+1] × [Y_l, Y_l+1]``. The dark area of a cell is a sum over the (at
most 2×2) squares it touches of products of 1-D interval overlaps, and with
c + r even <=> (c even and r even) or (c odd and r odd) it is four outer
products of 1-D arrays: exact and cheap. Each cell must be narrower than a
square (checked).
"""

from __future__ import annotations

import numpy as np

from bench.mcsim.board import DARK, HALF_EXTENT_MM, LIGHT, Board
from bench.wavesim.psf import FloatArray


def _interval_overlap(edges: FloatArray, square: float, c: FloatArray, inset: float) -> FloatArray:
    """Overlap (mm) of each cell ``[edges[k], edges[k+1]]`` with ``[c·s + inset, (c+1)·s - inset]``.

    The interval is clipped to the board's extent, ±150 mm.
    """
    lo, hi = edges[:-1], edges[1:]
    a = np.maximum(c * square + inset, -HALF_EXTENT_MM)
    b = np.minimum((c + 1.0) * square - inset, HALF_EXTENT_MM)
    return np.clip(np.minimum(hi, b) - np.maximum(lo, a), 0.0, None)


def _by_parity(
    edges: FloatArray, square: float, inset: float, keep: str = "all"
) -> tuple[FloatArray, FloatArray]:
    """Per cell, the summed overlaps with the intervals of even and of odd indices.

    ``keep``: "all" indices, "standard" (index <= 0) or "reference" (index >= 1).
    """
    first = np.floor(edges[:-1] / square)
    even, odd = np.zeros(first.size), np.zeros(first.size)
    for step in (0.0, 1.0):  # a cell narrower than a square touches at most two
        c = first + step
        overlap = _interval_overlap(edges, square, c, inset)
        if keep == "standard":
            overlap = np.where(c <= 0, overlap, 0.0)
        elif keep == "reference":
            overlap = np.where(c >= 1, overlap, 0.0)
        is_odd = np.mod(c, 2.0) == 1.0
        odd += np.where(is_odd, overlap, 0.0)
        even += np.where(is_odd, 0.0, overlap)
    return even, odd


def dark_fraction(board: Board, x_edges: FloatArray, y_edges: FloatArray) -> FloatArray:
    """Dark area fraction of every cell; rows follow ``y_edges``, columns ``x_edges``.

    Edges are board coordinates (mm, ascending).
    """
    s, inset = board.square_mm, board.gap_mm / 2.0
    wx, wy = np.diff(x_edges), np.diff(y_edges)
    if wx.max(initial=0.0) >= s / 2 or wy.max(initial=0.0) >= s / 2:
        raise ValueError("board cells must be narrower than half a square")
    if wx.min(initial=1.0) <= 0 or wy.min(initial=1.0) <= 0:
        raise ValueError("board cell edges must ascend")
    x_std = _by_parity(x_edges, s, 0.0, "standard")
    x_ref = _by_parity(x_edges, s, inset, "reference")
    y_std = _by_parity(y_edges, s, 0.0)
    y_ref = _by_parity(y_edges, s, inset)
    dark = (
        np.outer(y_std[0], x_std[0])
        + np.outer(y_std[1], x_std[1])
        + np.outer(y_ref[0], x_ref[0])
        + np.outer(y_ref[1], x_ref[1])
    )
    return dark / np.outer(wy, wx)


def reflectance(board: Board, x_edges: FloatArray, y_edges: FloatArray) -> FloatArray:
    """Mean reflectance of every cell (dark 0.05, light 0.95), rows along Y."""
    dark = dark_fraction(board, x_edges, y_edges)
    return LIGHT + (DARK - LIGHT) * dark
