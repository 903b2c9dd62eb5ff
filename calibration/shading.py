"""Angular shading of the rays inside a micro-image, from the white image, and the disparity bias it causes.

Every ray that reaches sensor point ``s`` through aperture point ``p`` of its
microlens carries a weight ``w(s - p)`` that depends on its angle at the
sensor: ``cos⁴`` of that angle, the pixels' angular response, a stack's
acceptance. A defocused point is blurred into the aperture scaled by
``(Q - Q0)`` (OPTICS.md §1), so the weights shift the blur's centroid by

    (Q - Q0) · ⟨p - m⟩_w = -(Q - Q0) · Var(p) · ∇ log W(s)

where ``W(s) = ∫ w(s - p) dp`` is what the white image shows at ``s`` and
``Var(p)`` the aperture's variance along one axis. With the usual falloff
``log W ≈ const - (c/2)·|s - m|²`` about the lens centre ``m`` every corner
image moves by ``(Q - Q0)·Var·c·(s - m)``, and because ``s - m = Q·(m - r)``
the disparity fit then measures ``Q·(1 + η·(Q - Q0))`` with

    η = Var(p) · c     (pixels² times pixels⁻²: dimensionless).

The main-image positions are unchanged. Over a sweep this tilts ``1/Q(v)``
and biases ``b`` from its slope by ``-η·Q0`` (about -0.03 % for the paper's
optics with ``cos⁴``), so the calibration corrects ``Q`` with ``η``, measured
here: ``c`` is the curvature of ``log W`` inside the fully lit interior of the
micro-images, one value for the sensor, fitted with a free level and
gradient per micro-image (the gradient absorbs the tilt of off-axis
micro-images).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid

INTERIOR_FRACTION = 0.6
"""Radius of the fully lit interior used, as a fraction of half the micro-image pitch."""

MAX_MICRO_IMAGES = 600
"""At most this many micro-images (evenly spread over the sensor) are measured."""


@dataclass(frozen=True)
class WhiteShading:
    """``c``: curvature of ``-log W`` in micro-images (px⁻²) and its standard error."""

    curvature_px2: float
    curvature_se_px2: float
    micro_images: int

    def bias_coefficient(self, aperture_variance_px2: float) -> float:
        """``η = Var(p)·c``: the disparity reads ``Q·(1 + η·(Q - Q0))``."""
        return aperture_variance_px2 * self.curvature_px2

    def to_dict(self) -> dict[str, Any]:
        return {
            "curvature_px2": self.curvature_px2,
            "curvature_se_px2": self.curvature_se_px2,
            "micro_images": self.micro_images,
        }


def measure_shading(
    white: NDArray[Any], image_grid: LensGrid, *, background: float = 0.0
) -> WhiteShading:
    """The curvature of ``log W`` inside the micro-images of a white image.

    ``image_grid`` is the fitted micro-image lattice (pixels);
    ``background`` the dark level to subtract (counts).
    """
    img = np.asarray(white, dtype=np.float64) - background
    h, w = img.shape
    pitch = image_grid.pitch_px
    radius = INTERIOR_FRACTION * 0.5 * pitch
    ii, jj = image_grid.indices_in(w, h, margin_px=radius + 1)
    if ii.size == 0:
        return WhiteShading(float("nan"), float("nan"), 0)
    keep = np.linspace(0, ii.size - 1, min(MAX_MICRO_IMAGES, ii.size)).astype(np.int64)
    ii, jj = ii[keep], jj[keep]
    cx, cy = image_grid.centre(ii, jj)
    r = int(np.ceil(radius))
    oy, ox = np.mgrid[-r : r + 1, -r : r + 1]
    # per micro-image: pixels of its interior disc about its (sub-pixel) centre
    x0 = np.rint(cx).astype(np.int64)
    y0 = np.rint(cy).astype(np.int64)
    xs = x0[:, None, None] + ox[None]
    ys = y0[:, None, None] + oy[None]
    dx = xs - cx[:, None, None]
    dy = ys - cy[:, None, None]
    inside = (dx * dx + dy * dy) <= radius * radius
    values = img[np.clip(ys, 0, h - 1), np.clip(xs, 0, w - 1)]
    level = np.nanmedian(np.where(inside, values, np.nan).reshape(ii.size, -1), axis=1)
    lit = level > 0.2 * np.nanmax(level)
    good = inside & (values > 0.3 * level[:, None, None]) & lit[:, None, None]
    logv = np.where(good, np.log(np.maximum(values, 1e-9)), 0.0)
    # fixed effects: regress out a level and a gradient per micro-image, then one curvature
    rr = dx * dx + dy * dy
    regs = [np.ones_like(dx), dx, dy]
    y = _residual_after(logv, regs, good)
    x = _residual_after(rr, regs, good)
    sxx = float(np.sum(np.where(good, x * x, 0.0)))
    if sxx <= 0:
        return WhiteShading(float("nan"), float("nan"), 0)
    slope = float(np.sum(np.where(good, x * y, 0.0)) / sxx)
    resid = np.where(good, y - slope * x, 0.0)
    n = int(good.sum())
    dof = max(1, n - 3 * ii.size - 1)
    sigma2 = float(np.sum(resid * resid) / dof)
    # pixels of one micro-image share its noise only through the fitted level: independent
    se = float(np.sqrt(sigma2 / sxx))
    return WhiteShading(curvature_px2=-2.0 * slope, curvature_se_px2=2.0 * se, micro_images=ii.size)


def _residual_after(
    values: NDArray[np.float64], regressors: list[NDArray[np.float64]], mask: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """``values`` minus their per-micro-image least-squares fit on ``regressors`` (masked)."""
    n = values.shape[0]
    k = len(regressors)
    a = np.stack([np.where(mask, r, 0.0).reshape(n, -1) for r in regressors], axis=2)
    v = np.where(mask, values, 0.0).reshape(n, -1)
    ata = np.einsum("npk,npl->nkl", a, a) + 1e-12 * np.eye(k)[None]
    atv = np.einsum("npk,np->nk", a, v)
    coef = np.linalg.solve(ata, atv[:, :, None])[:, :, 0]
    fitted = np.einsum("npk,nk->np", a, coef)
    return (v - fitted).reshape(values.shape)
