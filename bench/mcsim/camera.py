"""Camera geometry of the Monte-Carlo renderer, from OPTICS.md §1-§2 only.

Coordinates: z is the optical axis, the main lens at z = 0, the board at
z = -u, the MLA at z = L, the sensor at z = L + b. Lateral positions (x, y) are
in mm from the optical axis, x along the sensor's columns, y along its rows;
pixel (column x, row y) has its centre at ``((x - cx)·δ, (y - cy)·δ)``.

The MLA is a square grid: lens (i, j) has its centre, projected straight along
z onto the sensor, at ``O + i·(D/δ)·e1 + j·(D/δ)·e2`` pixels with
``e1 = (cos θ, sin θ)``, ``e2 = (-sin θ, cos θ)``. Its micro-image centre (the
main-lens centre projected through the lens centre onto the sensor) is
``(L + b)/L`` times farther from the principal point. Every pixel belongs to
the lens whose micro-image centre is nearest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


class OpticsError(ValueError):
    """Optics that no Keplerian focused plenoptic camera can have (one-line message)."""


@dataclass(frozen=True)
class Camera:
    """A focused plenoptic camera (thin lenses, paraxial placement of the parts).

    All lengths in mm except the ``_px`` fields. ``mla_distance_mm`` is L,
    ``sensor_distance_mm`` is b, ``lens_origin_px`` is O (the projected centre of
    lens (0, 0)), ``main_aperture_mm`` the main-lens aperture diameter A.
    ``microlens_aperture`` is ``"square"`` (side D, fill factor 1) or
    ``"circle"`` (diameter D). ``vignetting_stop_mm`` (Z) and
    ``vignetting_diameter_mm`` (A_v) place an optional second circular stop,
    centred on the axis at z = Z (0 < Z < L: between the main lens and the MLA;
    Z < 0: in front of the main lens): mechanical vignetting; both None: none.
    """

    width: int
    height: int
    pixel_mm: float
    principal_point_px: tuple[float, float]
    main_focal_mm: float
    mla_focal_mm: float
    mla_pitch_mm: float
    sensor_distance_mm: float
    mla_distance_mm: float
    theta_deg: float
    lens_origin_px: tuple[float, float]
    main_aperture_mm: float
    microlens_aperture: str = "square"
    vignetting_stop_mm: float | None = None
    vignetting_diameter_mm: float | None = None

    # ---- thin-lens relations (OPTICS.md §1) -------------------------------------
    def v_mm(self, u_mm: float) -> float:
        """Main-lens image distance ``v = uF/(u - F)``."""
        F = self.main_focal_mm
        return u_mm * F / (u_mm - F)

    def a_mm(self, u_mm: float) -> float:
        """Distance of the main image in front of the MLA, ``a = L - v(u)``."""
        return self.mla_distance_mm - self.v_mm(u_mm)

    @property
    def a_focus_mm(self) -> float:
        """``a_f = 1/(1/f - 1/b)``: the virtual-image distance sharp on the sensor."""
        return 1.0 / (1.0 / self.mla_focal_mm - 1.0 / self.sensor_distance_mm)

    @property
    def u_focus_mm(self) -> float:
        """Object distance of the focus plane (where ``a(u) = a_f``)."""
        v0 = self.mla_distance_mm - self.a_focus_mm
        F = self.main_focal_mm
        return v0 * F / (v0 - F)

    def q(self, u_mm: float) -> float:
        """``Q = b/a(u)``."""
        return self.sensor_distance_mm / self.a_mm(u_mm)

    def defocus_blur_px(self, u_mm: float) -> float:
        """Geometric blur diameter ``D·b·|1/a_f - 1/a(u)|`` in pixels."""
        D, b = self.mla_pitch_mm, self.sensor_distance_mm
        return D * b * abs(1.0 / self.a_focus_mm - 1.0 / self.a_mm(u_mm)) / self.pixel_mm

    def micro_images_per_axis(self, u_mm: float) -> float:
        """About how many micro-images see one board point, per axis: (a/b)(L+b)/(L-a)."""
        a, b, L = self.a_mm(u_mm), self.sensor_distance_mm, self.mla_distance_mm
        return (a / b) * (L + b) / (L - a)

    # ---- lattices (OPTICS.md §2) --------------------------------------------------
    @property
    def lens_pitch_px(self) -> float:
        return self.mla_pitch_mm / self.pixel_mm

    @property
    def spread_factor(self) -> float:
        """``(L + b)/L``: micro-image centres versus lens centres, from the principal point."""
        return (self.mla_distance_mm + self.sensor_distance_mm) / self.mla_distance_mm

    @property
    def micro_image_pitch_px(self) -> float:
        return self.lens_pitch_px * self.spread_factor

    @property
    def micro_image_origin_px(self) -> tuple[float, float]:
        cx, cy = self.principal_point_px
        ox, oy = self.lens_origin_px
        k = self.spread_factor
        return (cx + (ox - cx) * k, cy + (oy - cy) * k)

    @property
    def _axes(self) -> tuple[tuple[float, float], tuple[float, float]]:
        t = math.radians(self.theta_deg)
        return (math.cos(t), math.sin(t)), (-math.sin(t), math.cos(t))

    def lens_of_pixels(self, x_px: FloatArray, y_px: FloatArray) -> tuple[IntArray, IntArray]:
        """Indices (i, j) of the lens whose micro-image centre is nearest to each pixel."""
        u, v = self.lattice_coords(x_px, y_px)
        return np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)

    def lattice_coords(self, x_px: FloatArray, y_px: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Fractional micro-image lattice coordinates of sensor points (pixels)."""
        (e1x, e1y), (e2x, e2y) = self._axes
        mx, my = self.micro_image_origin_px
        pitch = self.micro_image_pitch_px
        dx = np.asarray(x_px, dtype=np.float64) - mx
        dy = np.asarray(y_px, dtype=np.float64) - my
        return (dx * e1x + dy * e1y) / pitch, (dx * e2x + dy * e2y) / pitch

    def lens_centre_px(self, i: IntArray, j: IntArray) -> tuple[FloatArray, FloatArray]:
        """Projected (straight along z) lens centres, pixels."""
        (e1x, e1y), (e2x, e2y) = self._axes
        ox, oy = self.lens_origin_px
        p = self.lens_pitch_px
        return ox + p * (i * e1x + j * e2x), oy + p * (i * e1y + j * e2y)

    def micro_image_centre_px(self, i: IntArray, j: IntArray) -> tuple[FloatArray, FloatArray]:
        (e1x, e1y), (e2x, e2y) = self._axes
        mx, my = self.micro_image_origin_px
        p = self.micro_image_pitch_px
        return mx + p * (i * e1x + j * e2x), my + p * (i * e1y + j * e2y)

    def px_to_mm(self, x_px: FloatArray, y_px: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pixel coordinates to lateral mm from the optical axis."""
        cx, cy = self.principal_point_px
        return (np.asarray(x_px) - cx) * self.pixel_mm, (np.asarray(y_px) - cy) * self.pixel_mm

    # ---- checks -------------------------------------------------------------------
    def check(self, u_values_mm: list[float]) -> None:
        """Raise :class:`OpticsError` (one line) for optics no Keplerian camera has."""
        F, f, b, L = (
            self.main_focal_mm,
            self.mla_focal_mm,
            self.sensor_distance_mm,
            self.mla_distance_mm,
        )
        positive = {
            "F": F,
            "f": f,
            "D": self.mla_pitch_mm,
            "pixel": self.pixel_mm,
            "b": b,
            "L": L,
            "main aperture": self.main_aperture_mm,
        }
        for name, value in positive.items():
            if not value > 0:
                raise OpticsError(f"{name} must be > 0 mm (got {value:g})")
        if self.width < 1 or self.height < 1:
            raise OpticsError(f"frame size must be positive (got {self.width}x{self.height})")
        if b <= f:
            raise OpticsError(f"b ({b:g} mm) must exceed f ({f:g} mm): no sharp virtual image")
        if L - self.a_focus_mm <= F:
            raise OpticsError(
                f"L ({L:g} mm) - a_f ({self.a_focus_mm:g} mm) <= F ({F:g} mm): no focus plane"
            )
        for u in u_values_mm:
            if u <= F:
                raise OpticsError(f"object distance u = {u:g} mm <= F = {F:g} mm: no real image")
            a = self.a_mm(u)
            if a <= 0:
                raise OpticsError(
                    f"a = {a:g} mm <= 0 at u = {u:g} mm: main image behind the MLA (not Keplerian)"
                )
        self._check_vignetting_stop(u_values_mm)

    def _check_vignetting_stop(self, u_values_mm: list[float]) -> None:
        """The second stop: both numbers or neither, a real diameter, a place on the light path."""
        z, d = self.vignetting_stop_mm, self.vignetting_diameter_mm
        if z is None and d is None:
            return
        if z is None or d is None:
            raise OpticsError(
                "the vignetting stop needs both its position and its diameter "
                "(--vignetting-stop-mm and --vignetting-diameter-mm), or neither"
            )
        if not math.isfinite(z):
            raise OpticsError(f"vignetting stop position must be a finite number (got {z:g})")
        if not (math.isfinite(d) and d > 0):
            raise OpticsError(f"vignetting stop diameter must be > 0 mm (got {d:g})")
        L, b = self.mla_distance_mm, self.sensor_distance_mm
        where = f"vignetting stop at z = {z:g} mm"
        if z == 0:
            raise OpticsError(f"{where} is the main lens itself (use the main aperture instead)")
        if z >= L:
            if z == L:
                place = "at the MLA"
            elif z < L + b:
                place = "between the MLA and the sensor"
            else:
                place = "behind the sensor"
            raise OpticsError(
                f"{where} lies {place} (L = {L:g} mm): put it between the main lens "
                f"and the MLA (0 < Z < L) or in front of the main lens (Z < 0)"
            )
        for u in u_values_mm:
            if z < 0 and u <= -z:
                raise OpticsError(
                    f"board at u = {u:g} mm is not beyond the {where} (needs u > {-z:g} mm)"
                )
