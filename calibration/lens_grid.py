"""Square microlens-array lattice in sensor pixel coordinates (``shared/OPTICS.md`` §2).

Lens ``(i, j)`` has its centre, projected straight along z onto the sensor, at
``origin + i·pitch·e1 + j·pitch·e2`` with ``e1 = (cos θ, sin θ)`` and
``e2 = (-sin θ, cos θ)``. Pixel centre ``(x, y)`` is at integer coordinates
(OpenCV's convention); arrays are indexed ``[y, x]``.

A lattice of micro-image centres is the lens lattice scaled by ``k = (L+b)/L``
about the principal point; :meth:`LensGrid.scaled_about` builds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class LensGrid:
    """A square lattice: ``origin_px`` (x, y), ``pitch_px``, ``rotation_rad``."""

    origin_px: tuple[float, float]
    pitch_px: float
    rotation_rad: float

    @property
    def e1(self) -> NDArray[np.float64]:
        """Unit vector of lattice index i (sensor x, y)."""
        return np.array([np.cos(self.rotation_rad), np.sin(self.rotation_rad)])

    @property
    def e2(self) -> NDArray[np.float64]:
        """Unit vector of lattice index j (sensor x, y)."""
        return np.array([-np.sin(self.rotation_rad), np.cos(self.rotation_rad)])

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(self.rotation_rad))

    def centre(self, i: ArrayLike, j: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixel coordinates ``(x, y)`` of lattice node(s) ``(i, j)``."""
        c, s = np.cos(self.rotation_rad), np.sin(self.rotation_rad)
        i_arr = np.asarray(i, dtype=np.float64)
        j_arr = np.asarray(j, dtype=np.float64)
        x = self.origin_px[0] + self.pitch_px * (c * i_arr - s * j_arr)
        y = self.origin_px[1] + self.pitch_px * (s * i_arr + c * j_arr)
        return x, y

    def fractional_index(
        self, x: NDArray[np.floating], y: NDArray[np.floating]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Continuous lattice coordinates ``(i, j)`` of pixel positions ``(x, y)``."""
        c, s = np.cos(self.rotation_rad), np.sin(self.rotation_rad)
        dx = (np.asarray(x, dtype=np.float64) - self.origin_px[0]) / self.pitch_px
        dy = (np.asarray(y, dtype=np.float64) - self.origin_px[1]) / self.pitch_px
        return c * dx + s * dy, -s * dx + c * dy

    def nearest(
        self, x: NDArray[np.floating], y: NDArray[np.floating]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Integer index ``(i, j)`` of the lattice node nearest each position."""
        fi, fj = self.fractional_index(x, y)
        return np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)

    def scaled_about(self, centre_px: tuple[float, float], scale: float) -> LensGrid:
        """The lattice scaled by ``scale`` about ``centre_px`` (same indices, same rotation)."""
        ox = centre_px[0] + scale * (self.origin_px[0] - centre_px[0])
        oy = centre_px[1] + scale * (self.origin_px[1] - centre_px[1])
        return LensGrid((ox, oy), self.pitch_px * scale, self.rotation_rad)

    def indices_in(
        self, width: int, height: int, margin_px: float = 0.0
    ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """All ``(i, j)`` whose node lies inside ``[margin, W-1-margin] × [margin, H-1-margin]``."""
        corners_x = np.array([0.0, width - 1.0, 0.0, width - 1.0])
        corners_y = np.array([0.0, 0.0, height - 1.0, height - 1.0])
        fi, fj = self.fractional_index(corners_x, corners_y)
        ii, jj = np.meshgrid(
            np.arange(np.floor(fi.min()) - 1, np.ceil(fi.max()) + 2),
            np.arange(np.floor(fj.min()) - 1, np.ceil(fj.max()) + 2),
            indexing="ij",
        )
        i_all = ii.ravel().astype(np.int64)
        j_all = jj.ravel().astype(np.int64)
        x, y = self.centre(i_all, j_all)
        keep = (
            (x >= margin_px)
            & (x <= width - 1 - margin_px)
            & (y >= margin_px)
            & (y <= height - 1 - margin_px)
        )
        return i_all[keep], j_all[keep]
