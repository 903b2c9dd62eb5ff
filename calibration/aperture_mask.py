"""The pixels of vignetted micro-images that still see their whole microlens aperture.

A pixel's value in a white image is the part of its microlens aperture whose rays get
through the main lens, weighted by the rays' angular shading (OPTICS.md §1;
:mod:`calibration.shading`). Where the main lens vignets (:mod:`calibration.vignetting`)
some pixels of a micro-image lose part of it: their defocus kernel is the aperture
clipped (smaller and lopsided), so an edge there reads sharper and off-centre, and the
flat field, fitted where nothing is clipped, does not describe them. A corner's edges
measured across such pixels move with the defocus, which biases the disparity (a
Monte-Carlo camera whose reference corner lay where a rear stop took a quarter of each
micro-image: ``Q`` -0.04 %, its main image +0.08 px, b -0.02 %).

:func:`full_aperture_mask` divides each vignetted micro-image of the white image by the
smooth shading the unvignetted ones have (:class:`~calibration.flat_field.FlatField`),
averages it over ``SMOOTH_PX``×``SMOOTH_PX`` pixels, and keeps the pixels within
``tolerance`` of the micro-image's lit level (its ``LEVEL_QUANTILE`` over the plateau):
the rest are left out of the corners' and the edge spreads' profiles. Micro-images
inside the vignetting's onset are not marked (the plateau's radius already bounds them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter

from .flat_field import FlatField
from .lens_grid import LensGrid

SMOOTH_PX = 5
"""Side of the box the white image's ratio to its shading is averaged over (pixels)."""

LEVEL_QUANTILE = 0.9
"""A vignetted micro-image's lit level: this quantile of its smoothed ratio over the plateau."""

MIN_TOLERANCE = 2e-3
"""A pixel whose aperture is clipped by less than this fraction is kept."""

NOISE_SIGMAS = 4.0
"""The tolerance is at least this many standard deviations of the smoothed ratio's noise."""

CHUNK = 256
"""Micro-images processed at once (memory: ~5 MB each for 100 px lenses)."""


@dataclass(frozen=True, eq=False)
class ApertureMask:
    """``full[y, x]``: whether the pixel sees its whole microlens aperture (True outside the
    vignetted micro-images); ``micro_images`` the vignetted micro-images marked,
    ``tolerance`` the clipped fraction a kept pixel may have; the vignetted micro-images
    are those centred farther than ``onset_px`` from ``principal_point_px``."""

    full: NDArray[np.bool_]
    micro_images: int
    tolerance: float
    principal_point_px: tuple[float, float]
    onset_px: float

    def vignetted(self, x: NDArray[Any], y: NDArray[Any]) -> NDArray[np.bool_]:
        """Whether micro-images centred at ``x``, ``y`` (px) are vignetted."""
        px, py = self.principal_point_px
        return np.asarray(np.hypot(np.asarray(x) - px, np.asarray(y) - py) > self.onset_px)

    def at(self, rows: NDArray[Any], cols: NDArray[Any]) -> NDArray[np.bool_]:
        """The mask at integer pixel ``rows``, ``cols`` (same shape; False off the sensor)."""
        r = np.asarray(rows, dtype=np.intp)
        c = np.asarray(cols, dtype=np.intp)
        h, w = self.full.shape
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        out = np.zeros(r.shape, dtype=bool)
        out[inside] = self.full[r[inside], c[inside]]
        return out


def full_aperture_mask(
    white: NDArray[Any],
    image_grid: LensGrid,
    lens_grid: LensGrid,
    flat_field: FlatField,
    *,
    plateau_px: float,
    principal_point_px: tuple[float, float],
    onset_px: float,
) -> ApertureMask | None:
    """The mask of the micro-images farther than ``onset_px`` from ``principal_point_px``
    (None when none is: no vignetting). ``plateau_px``: the plateau's radius (px), the
    part of each micro-image the profiles may use; ``flat_field``: the shading about each
    micro-image centre (its ``background`` is subtracted)."""
    if not math.isfinite(onset_px):
        return None
    img = np.asarray(white, dtype=np.float64)
    h, w = img.shape
    ii, jj = image_grid.indices_in(w, h, margin_px=0.0)
    cx, cy = image_grid.centre(ii, jj)
    far = np.hypot(cx - principal_point_px[0], cy - principal_point_px[1]) > onset_px
    ii, jj = ii[far], jj[far]
    full = np.ones((h, w), dtype=bool)
    if ii.size == 0:
        return ApertureMask(full, 0, MIN_TOLERANCE, principal_point_px, onset_px)
    patches = _Patches(img, image_grid, lens_grid, flat_field, plateau_px)
    # the smoothed ratio's noise, from the pixels' scatter about it on the lit plateau of
    # up to CHUNK micro-images spread over the vignetted field
    sample = np.linspace(0, ii.size - 1, min(CHUNK, ii.size)).astype(np.intp)
    _, _, disc, filled, smooth, level = patches.ratio(ii[sample], jj[sample])
    lit = disc & (smooth >= 0.98 * level[:, None, None])  # False where level is NaN
    rel = (filled - smooth)[lit] / np.broadcast_to(level[:, None, None], lit.shape)[lit]
    pixel_noise = 1.4826 * float(np.median(np.abs(rel))) if rel.size else 0.0
    tolerance = max(MIN_TOLERANCE, NOISE_SIGMAS * pixel_noise / SMOOTH_PX)
    for start in range(0, ii.size, CHUNK):
        rows, cols, disc, _, smooth, level = patches.ratio(
            ii[start : start + CHUNK], jj[start : start + CHUNK]
        )
        keep = smooth >= level[:, None, None] * (1.0 - tolerance)
        # only each micro-image's own plateau is written (patches do not reach a neighbour's);
        # an unlit one (level NaN) keeps nothing
        full[rows[disc], cols[disc]] = keep[disc]
    return ApertureMask(full, int(ii.size), tolerance, principal_point_px, onset_px)


class _Patches:
    """The white image about vignetted micro-images, divided by the shading and smoothed."""

    def __init__(
        self,
        img: NDArray[np.float64],
        image_grid: LensGrid,
        lens_grid: LensGrid,
        flat_field: FlatField,
        plateau_px: float,
    ) -> None:
        self.img, self.image_grid, self.lens_grid = img, image_grid, lens_grid
        self.flat_field, self.plateau_px = flat_field, plateau_px
        self.half = int(math.ceil(plateau_px)) + SMOOTH_PX // 2 + 1

    def ratio(self, ii: NDArray[np.int64], jj: NDArray[np.int64]) -> tuple[NDArray[Any], ...]:
        """Per micro-image ``(i, j)``: the patch's pixel rows and columns, its plateau
        (``disc``), the white over the shading there (``filled``, 0 elsewhere), that
        averaged over ``SMOOTH_PX``² plateau pixels (``smooth``) and the lit ``level``."""
        img, ff = self.img, self.flat_field
        h, w = img.shape
        cx, cy = self.image_grid.centre(ii, jj)
        gx, gy = ff.gradients((cx, cy), self.lens_grid.centre(ii, jj))
        x0, y0 = np.rint(cx).astype(np.intp), np.rint(cy).astype(np.intp)
        off = np.arange(-self.half, self.half + 1)
        shape = (ii.size, off.size, off.size)
        rows = np.broadcast_to(y0[:, None, None] + off[None, :, None], shape)
        cols = np.broadcast_to(x0[:, None, None] + off[None, None, :], shape)
        on_sensor = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        values = img[np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)] - ff.background
        dx, dy = cols - cx[:, None, None], rows - cy[:, None, None]
        rr = dx * dx + dy * dy
        log_w = ff.log_shading((dx, dy), (gx[:, None, None], gy[:, None, None]))
        disc = (rr <= self.plateau_px**2) & on_sensor
        # averaged over the plateau only (normalised convolution): the rim beyond it falls
        filled = np.where(disc, values * np.exp(-log_w), 0.0)
        size = (1, SMOOTH_PX, SMOOTH_PX)
        weight = uniform_filter(disc.astype(np.float64), size=size, mode="constant")
        smooth = uniform_filter(filled, size=size, mode="constant") / np.maximum(weight, 1e-12)
        level = np.array(
            [
                np.quantile(s[d], LEVEL_QUANTILE) if d.any() else np.nan
                for s, d in zip(smooth, disc, strict=True)
            ]
        )
        level = np.where(level > 0, level, np.nan)  # a micro-image the vignetting darkens whole
        return rows, cols, disc, filled, smooth, level
