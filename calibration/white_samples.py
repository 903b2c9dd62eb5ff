"""White-image pixels about micro-image centres, and per-micro-image least squares on them.

Shared by the white image's shading (:mod:`calibration.shading`) and its rings
(:mod:`calibration.white_rings`). Offsets in pixels from the micro-image centres of the
fitted lattice; arrays ``(micro-image, row, column)``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid


class MicroImageSamples(NamedTuple):
    """White-image pixels of some micro-images, arrays ``(micro-image, row, column)``:
    offsets from the micro-image centre (px), values (background subtracted), the usable
    mask; and the micro-images' lattice indices."""

    dx: NDArray[np.float64]
    dy: NDArray[np.float64]
    values: NDArray[np.float64]
    good: NDArray[np.bool_]
    ii: NDArray[np.int64]
    jj: NDArray[np.int64]

    @property
    def n_images(self) -> int:
        return int(self.ii.size)

    def log_values(self) -> NDArray[np.float64]:
        """``log W`` on the usable pixels, 0 elsewhere."""
        return np.where(self.good, np.log(np.maximum(self.values, 1e-9)), 0.0)


def spread_micro_images(
    image_grid: LensGrid,
    shape: tuple[int, int],
    *,
    margin_px: float,
    max_images: int,
    unvignetted: tuple[tuple[float, float], float] | None = None,
    extent_px: float = 0.0,
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Lattice indices ``(i, j)`` of up to ``max_images`` micro-images evenly spread over a
    sensor of ``shape`` (rows, columns), their centres at least ``margin_px`` inside it and,
    with ``unvignetted`` (principal point, radius px), at most that radius less
    ``extent_px`` from the principal point; None when there is none."""
    h, w = shape
    ii, jj = image_grid.indices_in(w, h, margin_px=margin_px)
    if unvignetted is not None and ii.size:
        (px, py), limit = unvignetted
        cx, cy = image_grid.centre(ii, jj)
        inside = np.hypot(cx - px, cy - py) + extent_px <= limit
        ii, jj = ii[inside], jj[inside]
    if ii.size == 0:
        return None
    keep = np.linspace(0, ii.size - 1, min(max_images, ii.size)).astype(np.int64)
    return ii[keep], jj[keep]


def micro_image_samples(
    white: NDArray[Any],
    image_grid: LensGrid,
    background: float,
    fraction: float,
    *,
    max_images: int,
    unvignetted: tuple[tuple[float, float], float] | None = None,
) -> MicroImageSamples | None:
    """Pixels within ``fraction`` of half the pitch of up to ``max_images`` lit
    micro-images (evenly spread over the sensor, within ``unvignetted``'s radius of its
    principal point when given)."""
    img = np.asarray(white, dtype=np.float64) - background
    h, w = img.shape
    pitch = image_grid.pitch_px
    radius = fraction * 0.5 * pitch
    chosen = spread_micro_images(
        image_grid, (h, w), margin_px=radius + 1, max_images=max_images, unvignetted=unvignetted
    )
    if chosen is None:
        return None
    ii, jj = chosen
    cx, cy = image_grid.centre(ii, jj)
    r = int(np.ceil(radius))
    oy, ox = np.mgrid[-r : r + 1, -r : r + 1]
    # per micro-image: pixels of its disc about its (sub-pixel) centre
    x0 = np.rint(cx).astype(np.int64)
    y0 = np.rint(cy).astype(np.int64)
    xs = x0[:, None, None] + ox[None]
    ys = y0[:, None, None] + oy[None]
    dx = xs - cx[:, None, None]
    dy = ys - cy[:, None, None]
    inside = (dx * dx + dy * dy) <= radius * radius
    values = img[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
    core = inside & ((dx * dx + dy * dy) <= (0.3 * pitch) ** 2)
    level = np.nanmedian(np.where(core, values, np.nan).reshape(ii.size, -1), axis=1)
    lit = level > 0.2 * np.nanmax(level)
    good = inside & (values > 0.3 * level[:, None, None]) & lit[:, None, None]
    return MicroImageSamples(dx, dy, values, good, ii, jj)


def per_image_fit(
    values: NDArray[np.float64], regressors: list[NDArray[np.float64]], mask: NDArray[np.bool_]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least squares of ``values`` on ``regressors`` per micro-image (first axis) over the
    ``mask``ed pixels: the coefficients ``(n, k, 1)`` and the masked values minus the fit
    ``(n, pixels)``."""
    n = values.shape[0]
    k = len(regressors)
    a = np.stack([np.where(mask, r, 0.0).reshape(n, -1) for r in regressors], axis=2)
    v = np.where(mask, values, 0.0).reshape(n, -1)
    at = np.swapaxes(a, 1, 2)
    coef = np.linalg.solve(at @ a + 1e-12 * np.eye(k)[None], at @ v[:, :, None])
    return coef, v - (a @ coef)[:, :, 0]


def residual_after(
    values: NDArray[np.float64], regressors: list[NDArray[np.float64]], mask: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """``values`` minus their per-micro-image least-squares fit on ``regressors`` (masked)."""
    return per_image_fit(values, regressors, mask)[1].reshape(values.shape)
