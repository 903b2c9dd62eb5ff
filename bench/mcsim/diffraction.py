"""Diffraction of the microlens aperture: random landing-point offsets on the sensor.

The in-focus (Fraunhofer) pattern of a microlens aperture seen from the sensor at
distance b, wavelength λ:

* circular aperture of diameter D (f-number N = b/D): the Airy pattern,
  ``I(r) ∝ [2 J1(k)/k]²`` with ``k = π r/(λ N)``; its encircled energy is
  ``E(k) = 1 - J0(k)² - J1(k)²`` (first dark ring at r = 1.22 λN);
* square aperture of side D (fill factor 1): the separable pattern
  ``I(x, y) ∝ sinc²(x D/(λ b)) · sinc²(y D/(λ b))`` (normalised sinc), which is
  the exact Fraunhofer pattern of a square, i.e. the "Airy pattern" of a square
  aperture; its first zeros are at ±λN along x and y.

Offsets are drawn by inverting the tabulated cumulative distribution. The
tails fall off as ``1/r³`` (Airy) and ``1/x²`` (sinc²), so the patterns are
truncated where 99 % of the energy is enclosed: k ≤ 64 for Airy (1 − E ≈ 2/(πk)),
and |q| ≤ 64 per axis for sinc² (tail ≈ 1/(πq) ≈ 0.5 % per axis), then
renormalised. The truncated light would land far outside the pixel's own
micro-image (tens of pixels away) where a renderer that traces each pixel
through its own lens cannot place it anyway.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy import special

AIRY_K_MAX = 64.0
SINC_Q_MAX = 64.0
_TABLE_POINTS = 65536


@dataclass(frozen=True)
class DiffractionSampler:
    """Random landing-point offsets (mm) for one wavelength and microlens aperture."""

    wavelength_mm: float
    f_number: float
    aperture: str  # "square" or "circle"
    _cdf: npt.NDArray[np.float64] = field(init=False, repr=False)
    _arg: npt.NDArray[np.float64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.aperture == "circle":
            k = np.linspace(0.0, AIRY_K_MAX, _TABLE_POINTS)
            cdf = 1.0 - special.j0(k) ** 2 - special.j1(k) ** 2
        elif self.aperture == "square":
            k = np.linspace(0.0, SINC_Q_MAX, _TABLE_POINTS)
            density = np.sinc(k / math.pi) ** 2  # sin²q/q² (np.sinc is normalised)
            cdf = np.concatenate(([0.0], np.cumsum(0.5 * (density[1:] + density[:-1]))))
        else:
            raise ValueError(f"unknown microlens aperture {self.aperture!r}")
        cdf = np.maximum.accumulate(cdf)
        object.__setattr__(self, "_cdf", cdf / cdf[-1])
        object.__setattr__(self, "_arg", k)

    @property
    def _mm_per_unit(self) -> float:
        """mm per unit of k (Airy) or q (sinc²): ``λN/π``."""
        return self.wavelength_mm * self.f_number / math.pi

    @property
    def max_offset_mm(self) -> float:
        """The largest offset (radius) a sample can have."""
        if self.aperture == "circle":
            return AIRY_K_MAX * self._mm_per_unit
        return math.sqrt(2.0) * SINC_Q_MAX * self._mm_per_unit

    def sample(
        self, rng: np.random.Generator, shape: tuple[int, ...]
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """Offsets (dx, dy) in mm, float32 arrays of ``shape``."""
        scale = self._mm_per_unit
        if self.aperture == "circle":
            radius = np.interp(rng.random(shape), self._cdf, self._arg) * scale
            angle = rng.random(shape) * (2.0 * math.pi)
            return (
                (radius * np.cos(angle)).astype(np.float32),
                (radius * np.sin(angle)).astype(np.float32),
            )
        out = []
        for _ in range(2):
            signed = rng.random(shape) * 2.0 - 1.0  # sign and magnitude from one number
            q = np.interp(np.abs(signed), self._cdf, self._arg) * scale
            out.append(np.copysign(q, signed).astype(np.float32))
        return out[0], out[1]
