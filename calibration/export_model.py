"""The calibrated camera model that an ``lfcal-result/1`` JSON describes.

A result holds the calibrated ``b``, ``a`` (= ``a_f``), ``Q``, ``p`` at the focus
plane, the focus plane ``u0``, the MLA lattices, and the priors it used
(``inputs``: F, f, D, δ, the principal point, the sensor size). Newer results
may also carry ``priors`` (a data-sheet value, the calibrated value, its
uncertainty and a tolerance for F, f, the rail zero and L) and a top-level
``L_mm``; both are read when present and the older layout is the fallback.

:class:`CalibratedCamera` gathers the model in one place (symbols of
``shared/OPTICS.md``, millimetres unless a name says ``_px``) and answers what
the users of a calibration ask: the patch size at any object distance,

    ``p(u) = Q(u)·D/δ``,  ``Q(u) = b / a(u)``,  ``a(u) = L − v(u)``,  ``v(u) = uF/(u − F)``,

and the lattices. ``L`` (main lens to MLA) comes, in this order, from the
result's ``L_mm``, ``priors.L_mm.calibrated``, the ESIF estimate at the focus
plane (``L = a + v(u0)``, which reproduces the calibrated ``p`` at ``u0``
exactly), or the global fit (``estimates.global.L_mm``); :attr:`CalibratedCamera.L_source`
says which.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .lens_grid import LensGrid
from .optics import image_distance


class ResultError(ValueError):
    """The result JSON lacks what the model needs (the message names the key)."""


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    f = float(value)
    return f if math.isfinite(f) else None


def _get(obj: Any, path: str) -> Any:
    """``obj["a"]["b"]`` for ``path = "a.b"``; None when any step is missing."""
    for key in path.split("."):
        if not isinstance(obj, dict) or key not in obj:
            return None
        obj = obj[key]
    return obj


def _required(result: dict[str, Any], *paths: str) -> float:
    for path in paths:
        value = _number(_get(result, path))
        if value is not None:
            return value
    raise ResultError(
        f"the result has no {paths[0]}"
        + (f" (nor {', '.join(paths[1:])})" if len(paths) > 1 else "")
        + ": is it an lfcal-result/1 file of a successful calibration?"
    )


def prior_value(result: dict[str, Any], name: str, inputs_path: str) -> float | None:
    """The value a result *used* for a prior: ``priors.NAME.calibrated`` when the
    calibration refined it, else the data-sheet value it was given (``inputs``)."""
    calibrated = _number(_get(result, f"priors.{name}.calibrated"))
    if calibrated is not None:
        return calibrated
    return _number(_get(result, inputs_path))


def grid_from_dict(grid: Any, what: str) -> LensGrid:
    """A :class:`LensGrid` from the result's ``{"origin_px", "pitch_px", "rotation_deg"}``."""
    try:
        return LensGrid(
            (float(grid["origin_px"][0]), float(grid["origin_px"][1])),
            float(grid["pitch_px"]),
            math.radians(float(grid["rotation_deg"])),
        )
    except (KeyError, TypeError, IndexError, ValueError):
        raise ResultError(f"the result has no usable {what}") from None


@dataclass(frozen=True)
class CalibratedCamera:
    """The calibrated focused-plenoptic camera (mm, px; ``shared/OPTICS.md``).

    Attributes:
        F, f, D, delta: main-lens focal length, microlens focal length, microlens
            pitch and pixel pitch.
        b, L: MLA-to-sensor and main-lens-to-MLA distances.
        a_f: virtual-image distance in focus on the sensor (the calibrated ``a``).
        focus_mm: object distance of the focus plane ``u0``.
        patch_px: the calibrated ESIF patch size ``p`` at the focus plane.
        width, height: sensor (frame) size in pixels.
        principal_point_px: where the optical axis meets the sensor.
        image_grid, lens_grid: micro-image-centre and lens-centre lattices.
        L_source: where ``L`` came from (module docstring).
    """

    F: float
    f: float
    D: float
    delta: float
    b: float
    L: float
    a_f: float
    focus_mm: float
    patch_px: float
    width: int
    height: int
    principal_point_px: tuple[float, float]
    image_grid: LensGrid
    lens_grid: LensGrid
    L_source: str

    @classmethod
    def from_result(cls, result: dict[str, Any]) -> CalibratedCamera:
        """The model of an ``lfcal-result/1`` dict; :class:`ResultError` names what is missing."""
        if not isinstance(result, dict):
            raise ResultError("the result is not a JSON object")
        fmt = result.get("format")
        if fmt is not None and fmt != "lfcal-result/1":
            raise ResultError(f"the file is {fmt!r}, not an lfcal-result/1 calibration result")
        F = prior_value(result, "main_focal_mm", "inputs.optics.main_focal_mm")
        f = prior_value(result, "mla_focal_mm", "inputs.optics.mla_focal_mm")
        if F is None or f is None:
            raise ResultError("the result has no optics priors (inputs.optics)")
        D = _required(result, "inputs.optics.mla_pitch_mm")
        delta = _required(result, "inputs.camera.pixel_pitch_mm")
        b = _required(result, "b_mm")
        a_f = _required(result, "a_mm")
        u0 = _required(result, "focus.object_distance_mm")
        p = _required(result, "patch_size_px")
        width = int(_required(result, "inputs.camera.width"))
        height = int(_required(result, "inputs.camera.height"))
        pp = _get(result, "inputs.camera.principal_point_px")
        try:
            principal = (float(pp[0]), float(pp[1]))
        except (TypeError, IndexError, ValueError):
            principal = ((width - 1) / 2.0, (height - 1) / 2.0)
        L, source = _main_lens_to_mla(result, a_f, u0, F)
        mla = result.get("mla") or {}
        image_grid = grid_from_dict(mla.get("image_grid"), "micro-image lattice (mla.image_grid)")
        lens_grid = grid_from_dict(mla.get("lens_grid"), "lens lattice (mla.lens_grid)")
        return cls(
            F=F,
            f=f,
            D=D,
            delta=delta,
            b=b,
            L=L,
            a_f=a_f,
            focus_mm=u0,
            patch_px=p,
            width=width,
            height=height,
            principal_point_px=principal,
            image_grid=image_grid,
            lens_grid=lens_grid,
            L_source=source,
        )

    @property
    def lens_pitch_px(self) -> float:
        """``D/δ``, the lens-centre pitch on the sensor (px)."""
        return self.D / self.delta

    @property
    def image_pitch_px(self) -> float:
        """``μ``, the measured micro-image-centre pitch (px)."""
        return self.image_grid.pitch_px

    @property
    def Q_focus(self) -> float:
        """``Q = b/a_f`` at the focus plane."""
        return self.b / self.a_f

    def a_at(self, object_distance_mm: float) -> float:
        """``a(u) = L − v(u)`` (mm): where the main image of a point at ``u`` lies."""
        u = float(object_distance_mm)
        if not u > self.F:
            raise ValueError(
                f"object distance {u:g} mm must exceed the main-lens focal length F = {self.F:g} mm"
            )
        return self.L - float(image_distance(u, self.F))

    def Q_at(self, object_distance_mm: float) -> float:
        """``Q(u) = b/a(u)``; ``ValueError`` where the main image reaches the MLA (``a ≤ 0``)."""
        a = self.a_at(object_distance_mm)
        if not a > 0:
            u_min = self.F * self.L / (self.L - self.F)
            raise ValueError(
                f"at u = {object_distance_mm:g} mm the main image lies behind the microlens "
                f"array (a = {a:.3f} mm): the model covers object distances above {u_min:.1f} mm"
            )
        return self.b / a

    def patch_at(self, object_distance_mm: float) -> float:
        """ESIF patch size ``p(u) = Q(u)·D/δ`` (px) at object distance ``u`` (mm)."""
        return self.Q_at(object_distance_mm) * self.lens_pitch_px

    def seamless_patch(self, patch_px: float) -> float:
        """The rendering patch (px) that joins patches of ESIF size ``p`` without seams:
        ``p − (μ − D/δ)`` (see :mod:`calibration.rendering`)."""
        return float(patch_px) - (self.image_pitch_px - self.lens_pitch_px)

    @property
    def main_aperture_mm(self) -> float:
        """Main-lens aperture diameter under f-number matching (``L/A = b/D``), mm."""
        return self.D * self.L / self.b


def designed_patch_px(
    *, b_mm: float, f_mm: float, D_mm: float, delta_mm: float, a_mm: float | None = None
) -> float:
    """The ESIF patch size ``p = (b/a)·D/δ`` of designed optics (px).

    ``a`` defaults to the microlens's thin-lens conjugate of ``b``,
    ``a = f·b/(b − f)`` (the designed camera in focus).
    """
    if not b_mm > f_mm > 0:
        raise ValueError(f"designed b = {b_mm:g} mm must exceed f = {f_mm:g} mm")
    a = a_mm if a_mm is not None else f_mm * b_mm / (b_mm - f_mm)
    if not a > 0:
        raise ValueError(f"designed a = {a:g} mm must be positive")
    return (b_mm / a) * (D_mm / delta_mm)


def _main_lens_to_mla(result: dict[str, Any], a_f: float, u0: float, F: float) -> tuple[float, str]:
    top = _number(result.get("L_mm"))
    if top is not None:
        return top, "L_mm"
    prior = _number(_get(result, "priors.L_mm.calibrated"))
    if prior is not None:
        return prior, "priors.L_mm.calibrated"
    if u0 > F:
        return a_f + float(image_distance(u0, F)), "a + v(u0) (ESIF at the focus plane)"
    glob = _number(_get(result, "estimates.global.L_mm"))
    if glob is not None:
        return glob, "estimates.global.L_mm"
    raise ResultError("the result gives no main-lens-to-MLA distance L")


__all__ = [
    "CalibratedCamera",
    "ResultError",
    "designed_patch_px",
    "grid_from_dict",
    "prior_value",
]
