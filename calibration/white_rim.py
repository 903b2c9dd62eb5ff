"""The blur of the micro-images' rims in a white image: the microlens aperture, measured far from focus.

A micro-image of a white image is the main aperture seen through its microlens. The main
aperture lies at distance ``L`` in front of the MLA, so like any point at that distance it
is imaged with ``Q = b/L = β`` (``β = (L+b)/L - 1``, the white's measured scale less one)
and blurred by the microlens aperture scaled to ``(D/δ)·|Q0 - β|`` pixels (OPTICS.md §1;
ray by ray: a ray through aperture point ``m`` reaches the sensor ``(β - Q0)·m`` from where
the lens centre's ray does), then by the static blur (pixel response, lens PSF,
diffraction). For the cameras here that is 12-17 px, five to ten times the largest defocus
of a corner in a sweep and several times a diffraction pattern: the rim measures the
aperture by geometric optics, whatever the edges near focus do. Its blur's variance along
the rim's normal is

    Var_rim = κ²·((D/δ)·|Q0 - β|)²/12 + Var_static

with ``κ`` the aperture's RMS scale as :mod:`calibration.defocus` defines it (the
variance of a square's or a disc's projection is the same in every direction, so the
rim's variance is too), which the defocus fit of the corners must agree with.

:func:`measure_rim` measures ``Var_rim`` from moments of the rim's mean radial profile,
``I(r)`` from 1 on the plateau to 0 outside, without a model of its shape: with ``u`` from
a radius inside the plateau, ``∫I du`` is the rim's mean radius and ``2∫I·u du - (∫I du)²``
its variance. It uses the pixels within ``RIM_HALF_ANGLE_DEG`` of the lattice's diagonals,
where a micro-image's cell (the pixels nearest its centre, OPTICS.md §2) reaches farthest,
of micro-images clear of the main lens's vignetting, each scaled by its own plateau. The
disc's curvature changes the variance by about ``Var²/(2R²)``, 1 % for these rims. On the
whites of four renderers (50 px square lenses: 12.60-12.65 px² on mcsim, indsim and
wavesim where ``κ = 1`` gives 12.38; round lenses 9.54 against 9.29; 80 and 120 px lenses
24.84 and 24.74 against 24.2 and 24.6) it is within 3 % of the optics, and the ``κ`` it
gives within 1-6 % of the defocus fit's on 20 random ray-traced cameras.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid
from .white_samples import spread_micro_images

RIM_HALF_ANGLE_DEG = 10.0
"""Pixels within this angle (degrees) of a diagonal of the lattice are used: there the cell
reaches ``√2`` times half the pitch from the centre, room for the rim's outer tail."""

RIM_BIN_PX = 0.25
"""Radial bin of the rim's profile (pixels)."""

RIM_INNER_FRACTION = 0.15
"""The profile's moments start at this fraction of the pitch from the centre (inside the
plateau; each micro-image's level is the median inside it)."""

RIM_MAX_MICRO_IMAGES = 200
"""The rim is measured on at most this many micro-images (evenly spread)."""

RIM_TAIL_MAX = 0.01
"""The profile must have fallen below this fraction of the plateau before the cell's
corner (otherwise the rim is cut by the cell: overlapping micro-images), and start within
it of the plateau (otherwise the rim reaches the micro-image's centre); else it is not
measured."""


@dataclass(frozen=True)
class WhiteRim:
    """The micro-images' rim in a white image: the variance of its blur along its normal
    (px²), its mean radius (px, where the disc's edge is) and the micro-images measured."""

    variance_px2: float
    radius_px: float
    micro_images: int

    def aperture_scale(
        self, *, q0: float, q_rim: float, lens_pitch_px: float, static_rms_px: float
    ) -> float:
        """``κ`` the rims show: ``√(12·(Var_rim - static²))/((D/δ)·|Q0 - β|)``.

        ``q_rim`` is ``β = b/L``; ``static_rms_px`` the static blur's RMS (px) a defocus fit
        found, taken off the rim's variance (the larger it is, the smaller the ``κ``); NaN
        when the rim's defocus is zero."""
        defocus_px = lens_pitch_px * abs(q0 - q_rim)
        if not defocus_px > 0:
            return float("nan")
        aperture_var = max(self.variance_px2 - static_rms_px**2, 0.0)
        return float(np.sqrt(12.0 * aperture_var) / defocus_px)

    def to_dict(self) -> dict[str, Any]:
        return {
            "variance_px2": self.variance_px2,
            "radius_px": self.radius_px,
            "micro_images": self.micro_images,
        }


def measure_rim(
    white: NDArray[Any],
    image_grid: LensGrid,
    *,
    background: float = 0.0,
    unvignetted: tuple[tuple[float, float], float] | None = None,
) -> WhiteRim | None:
    """The rim of the micro-images of a white image (module docstring); None when no
    micro-image is clear of the sensor's edges and the vignetting, or when the rim is cut
    by the cells (it has not fallen to ``RIM_TAIL_MAX`` before their corners).

    ``image_grid``: the micro-image lattice (px); ``background``: the dark level (counts);
    ``unvignetted``: the principal point and the radius about it (px) within which the
    micro-images are whole (:mod:`calibration.vignetting`).
    """
    pitch = image_grid.pitch_px
    half = 0.5 * pitch
    reach = float(np.sqrt(2.0) * half)
    chosen = spread_micro_images(
        image_grid,
        white.shape,
        margin_px=reach + 1.0,
        max_images=RIM_MAX_MICRO_IMAGES,
        unvignetted=unvignetted,
        extent_px=reach,
    )
    if chosen is None:
        return None
    ii, jj = chosen
    cx, cy = image_grid.centre(ii, jj)
    c, s = np.cos(image_grid.rotation_rad), np.sin(image_grid.rotation_rad)
    ox, oy = _candidate_offsets(reach, RIM_INNER_FRACTION * pitch, c, s)
    xs = np.rint(cx).astype(np.int64)[:, None] + ox[None]
    ys = np.rint(cy).astype(np.int64)[:, None] + oy[None]
    dx, dy = xs - cx[:, None], ys - cy[:, None]
    # lattice-aligned offsets: the cell is |du|, |dv| <= half the pitch
    du, dv = c * dx + s * dy, -s * dx + c * dy
    values = np.asarray(white, dtype=np.float64)[ys, xs] - background
    radius = np.hypot(du, dv)
    core = radius <= RIM_INNER_FRACTION * pitch
    level = np.nanmedian(np.where(core, values, np.nan), axis=1)
    lit = np.isfinite(level) & (level > 0)
    if not lit.any():
        return None
    scaled = values[lit] / level[lit][:, None]
    du, dv, radius = du[lit], dv[lit], radius[lit]
    angle = np.degrees(np.arctan2(np.abs(dv), np.abs(du)))
    in_cell = (np.abs(du) <= half) & (np.abs(dv) <= half)
    use = in_cell & (np.abs(angle - 45.0) <= RIM_HALF_ANGLE_DEG)
    start = RIM_INNER_FRACTION * pitch
    edges = np.arange(start, reach, RIM_BIN_PX)
    which = np.digitize(radius[use], edges) - 1
    ok = (which >= 0) & (which < edges.size - 1)
    bins = edges.size - 1
    count = np.bincount(which[ok], minlength=bins)
    total = np.bincount(which[ok], weights=scaled[use][ok], minlength=bins)
    filled = np.flatnonzero(count > 0)
    # the profile runs from the plateau to the last filled bin before the cell's corner
    last = int(filled[-1]) if filled.size else -1
    if last < 4 or not np.all(count[: last + 1] > 0):
        return None
    profile = np.clip(total[: last + 1] / count[: last + 1], 0.0, None)
    if (
        float(profile[-4:].max()) > RIM_TAIL_MAX
        or abs(float(profile[:4].mean()) - 1.0) > RIM_TAIL_MAX
    ):
        return None
    u = (np.arange(last + 1) + 0.5) * RIM_BIN_PX
    first = float(np.sum(profile) * RIM_BIN_PX)
    second = float(2.0 * np.sum(profile * u) * RIM_BIN_PX)
    return WhiteRim(
        variance_px2=second - first * first,
        radius_px=start + first,
        micro_images=int(lit.sum()),
    )


def _candidate_offsets(
    reach: float, core_px: float, c: float, s: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Whole-pixel offsets ``(x, y)`` from a micro-image's nearest pixel that can fall in the
    core (within ``core_px`` of its centre) or within ``RIM_HALF_ANGLE_DEG`` of a diagonal
    of the lattice (rotation cosine ``c``, sine ``s``) for any sub-pixel centre: the
    rest of the patch is never used."""
    r = int(np.ceil(reach)) + 1
    oy, ox = np.mgrid[-r : r + 1, -r : r + 1]
    u, v = c * ox + s * oy, -s * ox + c * oy
    radius = np.hypot(u, v)
    angle = np.degrees(np.arctan2(np.abs(v), np.abs(u)))
    # a centre up to 0.71 px from the pixel turns an offset by up to asin(0.71/radius)
    slack = np.degrees(np.arcsin(np.minimum(1.0, 0.75 / np.maximum(radius, 0.75))))
    keep = radius <= core_px + 1.0
    keep |= (np.abs(angle - 45.0) <= RIM_HALF_ANGLE_DEG + slack) & (radius <= reach + 1.0)
    return ox[keep].astype(np.int64), oy[keep].astype(np.int64)
