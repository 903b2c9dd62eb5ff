"""The white image's smooth shading about each micro-image centre, divided out of edge profiles.

Inside a micro-image the white image falls off as a bowl (rims blurred inwards,
vignetting, the main aperture's footprint clipping the microlens's beyond the fully lit
plateau) tilted off the axis by the angular shading (curvature ``c_t``), so that about
the micro-image centre ``c_i``

    log W(s) = g_i·(s - c_i) + R(|s - c_i|),   g_i = -c_t·(c_i - m_i),

``m_i`` the lens centre. ``R`` is the micro-images' mean radial profile of ``log W``,
measured on the white image in rings about their centres
(:func:`calibration.shading.measure_shading`), or, without one, the paraboloid
``-(c/2)·ρ²`` of the curvature ``c`` inside them. The paraboloid describes the bowl only
on the plateau: beyond it the white falls far faster (by 14 % at 0.75 of the radius
on a Monte-Carlo white with the microlenses' diffraction, where the paraboloid fell by
3 %), and an edge profile reaching there, divided by too little, pulled its corner
towards the micro-image centre and read ``Q`` 0.1 % low. A frame's samples above the
white's dark level are divided by the bowl before their levels are read
(:mod:`calibration.edge_profiles`, :mod:`calibration.corners`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class FlatField:
    """``curvature_px2``: ``c`` (px⁻²); ``background``: the white image's dark level
    (counts), the offset the flat field leaves alone; ``tilt_curvature_px2``: ``c_t``
    (px⁻²); ``radial_px`` and ``radial_log_w``: ``R`` tabulated (ring radii, px, rising;
    ``log W`` there, 0 at the centre), linear between them and held beyond the last; empty:
    the paraboloid of ``c``. All zero and empty: no flat field."""

    curvature_px2: float = 0.0
    background: float = 0.0
    tilt_curvature_px2: float = 0.0
    radial_px: tuple[float, ...] = ()
    radial_log_w: tuple[float, ...] = ()

    @property
    def active(self) -> bool:
        """Whether there is a shading to divide by."""
        return bool(self.curvature_px2 or self.tilt_curvature_px2 or self.radial_px)

    def gradients(
        self,
        centre: tuple[NDArray[np.float64], NDArray[np.float64]],
        lens: tuple[NDArray[np.float64], NDArray[np.float64]],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``g_i`` (x, y; per px) of micro-images centred at ``centre`` with lens centres
        ``lens`` (sensor pixels)."""
        return (
            -self.tilt_curvature_px2 * (centre[0] - lens[0]),
            -self.tilt_curvature_px2 * (centre[1] - lens[1]),
        )

    def log_shading(
        self,
        offset: tuple[NDArray[np.float64], NDArray[np.float64]],
        gradient: tuple[NDArray[np.float64], NDArray[np.float64]],
    ) -> NDArray[np.float64]:
        """``log W`` at ``offset`` (x, y; px) from the micro-image centre, relative to the
        centre; ``gradient`` the micro-image's ``g_i`` (broadcast against the offsets)."""
        dx, dy = offset
        rr = dx * dx + dy * dy
        if self.radial_px:
            bowl = np.interp(np.sqrt(rr), self.radial_px, self.radial_log_w)
        else:
            bowl = -0.5 * self.curvature_px2 * rr
        return np.asarray(gradient[0] * dx + gradient[1] * dy + bowl, dtype=np.float64)

    def divide(
        self,
        values: NDArray[np.float64],
        offset: tuple[NDArray[np.float64], NDArray[np.float64]],
        gradient: tuple[NDArray[np.float64], NDArray[np.float64]],
    ) -> NDArray[np.float64]:
        """``values`` (counts) at ``offset`` (x, y; px) from their micro-image centre,
        divided by the shading above the dark level; ``gradient`` the micro-image's ``g_i``
        (broadcast against ``values``)."""
        log_w = self.log_shading(offset, gradient)
        return self.background + (values - self.background) * np.exp(-log_w)
