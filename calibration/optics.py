"""Thin-lens, paraxial optics of a focused plenoptic camera (Keplerian mode).

Every function follows ``shared/OPTICS.md`` §1. Units are millimetres unless a
name ends in ``_px`` (sensor pixels). Symbols:

- ``F``: main-lens focal length; ``f``: microlens focal length;
- ``D``: microlens pitch; ``delta``: sensor pixel pitch;
- ``L``: main lens to MLA; ``b``: MLA to sensor;
- ``u``: object distance (board to main lens); ``v``: main-image distance
  behind the main lens; ``a = L - v``: main image in front of the MLA.

All functions accept floats or numpy arrays (vectorized element-wise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatOrArray = float | NDArray[np.float64]


def _as(x: ArrayLike) -> FloatOrArray:
    arr = np.asarray(x, dtype=np.float64)
    return float(arr) if arr.ndim == 0 else arr


def image_distance(u: ArrayLike, F: float) -> FloatOrArray:
    """Main-image distance ``v(u) = u F / (u - F)`` (mm) for an object at ``u`` > F."""
    u_arr = np.asarray(u, dtype=np.float64)
    return _as(u_arr * F / (u_arr - F))


def object_distance(v: ArrayLike, F: float) -> FloatOrArray:
    """Inverse of :func:`image_distance`: ``u(v) = v F / (v - F)`` (mm)."""
    v_arr = np.asarray(v, dtype=np.float64)
    return _as(v_arr * F / (v_arr - F))


def virtual_image_distance(u: ArrayLike, F: float, L: float) -> FloatOrArray:
    """``a(u) = L - v(u)``: main image in front of the MLA (mm); ``a > 0`` is Keplerian."""
    return _as(L - np.asarray(image_distance(u, F)))


def focused_virtual_distance(f: float, b: float) -> float:
    """``a_f = 1 / (1/f - 1/b)``: the virtual-image distance imaged sharply on the sensor (mm)."""
    if b <= f:
        raise ValueError(f"b = {b} mm must exceed the microlens focal length f = {f} mm")
    return 1.0 / (1.0 / f - 1.0 / b)


def focus_plane(F: float, f: float, b: float, L: float) -> float:
    """Object distance ``u0`` where ``a(u0) = a_f`` (mm): the focus plane."""
    v0 = L - focused_virtual_distance(f, b)
    if v0 <= F:
        raise ValueError(f"no focus plane: L - a_f = {v0:.4f} mm is not beyond F = {F} mm")
    return float(object_distance(v0, F))


def mla_distance_for_focus(u0: float, F: float, f: float, b: float) -> float:
    """``L`` that puts the focus plane at object distance ``u0`` (mm)."""
    return float(image_distance(u0, F)) + focused_virtual_distance(f, b)


def q_ratio(a: ArrayLike, b: float) -> FloatOrArray:
    """``Q = b / a`` (dimensionless): micro-image magnification / resolution scale."""
    return _as(b / np.asarray(a, dtype=np.float64))


def patch_size_px(Q: ArrayLike, D: float, delta: float) -> FloatOrArray:
    """Patch size ``p = Q D / delta`` in pixels (Eq. 4)."""
    return _as(np.asarray(Q, dtype=np.float64) * D / delta)


def b_from_q(Q: ArrayLike, f: float) -> FloatOrArray:
    """At the focus plane, ``1/a + 1/b = 1/f`` and ``Q = b/a`` give ``b = f (1 + Q)`` (mm)."""
    return _as(f * (1.0 + np.asarray(Q, dtype=np.float64)))


def a_from_q(Q: ArrayLike, f: float) -> FloatOrArray:
    """At the focus plane ``a = f (1 + Q) / Q`` (mm)."""
    Q_arr = np.asarray(Q, dtype=np.float64)
    return _as(f * (1.0 + Q_arr) / Q_arr)


def f_from_ab(a: float, b: float) -> float:
    """Microlens focal length from ``1/a + 1/b = 1/f`` (mm)."""
    return 1.0 / (1.0 / a + 1.0 / b)


def blur_diameter(u: ArrayLike, F: float, f: float, D: float, b: float, L: float) -> FloatOrArray:
    """Geometric defocus blur diameter in a micro-image, ``D b |1/a_f - 1/a(u)|`` (mm on the sensor)."""
    a_u = np.asarray(virtual_image_distance(u, F, L))
    return _as(D * b * np.abs(1.0 / focused_virtual_distance(f, b) - 1.0 / a_u))


def image_centre_scale(L: float, b: float) -> float:
    """Micro-image centres lie ``(L+b)/L`` times farther from the principal point than lens centres."""
    return (L + b) / L


def micro_images_per_point(a: ArrayLike, b: float, L: float) -> FloatOrArray:
    """Number of micro-images per axis that show one board point, ``(a/b)(L+b)/(L-a)``."""
    a_arr = np.asarray(a, dtype=np.float64)
    return _as((a_arr / b) * (L + b) / (L - a_arr))


def main_aperture_for_matching(L: float, b: float, D: float) -> float:
    """Main-aperture diameter ``A`` with ``L/A = b/D`` (f-number matching), mm."""
    return L * D / b


@dataclass(frozen=True)
class CameraOptics:
    """A complete focused-plenoptic camera (mm; ``delta`` is the pixel pitch).

    ``aperture`` is the main-lens aperture diameter ``A``.
    """

    F: float
    f: float
    D: float
    delta: float
    b: float
    L: float
    aperture: float

    def __post_init__(self) -> None:
        problems = []
        for name in ("F", "f", "D", "delta", "b", "L", "aperture"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                problems.append(f"{name} = {value} must be a positive number")
        if problems:
            raise ValueError("impossible optics: " + "; ".join(problems))
        if self.b <= self.f:
            raise ValueError(
                f"impossible optics: b = {self.b} mm must exceed f = {self.f} mm "
                "(otherwise no virtual image is in focus, a_f <= 0)"
            )
        if self.L - self.a_f <= self.F:
            raise ValueError(
                f"impossible optics: L - a_f = {self.L - self.a_f:.4f} mm must exceed F = {self.F} mm "
                "(no object distance is in focus)"
            )

    @property
    def a_f(self) -> float:
        """Virtual-image distance that is sharp on the sensor (mm)."""
        return focused_virtual_distance(self.f, self.b)

    @property
    def u0(self) -> float:
        """Focus-plane object distance (mm)."""
        return focus_plane(self.F, self.f, self.b, self.L)

    @property
    def Q_focus(self) -> float:
        """``Q = b / a_f`` at the focus plane."""
        return self.b / self.a_f

    @property
    def lens_pitch_px(self) -> float:
        """Lens-centre pitch on the sensor, ``D / delta`` (px)."""
        return self.D / self.delta

    @property
    def image_pitch_px(self) -> float:
        """Micro-image-centre pitch, ``D/delta (L+b)/L`` (px)."""
        return self.lens_pitch_px * image_centre_scale(self.L, self.b)

    def a(self, u: ArrayLike) -> FloatOrArray:
        """``a(u)`` for object distance(s) ``u`` (mm)."""
        return virtual_image_distance(u, self.F, self.L)

    def Q(self, u: ArrayLike) -> FloatOrArray:
        """``Q(u) = b / a(u)``: the disparity ratio seen at object distance ``u``."""
        return q_ratio(self.a(u), self.b)

    def patch_px(self, u: ArrayLike) -> FloatOrArray:
        """Patch size ``p(u) = Q(u) D / delta`` (px)."""
        return patch_size_px(self.Q(u), self.D, self.delta)

    def blur_px(self, u: ArrayLike) -> FloatOrArray:
        """Geometric defocus blur diameter at object distance ``u`` (px)."""
        return _as(
            np.asarray(blur_diameter(u, self.F, self.f, self.D, self.b, self.L)) / self.delta
        )


def optics_focused_at(
    u0: float, *, F: float, f: float, D: float, b: float, delta: float = 0.0025
) -> CameraOptics:
    """The camera with focal lengths ``F, f``, pitch ``D``, MLA-to-sensor ``b`` and pixel
    ``delta`` (mm) whose focus plane is at object distance ``u0``: ``L`` from it, the main
    aperture f-number matched (``L/A = b/D``)."""
    L = mla_distance_for_focus(u0, F, f, b)
    return CameraOptics(
        F=F, f=f, D=D, delta=delta, b=b, L=L, aperture=main_aperture_for_matching(L, b, D)
    )


def paper_optics() -> CameraOptics:
    """The seed paper's Zemax camera: F=35, f=2.5, D=0.25, delta=0.0025, b=3, focus at u=300."""
    return optics_focused_at(300.0, F=35.0, f=2.5, D=0.25, b=3.0)
