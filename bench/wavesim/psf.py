"""The defocused incoherent PSF of one microlens, by FFT (scalar Fresnel optics).

Units: lengths in mm, wavelengths in mm here (the CLI takes µm).

A microlens of pitch D with pupil P(ξ) (a square of side D turned by the grid
angle θ, or a disc of diameter D) focuses the light of a main-image point at
distance a to the plane b' (1/a + 1/b' = 1/f); the sensor is at b. The field on
the sensor is the Fraunhofer transform of the pupil times the defocus phase
``exp(iπ|ξ|²·c/λ)`` with ``c = 1/b - 1/b' = 1/a - 1/a_f`` (mm⁻¹), evaluated at
spatial frequency ``s/(λb)``; the PSF is its squared modulus, unit integral.

Sampling (one frame, one wavelength):

* the kernel grid is the frame's supersampled cell grid, spacing ``ds = δ/ss``;
* the FFT's PSF spacing is ``ds/n`` with ``n`` odd, the smallest for which the
  padded pupil field ``λb/(ds/n)`` is at least 2·D (intensity Nyquist); ``n``
  fine samples per kernel cell are summed (cell masses), so a geometric,
  hard-edged blur (λ → 0) is area-integrated, not point-sampled;
* the FFT field ``λb/dξ`` is at least ``2·H + 32·λb/D`` and the pupil has at
  least ``PUPIL_SAMPLES`` samples across D. ``H`` is the kernel's half-width:
  ``rings·λb/D`` plus the geometric blur's half-diagonal plus 2 px. With the
  field that wide the phase step between pupil samples stays below π/2, and the
  periodic images of the PSF (the FFT's wrap-around) put < 0.1 % of the energy
  into the kernel;
* pupil samples are area coverages of their cells (8×8 sub-samples; fewer,
  down to 2×2, once more than 128 cells span D), so the aperture's edge is
  not a staircase.

Truncation: the kernel keeps the PSF within ±H (a square) and is renormalised
to unit sum. What it drops (the far rings: ~1/(π²·rings) per axis for the
square pupil, about 2.5 % at the default 8 rings; ~1.3 % for the disc) is
reported per frame (``truncated_energy``); physically it lands in neighbouring
micro-images (crosstalk, which mcsim does not model either) or forms a faint veil.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.fft

FloatArray = npt.NDArray[np.float64]

PUPIL_SAMPLES = 64  # minimum pupil samples across D
COVERAGE_SUBSAMPLES = 8  # per pupil cell and axis (fewer, down to 2, above 128 cells across D)
ALIAS_RINGS = 16  # diffraction units of room beyond the kernel on each side


@dataclass(frozen=True)
class Pupil:
    """A microlens aperture: ``shape`` "square" (side D) or "circle" (diameter D), turned by θ."""

    shape: str
    pitch_mm: float
    theta_deg: float = 0.0

    def coverage(self, x_mm: FloatArray, y_mm: FloatArray, cell_mm: float) -> FloatArray:
        """Area fraction of each cell (centres x, y; side ``cell_mm``) inside the aperture."""
        n = max(2, min(COVERAGE_SUBSAMPLES, math.ceil(1024 * cell_mm / self.pitch_mm)))
        offsets = ((np.arange(n) + 0.5) / n - 0.5) * cell_mm
        t = math.radians(self.theta_deg)
        ct, st = math.cos(t), math.sin(t)
        half = self.pitch_mm / 2.0
        total = np.zeros(np.broadcast(x_mm, y_mm).shape)
        for oy in offsets:
            for ox in offsets:
                px, py = x_mm + ox, y_mm + oy
                if self.shape == "circle":
                    inside = px * px + py * py <= half * half
                else:  # the square turns with the grid: lens frame = rotate by -θ
                    lx, ly = ct * px + st * py, -st * px + ct * py
                    inside = (np.abs(lx) <= half) & (np.abs(ly) <= half)
                total += inside
        return total / (n * n)


@dataclass(frozen=True)
class FinePsf:
    """A PSF on the FFT grid: ``values`` (N×N, unit sum, centre at [N//2, N//2]), spacing mm."""

    values: FloatArray
    spacing_mm: float
    pupil_step_mm: float


def fine_psf(
    pupil: Pupil,
    wavelength_mm: float,
    b_mm: float,
    defocus_per_mm: float,
    spacing_mm: float,
    size: int,
) -> FinePsf:
    """``|FFT(P·exp(iπ|ξ|²c/λ))|²`` sampled at ``spacing_mm`` on a ``size``² grid (even size).

    The pupil step is ``dξ = λb/(size·spacing)``; the pupil must fit (size·dξ >= D·√2).
    """
    if size % 2:
        raise ValueError("the FFT size must be even")
    step = wavelength_mm * b_mm / (size * spacing_mm)
    reach = pupil.pitch_mm / math.sqrt(2.0) if pupil.shape == "square" else pupil.pitch_mm / 2
    m = int(math.ceil(reach / step)) + 1
    if 2 * m + 1 > size:
        raise ValueError("the pupil does not fit the FFT grid: lower the PSF spacing")
    k = np.arange(-m, m + 1, dtype=np.float64) * step
    xi_x, xi_y = np.meshgrid(k, k, indexing="xy")
    aperture = pupil.coverage(xi_x, xi_y, step)
    phase = np.pi * defocus_per_mm / wavelength_mm * (xi_x * xi_x + xi_y * xi_y)
    field = np.zeros((size, size), dtype=np.complex128)
    centre = size // 2
    field[centre - m : centre + m + 1, centre - m : centre + m + 1] = aperture * np.exp(1j * phase)
    spectrum = scipy.fft.fft2(scipy.fft.ifftshift(field))
    intensity = scipy.fft.fftshift(spectrum.real**2 + spectrum.imag**2)
    return FinePsf(intensity / intensity.sum(), spacing_mm, step)


def line_psf(
    pitch_mm: float,
    wavelength_mm: float,
    b_mm: float,
    defocus_per_mm: float,
    spacing_mm: float,
    size: int,
) -> FloatArray:
    """One factor of the square pupil's separable PSF: ``|FFT(rect·exp(iπξ²c/λ))|²``, 1-D.

    The square pupil and the defocus phase both factor into x and y, so the 2-D
    PSF (in the lens frame) is ``p(x)·p(y)``. Samples at ``spacing_mm`` on a
    ``size`` grid (even), unit sum, centre at ``size//2``; the pupil cells hold
    their exact covered fraction of [-D/2, D/2].
    """
    if size % 2:
        raise ValueError("the FFT size must be even")
    step = wavelength_mm * b_mm / (size * spacing_mm)
    half = pitch_mm / 2.0
    m = int(math.ceil(half / step)) + 1
    if 2 * m + 1 > size:
        raise ValueError("the pupil does not fit the FFT grid: lower the PSF spacing")
    xi = np.arange(-m, m + 1, dtype=np.float64) * step
    cover = np.clip(np.minimum(xi + step / 2, half) - np.maximum(xi - step / 2, -half), 0, None)
    field = np.zeros(size, dtype=np.complex128)
    c = size // 2
    field[c - m : c + m + 1] = (
        cover / step * np.exp(1j * np.pi * defocus_per_mm / wavelength_mm * xi**2)
    )
    spectrum = scipy.fft.fft(scipy.fft.ifftshift(field))
    intensity = scipy.fft.fftshift(spectrum.real**2 + spectrum.imag**2)
    return intensity / intensity.sum()


def fft_size(samples: float) -> int:
    """The smallest even FFT-friendly size >= ``samples``."""
    size = scipy.fft.next_fast_len(int(math.ceil(samples)))
    while size % 2:
        size = scipy.fft.next_fast_len(size + 1)
    return size
