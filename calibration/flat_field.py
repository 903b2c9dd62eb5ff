"""The white image's smooth shading about each micro-image centre, divided out of edge profiles.

Inside a micro-image the white image falls off as a bowl (rims blurred inwards,
vignetting; curvature ``c`` of ``-log W``) tilted off the axis by the angular shading
(its curvature ``c_t``), so that about the micro-image centre ``c_i``

    log W(s) = g_i·(s - c_i) - (c/2)·|s - c_i|²,   g_i = -c_t·(c_i - m_i),

``m_i`` the lens centre (:class:`calibration.shading.WhiteShading` measures ``c`` and
``c_t``). A frame's samples above the white's dark level are divided by it before their
levels are read (:mod:`calibration.edge_profiles`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class FlatField:
    """``curvature_px2``: ``c`` (px⁻²); ``background``: the white image's dark level
    (counts), the offset the flat field leaves alone; ``tilt_curvature_px2``: ``c_t``
    (px⁻²). All zero: no flat field."""

    curvature_px2: float = 0.0
    background: float = 0.0
    tilt_curvature_px2: float = 0.0

    @property
    def active(self) -> bool:
        """Whether there is a shading to divide by."""
        return bool(self.curvature_px2 or self.tilt_curvature_px2)

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

    def divide(
        self,
        values: NDArray[np.float64],
        offset: tuple[NDArray[np.float64], NDArray[np.float64]],
        gradient: tuple[NDArray[np.float64], NDArray[np.float64]],
    ) -> NDArray[np.float64]:
        """``values`` (counts) at ``offset`` (x, y; px) from their micro-image centre,
        divided by the shading above the dark level; ``gradient`` the micro-image's ``g_i``
        (broadcast against ``values``)."""
        dx, dy = offset
        log_w = gradient[0] * dx + gradient[1] * dy - 0.5 * self.curvature_px2 * (dx * dx + dy * dy)
        return self.background + (values - self.background) * np.exp(-log_w)
