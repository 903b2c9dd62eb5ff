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

That tilt measures ``c`` a second way (:func:`_tilt_curvature`): the paraboloid is
centred on the lens centre ``m``, not on the micro-image centre ``c_i = m +
β·(m - axis)``, so the gradient of ``log W`` at ``c_i`` is ``-c·(c_i - m)``, linear
across the sensor. A micro-image rim blurred into the interior (diffraction's
1/x² tails) bends ``log W`` symmetrically about ``c_i``: it adds curvature inside
every micro-image (19× the rays' cos⁴ on a Monte-Carlo white image with a
diffraction-limited microlens at f/15.6) but no tilt (the tilt gave the cos⁴ value
within 4 %). When the two disagree, the tilt is the angular shading.

The same white image says where that interior ends, and how it falls beyond
(:mod:`calibration.white_rings`): the flat field edge profiles are divided by
(:meth:`WhiteShading.flat_field`) is the paraboloid of ``c`` on the plateau and the
measured fall beyond it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .flat_field import FlatField
from .lens_grid import LensGrid
from .white_rings import white_rings
from .white_samples import (
    MicroImageSamples,
    micro_image_samples,
    per_image_fit,
    residual_after,
)

INTERIOR_FRACTION = 0.6
"""Radius of the fully lit interior used, as a fraction of half the micro-image pitch."""

MAX_MICRO_IMAGES = 600
"""At most this many micro-images (evenly spread over the sensor) are measured."""

RADIAL_CONSISTENCY_SIGMAS = 3.0
"""The curvature measured inside half the radius must agree with the whole interior's within
this many combined standard errors; otherwise the white image's falloff is not angular
shading alone (see :meth:`WhiteShading.angular_curvature`)."""

TILT_CONSISTENCY_SIGMAS = 3.0
"""The curvature inside the micro-images and the one from their tilt across the sensor
agree when within this many combined standard errors; otherwise the former is taken to be
bent by the rims (see :meth:`WhiteShading.angular_curvature`)."""

TILT_MIN_MICRO_IMAGES = 10
"""Fewest micro-images for a curvature from their tilt."""


@dataclass(frozen=True)
class WhiteShading:
    """``c``: curvature of ``-log W`` in micro-images (px⁻²) and its standard error."""

    curvature_px2: float
    curvature_se_px2: float
    micro_images: int
    plateau_fraction: float = float("nan")
    """Radius of the fully lit interior, fraction of half the micro-image pitch (NaN: not
    measured)."""
    inner_curvature_px2: float = float("nan")
    """The same curvature fitted inside half that radius (NaN: not measured)."""
    inner_curvature_se_px2: float = float("nan")
    tilt_curvature_px2: float = float("nan")
    """The curvature from the tilt of the micro-images across the sensor (NaN: not measured,
    e.g. no lens grid given or too few micro-images off the axis)."""
    tilt_curvature_se_px2: float = float("nan")
    radial_px: tuple[float, ...] = ()
    """Radii (px from the micro-image centres) of the flat field's bowl
    (:attr:`radial_log_w`, ``log W``): the paraboloid of :attr:`curvature_px2` on the
    plateau, the white's measured fall beyond it
    (:meth:`calibration.white_rings.WhiteRings.bowl`); empty: the paraboloid everywhere."""
    radial_log_w: tuple[float, ...] = ()

    @property
    def radially_consistent(self) -> bool:
        """Whether the curvature is the same inside half the radius as over the whole
        interior (within :data:`RADIAL_CONSISTENCY_SIGMAS`; true when not measured)."""
        if not (np.isfinite(self.inner_curvature_px2) and np.isfinite(self.curvature_px2)):
            return True
        se = float(np.hypot(self.curvature_se_px2, self.inner_curvature_se_px2))
        return abs(self.curvature_px2 - self.inner_curvature_px2) <= RADIAL_CONSISTENCY_SIGMAS * se

    @property
    def tilt_measured(self) -> bool:
        return bool(np.isfinite(self.tilt_curvature_px2) and self.tilt_curvature_se_px2 > 0)

    @property
    def tilt_consistent(self) -> bool:
        """Whether the curvature inside the micro-images agrees with the one from their tilt
        (within :data:`TILT_CONSISTENCY_SIGMAS`; true when either is not measured)."""
        if not (self.tilt_measured and np.isfinite(self.curvature_px2)):
            return True
        se = float(np.hypot(self.curvature_se_px2, self.tilt_curvature_se_px2))
        return abs(self.curvature_px2 - self.tilt_curvature_px2) <= TILT_CONSISTENCY_SIGMAS * se

    @property
    def interior_consistent(self) -> bool:
        """Whether the white image's curvature inside the micro-images is angular shading
        alone (both checks pass); false: a rim is blurred into the interior."""
        return self.radially_consistent and self.tilt_consistent

    def angular_curvature(self) -> tuple[float, float]:
        """``(c, σ)`` of the angular shading (px⁻²).

        The rays' angular weights make ``log W`` a paraboloid about the lens centre,
        the same at every radius, whose tilt across the sensor is ``c`` too. When the
        curvature grows with the radius it is fitted over (:attr:`radially_consistent`
        false) or differs from the tilt's (:attr:`tilt_consistent` false), something else
        bends the white image inside the micro-images: a rim blurred inwards, by
        diffraction above all (a microlens at f/12 in green light spreads ~1/x² tails
        over the whole micro-image; on a Monte-Carlo white image with that diffraction
        the curvature came out 7-19× the rays' cos⁴, 4× even inside a fifth of the
        radius). The tilt is then the angular shading; when both agree, their weighted
        mean. Without a tilt (no lens grid, a window too close to the axis) or one less
        certain than that: light taken from the interior by a blurred rim only adds
        curvature, so the angular part lies between 0 and the measured value: ``c/2 ±
        c/2``, the whole interval within one sigma.
        """
        c, se = self.curvature_px2, self.curvature_se_px2
        if self.tilt_measured and self.interior_consistent and np.isfinite(c) and se > 0:
            w, wt = 1.0 / se**2, 1.0 / self.tilt_curvature_se_px2**2
            return (w * c + wt * self.tilt_curvature_px2) / (w + wt), float(1.0 / np.sqrt(w + wt))
        if self.interior_consistent:
            return c, se
        bounded = 0.5 * c, float(np.hypot(se, 0.5 * abs(c)))
        if self.tilt_measured and self.tilt_curvature_se_px2 < bounded[1]:
            return self.tilt_curvature_px2, self.tilt_curvature_se_px2
        return bounded

    def flat_field(self, background: float) -> FlatField | None:
        """The shading edge profiles are divided by (None when the curvature inside the
        micro-images was not measured): that curvature, the white image's dark level
        ``background`` (counts), and the tilt's curvature (the measured tilt, else the
        angular curvature, else 0)."""
        if not np.isfinite(self.curvature_px2):
            return None
        tilt = self.tilt_curvature_px2 if self.tilt_measured else self.angular_curvature()[0]
        return FlatField(
            curvature_px2=self.curvature_px2,
            background=float(background),
            tilt_curvature_px2=float(tilt) if np.isfinite(tilt) else 0.0,
            radial_px=self.radial_px,
            radial_log_w=self.radial_log_w,
        )

    def bias_coefficient(self, aperture_variance_px2: float) -> float:
        """``η = Var(p)·c``: the disparity reads ``Q·(1 + η·(Q - Q0))`` (``c`` the angular
        curvature, :meth:`angular_curvature`)."""
        return aperture_variance_px2 * self.angular_curvature()[0]

    def to_dict(self) -> dict[str, Any]:
        c, c_se = self.angular_curvature()
        return {
            "curvature_px2": self.curvature_px2,
            "curvature_se_px2": self.curvature_se_px2,
            "inner_curvature_px2": self.inner_curvature_px2,
            "inner_curvature_se_px2": self.inner_curvature_se_px2,
            "radially_consistent": self.radially_consistent,
            "tilt_curvature_px2": self.tilt_curvature_px2,
            "tilt_curvature_se_px2": self.tilt_curvature_se_px2,
            "tilt_consistent": self.tilt_consistent,
            "angular_curvature_px2": c,
            "angular_curvature_se_px2": c_se,
            "micro_images": self.micro_images,
            "plateau_fraction": self.plateau_fraction,
        }


def measure_shading(
    white: NDArray[Any],
    image_grid: LensGrid,
    *,
    background: float = 0.0,
    lens_grid: LensGrid | None = None,
    unvignetted: tuple[tuple[float, float], float] | None = None,
) -> WhiteShading:
    """The curvature of ``log W`` inside the micro-images of a white image, and the radius
    of their fully lit plateau.

    ``image_grid`` is the fitted micro-image lattice (pixels);
    ``background`` the dark level to subtract (counts); ``lens_grid`` the lens
    centres' projections (same indices), which the curvature from the micro-images'
    tilt needs (not measured without it); ``unvignetted`` the principal point and the
    radius about it (px) outside which the main lens vignets the micro-images
    (:mod:`calibration.vignetting`): only micro-images inside it are measured. The
    curvature is fitted inside ``INTERIOR_FRACTION`` of the half pitch, or inside the
    plateau when that ends sooner.
    """
    rings = white_rings(white, image_grid, background, unvignetted)
    plateau = float("nan") if rings is None else rings.plateau_fraction()
    fraction = INTERIOR_FRACTION if not np.isfinite(plateau) else min(INTERIOR_FRACTION, plateau)
    samples = micro_image_samples(
        white,
        image_grid,
        background,
        fraction,
        max_images=MAX_MICRO_IMAGES,
        unvignetted=unvignetted,
    )
    if samples is None:
        return WhiteShading(float("nan"), float("nan"), 0, plateau)
    dx, dy, good = samples.dx, samples.dy, samples.good
    n_images = samples.n_images
    logv = samples.log_values()
    rr = dx * dx + dy * dy
    curvature, se = _curvature(logv, dx, dy, good, n_images)
    # the same inside half the radius: angular shading is one paraboloid at every radius
    inner_radius = 0.5 * fraction * 0.5 * image_grid.pitch_px
    inner, inner_se = _curvature(logv, dx, dy, good & (rr <= inner_radius**2), n_images)
    tilt, tilt_se = (
        (float("nan"), float("nan"))
        if lens_grid is None
        else _tilt_curvature(samples, logv, image_grid, lens_grid)
    )
    radial_px, radial_log_w = (
        ((), ()) if rings is None else rings.bowl(curvature, plateau * 0.5 * image_grid.pitch_px)
    )
    return WhiteShading(
        curvature_px2=curvature,
        curvature_se_px2=se,
        micro_images=n_images if np.isfinite(curvature) else 0,
        plateau_fraction=plateau,
        inner_curvature_px2=inner,
        inner_curvature_se_px2=inner_se,
        tilt_curvature_px2=tilt,
        tilt_curvature_se_px2=tilt_se,
        radial_px=radial_px,
        radial_log_w=radial_log_w,
    )


def _tilt_curvature(
    samples: MicroImageSamples, logv: NDArray[np.float64], image_grid: LensGrid, lens_grid: LensGrid
) -> tuple[float, float]:
    """``c`` from the tilt of the micro-images: the gradient of ``log W`` at each centre
    ``c_i`` is ``g_0 - c·(c_i - m_i)`` (``m_i`` its lens centre; ``g_0`` a common tilt),
    each gradient fitted with the micro-image's own level and curvature (which take
    whatever bends it symmetrically). Least squares over both axes, one pass without the
    micro-images beyond 5 robust sigmas (a defect, a dust shadow); its standard error
    from the residual scatter (px⁻²; NaN when the offsets do not determine it).
    """
    dx, dy, good = samples.dx, samples.dy, samples.good
    coef, _ = per_image_fit(logv, [np.ones_like(dx), dx, dy, dx * dx + dy * dy], good)
    n = samples.n_images
    counts = good.reshape(n, -1).sum(axis=1)
    usable = counts >= 0.8 * np.max(counts, initial=0)
    cx, cy = image_grid.centre(samples.ii, samples.jj)
    mx, my = lens_grid.centre(samples.ii, samples.jj)
    gradient = np.concatenate([coef[:, 1, 0], coef[:, 2, 0]])
    offset = np.concatenate([cx - mx, cy - my])
    axis = np.repeat([0, 1], n)
    use = np.concatenate([usable, usable])
    for _ in range(2):
        if use.sum() < 2 * TILT_MIN_MICRO_IMAGES:
            return float("nan"), float("nan")
        g_dev = gradient.copy()
        d_dev = offset.copy()
        for k in (0, 1):  # the common tilt g_0, per axis
            on = use & (axis == k)
            g_dev[axis == k] -= gradient[on].mean()
            d_dev[axis == k] -= offset[on].mean()
        sdd = float(np.sum(d_dev[use] ** 2))
        if sdd <= 1e-6 * use.sum():  # offsets under a milli-pixel: no tilt to see
            return float("nan"), float("nan")
        c = -float(np.sum(g_dev[use] * d_dev[use])) / sdd
        resid = g_dev + c * d_dev
        dof = max(1, int(use.sum()) - 3)
        se = float(np.sqrt(np.sum(resid[use] ** 2) / dof / sdd))
        robust = 1.4826 * float(np.median(np.abs(resid[use])))
        use &= np.abs(resid) <= 5.0 * max(robust, 1e-12)
    return c, se


def _curvature(
    logv: NDArray[np.float64],
    dx: NDArray[np.float64],
    dy: NDArray[np.float64],
    good: NDArray[np.bool_],
    n_images: int,
) -> tuple[float, float]:
    """``c`` of ``log W ≈ level + gradient·(dx, dy) - (c/2)·(dx² + dy²)`` with a level and a
    gradient per micro-image (fixed effects) and one ``c`` for all, over the ``good``
    pixels (``logv``: ``log W``, read only there); and its standard error (px⁻²; NaN when
    the pixels do not determine it)."""
    rr = dx * dx + dy * dy
    regs = [np.ones_like(dx), dx, dy]
    y = residual_after(logv, regs, good)
    x = residual_after(rr, regs, good)
    sxx = float(np.sum(np.where(good, x * x, 0.0)))
    if sxx <= 0:
        return float("nan"), float("nan")
    slope = float(np.sum(np.where(good, x * y, 0.0)) / sxx)
    resid = np.where(good, y - slope * x, 0.0)
    n = int(good.sum())
    dof = max(1, n - 3 * n_images - 1)
    sigma2 = float(np.sum(resid * resid) / dof)
    # pixels of one micro-image share its noise only through the fitted level: independent
    return -2.0 * slope, 2.0 * float(np.sqrt(sigma2 / sxx))
