"""Sensor model: photons -> electrons -> counts (shot noise, read noise, quantisation).

The tracer's signal is 1 for a reflectance-1 board seen along the axis through
the whole aperture. ``photons`` is the electron count of that full-light signal
and maps to the top of the count range: ``counts = black + e·(2^bits - 1 - black)/photons``,
so the brightest board (reflectance 0.95) stays about 5 % below saturation.
Electrons are Poisson (shot noise) plus Gaussian read noise (σ in e-); counts
are rounded, clipped to ``[0, 2^bits - 1]`` and right-aligned in uint16.
``exposure`` multiplies the board frames' light and ``white_exposure`` the white
image's (a lab exposes it on its own): above about 1.05 the bright squares saturate,
above 1 the white image's brightest micro-images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True)
class SensorSettings:
    bit_depth: int = 12
    photons: float = 20000.0
    read_noise_e: float = 5.0
    black_level: int = 0
    exposure: float = 1.0
    white_exposure: float = 1.0

    def check(self) -> None:
        if self.bit_depth not in (8, 10, 12, 14, 16):
            raise ValueError(f"bit depth must be 8, 10, 12, 14 or 16 (got {self.bit_depth})")
        if not self.photons > 0:
            raise ValueError(f"photons must be > 0 (got {self.photons:g})")
        if not (self.exposure > 0 and self.white_exposure > 0):
            raise ValueError(
                f"exposures must be > 0 (got {self.exposure:g}, white {self.white_exposure:g})"
            )
        if self.read_noise_e < 0:
            raise ValueError(f"read noise must be >= 0 e- (got {self.read_noise_e:g})")
        full = (1 << self.bit_depth) - 1
        if not 0 <= self.black_level < full:
            raise ValueError(f"black level must be in [0, {full}) (got {self.black_level})")

    @property
    def full_scale(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def counts_per_electron(self) -> float:
        return (self.full_scale - self.black_level) / self.photons


def expose(
    signal: npt.NDArray[np.float32],
    sensor: SensorSettings,
    rng: np.random.Generator,
    *,
    exposure: float = 1.0,
) -> npt.NDArray[np.uint16]:
    """Counts (uint16, right-aligned) of a frame whose noiseless signal is ``signal``.

    ``exposure`` scales the light (electrons) before the noise, not the count scale.
    """
    mean_electrons = np.clip(signal.astype(np.float64), 0.0, None) * (sensor.photons * exposure)
    electrons = rng.poisson(mean_electrons).astype(np.float64)
    if sensor.read_noise_e > 0:
        electrons += rng.normal(0.0, sensor.read_noise_e, size=signal.shape)
    counts = np.rint(sensor.black_level + electrons * sensor.counts_per_electron)
    return np.clip(counts, 0, sensor.full_scale).astype(np.uint16)
