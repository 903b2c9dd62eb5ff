"""Per-point transmission of the main aperture (and a second stop) through a microlens.

Units: mm. ``transmission(s, m) = cos⁴θ(s) · V(s)``:

* θ is the chief ray's angle to the axis between the MLA and the sensor,
  ``tan θ = |s - m|/b`` (s the sensor point, m the lens centre projected
  straight along z). mcsim averages cos⁴ over the pupil's rays instead; the two
  differ by ~2⟨|ξ - m|²⟩/b² (0.14 % for the ``small`` preset), uniformly.
* V is the fraction of the microlens pupil area whose ray from s (through the
  pupil point ξ, refracted by the thin microlens, continued backwards) passes
  the main aperture (diameter A at z = 0) and, if set, the second stop
  (diameter A_v at z = Z). Between the MLA and the main lens the ray's slope
  is ``(s - ξ)/b + (ξ - m)/f``, so its lateral position on any stop plane is
  linear in ξ, s and m: ``x = α·ξ + β·s + γ·m``. ``|x| <= R`` is therefore a
  disc in the pupil plane, centre ``-(β·s + γ·m)/α``, radius ``R/|α|``.
  V integrates the pupil rows exactly along x (each row ∩ disc(s) is an
  interval) and by the midpoint rule across ``rows`` rows (default 32) in the
  lens frame (turned by θ): a fixed, deterministic quadrature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.mcsim.camera import Camera
from bench.wavesim.psf import FloatArray

PUPIL_ROWS = 32
Points = FloatArray | float  # sensor or lens positions, mm (broadcastable)


@dataclass(frozen=True)
class Stop:
    """A circular stop of radius ``radius_mm``: the ray passes when ``|α·ξ + β·s + γ·m| <= R``."""

    alpha: float
    beta: float
    gamma: float
    radius_mm: float


def stops(camera: Camera) -> list[Stop]:
    """The main aperture and the optional second (vignetting) stop of ``camera``."""
    L, b, f, F = (
        camera.mla_distance_mm,
        camera.sensor_distance_mm,
        camera.mla_focal_mm,
        camera.main_focal_mm,
    )

    def behind_main_lens(d: float) -> tuple[float, float, float]:
        # lateral position a distance d in front of the MLA: ξ - d·[(s - ξ)/b + (ξ - m)/f]
        return 1.0 + d / b - d / f, -d / b, d / f

    alpha, beta, gamma = behind_main_lens(L)
    out = [Stop(alpha, beta, gamma, camera.main_aperture_mm / 2.0)]
    z, diameter = camera.vignetting_stop_mm, camera.vignetting_diameter_mm
    if z is not None and diameter is not None:
        if z > 0:
            a2, b2, g2 = behind_main_lens(L - z)
        else:  # in front of the main lens: refracted there (object-side slope k + x0/F)
            k = 1.0 + z / F
            a2 = k * alpha + z * (1.0 / f - 1.0 / b)
            b2 = k * beta + z / b
            g2 = k * gamma - z / f
        out.append(Stop(a2, b2, g2, diameter / 2.0))
    return out


def pupil_fraction(
    camera: Camera,
    sx: Points,
    sy: Points,
    mx: Points,
    my: Points,
    rows: int = PUPIL_ROWS,
) -> FloatArray:
    """V: the passing fraction of the pupil for sensor points (sx, sy) of lenses (mx, my), mm."""
    half = camera.mla_pitch_mm / 2.0
    t = math.radians(camera.theta_deg)
    ct, st = math.cos(t), math.sin(t)
    discs = []
    for stop in stops(camera):
        if abs(stop.alpha) < 1e-12:
            raise ValueError("a stop is conjugate to the sensor through the microlens")
        cx = -(stop.beta * sx + stop.gamma * mx) / stop.alpha - mx
        cy = -(stop.beta * sy + stop.gamma * my) / stop.alpha - my
        # into the lens frame (turned by θ)
        discs.append((ct * cx + st * cy, -st * cx + ct * cy, stop.radius_mm / abs(stop.alpha)))
    passed = np.zeros(np.broadcast(sx, sy, mx, my).shape)
    full = 0.0
    for row in range(rows):
        eta = -half + (row + 0.5) * 2.0 * half / rows
        if camera.microlens_aperture == "circle":
            w = math.sqrt(max(half * half - eta * eta, 0.0))
        else:
            w = half
        lo = np.full(passed.shape, -w)
        hi = np.full(passed.shape, w)
        for ux, uy, radius in discs:
            h2 = radius * radius - (eta - uy) ** 2
            h = np.sqrt(np.clip(h2, 0.0, None))
            lo = np.maximum(lo, np.where(h2 > 0, ux - h, np.inf))
            hi = np.minimum(hi, ux + h)
        passed += np.clip(hi - lo, 0.0, None)
        full += 2.0 * w
    return passed / full


def transmission(
    camera: Camera,
    sx: Points,
    sy: Points,
    mx: Points,
    my: Points,
    rows: int = PUPIL_ROWS,
) -> FloatArray:
    """``cos⁴θ·V`` at sensor points (sx, sy) mm seen through lenses centred at (mx, my) mm."""
    b = camera.sensor_distance_mm
    tan2 = ((sx - mx) ** 2 + (sy - my) ** 2) / (b * b)
    return pupil_fraction(camera, sx, sy, mx, my, rows) / (1.0 + tan2) ** 2
