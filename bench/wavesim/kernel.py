"""A frame's PSF kernel on the supersampled cell grid (polychromatic, truncated, unit sum).

Units: mm (wavelengths in mm here). The kernel's cells have side ``ds = δ/ss``
and hold the PSF's mass over each cell (the PSF is computed ``n`` times finer,
``n`` odd, and summed over n×n blocks), so hard-edged geometric blurs (λ → 0)
are area-integrated.

Why these grids. The FFT samples the pupil, which makes the PSF's *amplitude*
periodic with the FFT field: the rings of the neighbouring periods interfere
with the true rings, an error of the order x/field at distance x (the
amplitude of a hard-edged pupil decays only like 1/x). So the field is made
much wider than the kernel:

* square pupil (the default): the PSF factors, ``p(x')·p(y')`` in the lens
  frame (turned by θ), so a 1-D FFT of 2^17 or more samples at ``ds/(8n)``
  gives a field of thousands of pixels (ring errors < 0.1 %); the 2-D kernel
  samples the factors at the turned fine-grid coordinates (linear
  interpolation on the 8× finer 1-D grid; exact when θ = 0);
* disc pupil: a 2-D FFT at spacing ``ds/n`` with a field of ``16·H`` (H the
  kernel half-width; at most 2H + 256 diffraction units ``λb/D``, which only
  binds as λ → 0 where there are no rings to speak of) and at least 64
  diffraction units; the
  rings near the kernel's edge are then within ~10 % of their (tiny) true
  intensity, a redistribution of ~0.1 % of the energy.

The kernel's half-width H is ``rings·λ_max·b/D`` (default 8 rings) plus the
geometric blur's half-diagonal plus 2 px; what lies outside is dropped and the
kernel renormalised; the dropped fraction is reported (``truncated_energy``,
~2 % for the square pupil, ~1 % for the disc at 8 rings).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.wavesim.psf import FloatArray, Pupil, fft_size, fine_psf, line_psf

LINE_REFINE = 8  # the 1-D factor is sampled this much finer than the 2-D fine grid
LINE_MIN_SIZE = 1 << 17
DISC_FIELD_KERNELS = 16.0  # disc FFT field >= this many kernel half-widths
DISC_MIN_RINGS = 64.0  # and >= this many diffraction units


@dataclass(frozen=True)
class Kernel:
    """(2M+1)² cell masses (sum 1, centre [M, M]) of cell side ``cell_mm``.

    ``truncated_energy``: the PSF energy outside the kernel before renormalising
    (mean over the wavelengths); ``fine_factors``: n per wavelength;
    ``fft_sizes``: the FFT length per wavelength (1-D for the square pupil).
    """

    values: FloatArray
    cell_mm: float
    truncated_energy: float
    fine_factors: tuple[int, ...]
    fft_sizes: tuple[int, ...]

    @property
    def half_cells(self) -> int:
        return self.values.shape[0] // 2


def half_width_mm(
    pupil: Pupil,
    wavelengths_mm: tuple[float, ...],
    b_mm: float,
    defocus_per_mm: float,
    pixel_mm: float,
    rings: float,
) -> float:
    """``H = rings·λ_max·b/D + (geometric blur half-diagonal) + 2 px``, mm."""
    diffraction = max(wavelengths_mm) * b_mm / pupil.pitch_mm
    blur = pupil.pitch_mm * b_mm * abs(defocus_per_mm)  # D·b·|1/a - 1/a_f|
    return rings * diffraction + blur / math.sqrt(2.0) + 2.0 * pixel_mm


def fine_factor(pitch_mm: float, wavelength_mm: float, b_mm: float, cell_mm: float) -> int:
    """Odd n with ``λb/(cell/n) >= 2·D``: the PSF sampled at or beyond intensity Nyquist."""
    n = max(1, math.ceil(2.0 * pitch_mm * cell_mm / (wavelength_mm * b_mm)))
    return n + 1 - n % 2


def frame_kernel(
    pupil: Pupil,
    wavelengths_mm: tuple[float, ...],
    b_mm: float,
    defocus_per_mm: float,
    cell_mm: float,
    half_cells: int,
) -> Kernel:
    """The equal-weight polychromatic PSF as (2·half_cells+1)² cell masses of side ``cell_mm``."""
    width = 2 * half_cells + 1
    total = np.zeros((width, width))
    lost, factors, sizes = [], [], []
    for lam in wavelengths_mm:
        n = fine_factor(pupil.pitch_mm, lam, b_mm, cell_mm)
        if pupil.shape == "square":
            fine, size = _square_fine(pupil, lam, b_mm, defocus_per_mm, cell_mm / n, width * n)
        else:
            fine, size = _disc_fine(pupil, lam, b_mm, defocus_per_mm, cell_mm / n, width * n)
        cells = fine.reshape(width, n, width, n).sum(axis=(1, 3))
        kept = float(cells.sum())
        lost.append(1.0 - kept)
        total += cells / kept
        factors.append(n)
        sizes.append(size)
    values = total / len(wavelengths_mm)
    return Kernel(values, cell_mm, float(np.mean(lost)), tuple(factors), tuple(sizes))


def _square_fine(
    pupil: Pupil, lam: float, b: float, c: float, spacing: float, samples: int
) -> tuple[FloatArray, int]:
    """The centred ``samples``² fine PSF of the turned square pupil (masses at ``spacing``)."""
    step = spacing / LINE_REFINE
    size = fft_size(max(LINE_MIN_SIZE, 64 * samples * LINE_REFINE))
    line = line_psf(pupil.pitch_mm, lam, b, c, step, size)
    grid = (np.arange(size) - size // 2) * step
    r = samples // 2
    k = np.arange(-r, r + 1) * spacing
    x, y = np.meshgrid(k, k, indexing="xy")
    t = math.radians(pupil.theta_deg)
    ct, st = math.cos(t), math.sin(t)
    if t == 0.0:
        centre = size // 2
        idx = centre + np.arange(-r, r + 1) * LINE_REFINE
        fx = line[idx]
        fine = np.outer(fx, fx)
    else:
        fine = np.interp(ct * x + st * y, grid, line) * np.interp(-st * x + ct * y, grid, line)
    # point samples of a unit-sum density at spacing `step` -> masses at `spacing`
    return fine * LINE_REFINE * LINE_REFINE, size


def _disc_fine(
    pupil: Pupil, lam: float, b: float, c: float, spacing: float, samples: int
) -> tuple[FloatArray, int]:
    """The centred ``samples``² fine PSF of the disc pupil (2-D FFT)."""
    diffraction = lam * b / pupil.pitch_mm
    half = samples * spacing / 2.0
    room = min((DISC_FIELD_KERNELS - 2.0) * half, 4.0 * DISC_MIN_RINGS * diffraction)
    field = max(2.0 * half + room, DISC_MIN_RINGS * diffraction)
    size = fft_size(max(field / spacing, samples + 2))
    psf = fine_psf(pupil, lam, b, c, spacing, size)
    centre, r = size // 2, samples // 2
    return psf.values[centre - r : centre + r + 1, centre - r : centre + r + 1], size
