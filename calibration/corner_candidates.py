"""Corner candidates in the micro-images of a raw frame (steps 1–2 of :mod:`calibration.corners`).

:class:`MicroImageMap` labels every pixel with the micro-image whose interior disc holds
it; :func:`find_junctions` finds the strongest saddle of each micro-image (the corner's
start point, to a pixel); :func:`hough_refine` is the paper's median filter + Hough lines
around a start point, run as a diagnostic. Coordinates are sensor pixels, pixel centres
at integers, arrays ``[y, x]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid

__all__ = ["Junctions", "MicroImageMap", "find_junctions", "hough_refine"]


@dataclass(frozen=True)
class Junctions:
    """Saddle candidates: one per micro-image (lattice index, position, strength)."""

    i: NDArray[np.int64]
    j: NDArray[np.int64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    strength: NDArray[np.float64]


class MicroImageMap:
    """Pixel -> micro-image bookkeeping for one lattice and frame size (computed once)."""

    def __init__(
        self, image_grid: LensGrid, shape: tuple[int, int], interior_radius_px: float
    ) -> None:
        h, w = shape
        self.grid = image_grid
        self.shape = shape
        self.interior_radius_px = interior_radius_px
        ys, xs = np.mgrid[0:h, 0:w]
        fi, fj = image_grid.fractional_index(xs, ys)
        ii, jj = np.rint(fi), np.rint(fj)
        r = np.hypot(fi - ii, fj - jj) * image_grid.pitch_px
        self.i_min, self.j_min = int(ii.min()), int(jj.min())
        self.n_j = int(jj.max()) - self.j_min + 1
        label = ((ii - self.i_min) * self.n_j + (jj - self.j_min)).astype(np.int32)
        label[r > interior_radius_px] = -1
        self.label = label
        self.n_labels = int(label.max()) + 1

    def index_of(self, label: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        return label // self.n_j + self.i_min, label % self.n_j + self.j_min


def find_junctions(
    frame: NDArray[np.floating] | NDArray[np.integer],
    mim: MicroImageMap,
    *,
    sigma_px: float = 2.0,
    relative_threshold: float = 0.12,
    rows: tuple[int, int] | None = None,
) -> Junctions:
    """The strongest saddle point of every micro-image interior that holds a corner.

    Strength is ``-det(Hessian)`` of the frame smoothed with ``sigma_px``; a
    micro-image is kept when its strength exceeds ``relative_threshold`` times
    a robust maximum over the frame. ``rows = (first, end)`` limits the search
    to a band of rows (sensor pixels).
    """
    r0, r1 = (0, mim.shape[0]) if rows is None else (max(0, rows[0]), min(mim.shape[0], rows[1]))
    if r1 <= r0:
        return _no_junctions()
    # the Hessian at half resolution (sigma halved): the saddle only seeds the edge fits,
    # a pixel of precision is plenty, and it is four times cheaper
    pad = 2 * (int(np.ceil(2 * sigma_px)) + 2)
    p0 = max(0, r0 - pad) // 2 * 2
    p1 = min(mim.shape[0], r1 + pad) // 2 * 2
    width = mim.shape[1] // 2 * 2
    img = np.asarray(frame[p0:p1, :width], dtype=np.float32)
    small = cv2.resize(img, (width // 2, (p1 - p0) // 2), interpolation=cv2.INTER_AREA)
    g = cv2.GaussianBlur(small, (0, 0), sigma_px / 2.0)
    ixx = cv2.Sobel(g, cv2.CV_32F, 2, 0, ksize=3)
    iyy = cv2.Sobel(g, cv2.CV_32F, 0, 2, ksize=3)
    ixy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
    q0, q1 = (r0 - p0 + 1) // 2, (r1 - p0) // 2
    strength = (ixy * ixy - ixx * iyy)[q0:q1]
    # label of each half-resolution pixel: that of the full-resolution pixel at its centre
    lab = mim.label[p0 + 2 * q0 : p0 + 2 * q1 : 2, 0:width:2]
    lab = lab[: strength.shape[0], : strength.shape[1]].ravel()
    inside = lab >= 0
    s_flat = strength[: len(lab) // strength.shape[1]].ravel()
    best = np.full(mim.n_labels, -np.inf, dtype=np.float32)
    np.maximum.at(best, lab[inside], s_flat[inside])
    top = np.sort(best[np.isfinite(best)])
    if top.size == 0:
        return _no_junctions()
    robust_max = top[-min(10, top.size)]
    strong = best > relative_threshold * max(float(robust_max), 1e-12)
    # position of the maximum within each kept label
    pix = np.flatnonzero(inside)
    lab_in = lab[pix]
    sel = strong[lab_in] & (s_flat[pix] == best[lab_in])
    pix_sel, lab_sel = pix[sel], lab_in[sel]
    _, first = np.unique(lab_sel, return_index=True)
    pix_sel, lab_sel = pix_sel[first], lab_sel[first]
    ys, xs = np.divmod(pix_sel, strength.shape[1])
    i, j = mim.index_of(lab_sel.astype(np.int64))
    x = 2.0 * xs + 0.5
    y = p0 + 2.0 * (ys + q0) + 0.5
    return Junctions(i, j, x, y, best[lab_sel].astype(float))


def _no_junctions() -> Junctions:
    return Junctions(*(np.empty(0, dtype=t) for t in (np.int64, np.int64, float, float, float)))


def hough_refine(patch: NDArray[np.float32], *, threshold: int) -> tuple[int, float, float]:
    """Count the half-edges found by Hough around the patch centre; refine the centre.

    The paper's median filter, Canny and probabilistic Hough (``threshold`` votes) on the
    patch, a square around the corner's start point. Returns ``(number of half-edges
    found (0..4), dx, dy)`` where ``(dx, dy)`` (pixels) moves the start point to the
    intersection of the best vertical and horizontal lines (0 when not found).
    """
    lo, hi = np.percentile(patch, [2, 98])
    if hi - lo <= 0:
        return 0, 0.0, 0.0
    img8 = np.clip((patch - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    img8 = cv2.medianBlur(img8, 3)
    edges = cv2.Canny(img8, 40, 120)
    lines = cv2.HoughLinesP(edges, 1, np.pi / 180, threshold, minLineLength=5, maxLineGap=2)
    if lines is None:
        return 0, 0.0, 0.0
    c = (patch.shape[1] - 1) / 2.0
    found: set[str] = set()
    # per orientation: the lines' positions across, and the half-edge names before/after
    across: dict[bool, list[float]] = {True: [], False: []}
    for x1, y1, x2, y2 in lines[:, 0, :].astype(float):
        dx, dy = x2 - x1, y2 - y1
        vertical = abs(dx) < 0.2 * abs(dy)
        if not vertical and not abs(dy) < 0.2 * abs(dx):
            continue  # neither vertical nor horizontal
        position = 0.5 * (x1 + x2) if vertical else 0.5 * (y1 + y2)
        if abs(position - c) > 3:
            continue
        across[vertical].append(position)
        start, end = (y1, y2) if vertical else (x1, x2)
        before, after = ("up", "down") if vertical else ("left", "right")
        found.add(before if min(start, end) < c - 1 else after)
        if max(start, end) > c + 1:
            found.add(after)
    ddx = float(np.median(across[True]) - c) if across[True] else 0.0
    ddy = float(np.median(across[False]) - c) if across[False] else 0.0
    return len(found), ddx, ddy
