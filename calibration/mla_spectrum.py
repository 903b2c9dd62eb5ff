"""The first lattice of micro-image centres, from the white image's spectrum
(:mod:`calibration.mla_grid`, step 1).

The power spectrum of a Hann-windowed, high-passed central crop (at most
``FFT_CROP_PX`` square) shows the lattice's fundamental peaks at ``|k| = 1/pitch``;
the strongest peak in the expected pitch band gives pitch and rotation (modulo 90°,
reported in (-45°, 45°]), a harmonic is refused, and the phases of the two
fundamentals give the origin. Pixels as in :mod:`calibration.mla_grid`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid

FFT_CROP_PX = 2048
"""Side of the central crop whose spectrum is read (pixels)."""


@dataclass(frozen=True)
class Lattice:
    """A square lattice of micro-image centres: ``origin + i·(a, b) + j·(-b, a)`` (pixels),
    ``a = pitch·cos θ``, ``b = pitch·sin θ``."""

    origin: tuple[float, float]
    a: float  # pitch·cos θ
    b: float  # pitch·sin θ

    @property
    def pitch(self) -> float:
        return math.hypot(self.a, self.b)

    @property
    def theta(self) -> float:
        return math.atan2(self.b, self.a)

    def grid(self) -> LensGrid:
        return LensGrid(self.origin, self.pitch, self.theta)

    def centre(
        self, i: NDArray[np.int64], j: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return (
            self.origin[0] + self.a * i - self.b * j,
            self.origin[1] + self.b * i + self.a * j,
        )


def initial_lattice(
    img: NDArray[Any], lens_pitch_px: float, pitch_guess_px: float | None
) -> Lattice:
    """Pitch, rotation and origin from the spectrum of a central crop (see the module docstring).

    ``lens_pitch_px``: the data-sheet lens pitch ``D/δ``; ``pitch_guess_px``: an expected
    micro-image pitch when known (else 1.05 × the lens pitch)."""
    expected = pitch_guess_px if pitch_guess_px is not None else 1.05 * lens_pitch_px
    if pitch_guess_px is not None:
        band = (0.95 * pitch_guess_px, 1.05 * pitch_guess_px)
    else:
        band = (0.99 * lens_pitch_px, 1.25 * lens_pitch_px)
    crop, x0, y0 = _highpass_crop(img, expected)
    power = np.abs(np.fft.rfft2(crop)) ** 2
    k1 = _strongest_peak(power, band)
    peak = _power_at(power, k1)
    _reject_harmonic(power, k1, peak)
    pitch, theta = _both_fundamentals(power, k1)
    origin = _phase_origin(crop, x0, y0, pitch, theta)
    return Lattice(origin, pitch * math.cos(theta), pitch * math.sin(theta))


def _highpass_crop(
    img: NDArray[Any], expected_pitch: float
) -> tuple[NDArray[np.float32], int, int]:
    """Even-sized central crop (≤ 2048² px) minus its one-pitch box average, Hann-windowed; and its offset."""
    h, w = img.shape
    sy, sx = min(h, FFT_CROP_PX) // 2 * 2, min(w, FFT_CROP_PX) // 2 * 2  # even sizes
    y0, x0 = (h - sy) // 2, (w - sx) // 2
    crop = img[y0 : y0 + sy, x0 : x0 + sx].astype(np.float32)
    # a box of about one pitch flattens the lattice: subtracting it removes the vignetting envelope
    box = 2 * int(round(0.5 * expected_pitch)) + 1
    crop -= cv2.blur(crop, (box, box), borderType=cv2.BORDER_REFLECT)
    crop *= np.outer(np.hanning(sy), np.hanning(sx)).astype(np.float32)
    return crop, x0, y0


def _frequencies(power: NDArray[Any]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(fx, fy)`` in cycles/px of an ``rfft2`` spectrum of a ``(sy, sx)`` image, broadcastable."""
    sy, nx = power.shape
    sx = 2 * (nx - 1)
    fx = np.asarray(np.fft.rfftfreq(sx), dtype=np.float64)[None, :]
    fy = np.asarray(np.fft.fftfreq(sy), dtype=np.float64)[:, None]
    return fx, fy


def _strongest_peak(power: NDArray[Any], band: tuple[float, float]) -> tuple[float, float]:
    """Sub-bin frequency ``(kx, ky)`` of the strongest peak with a period in ``band`` (px)."""
    p_lo, p_hi = band
    fx, fy = _frequencies(power)
    fr = np.hypot(fx, fy)
    inband = (fr >= 1.0 / p_hi) & (fr <= 1.0 / p_lo)
    if not inband.any():
        raise ValueError("white image too small to resolve the micro-image pitch")
    ky, kx = np.unravel_index(int(np.argmax(np.where(inband, power, 0.0))), power.shape)
    floor = max(float(np.median(power[(fr >= 0.7 / p_hi) & (fr <= 1.4 / p_lo)])), 1e-30)
    ratio = float(power[ky, kx]) / floor
    if not ratio > 200.0:
        raise ValueError(
            f"no microlens lattice found with a micro-image pitch in [{p_lo:.1f}, {p_hi:.1f}] px "
            f"(spectral peak only {ratio:.0f}x the background): is this a white (flat-field) "
            "image of this camera?"
        )
    return _refine_peak(power, int(ky), int(kx))


def _power_at(power: NDArray[Any], k: tuple[float, float]) -> float:
    """Spectral power at the local maximum nearest frequency ``k``."""
    by, bx = _bin_of(power, k)
    return float(power[by, bx])


def _bin_of(power: NDArray[Any], k: tuple[float, float]) -> tuple[int, int]:
    """The local-maximum bin ``(row, col)`` nearest frequency ``k`` (mirrored to ``kx >= 0``)."""
    sy, nx = power.shape
    sx = 2 * (nx - 1)
    kx, ky = k
    if kx < 0:
        kx, ky = -kx, -ky
    bx = min(int(round(kx * sx)), nx - 1)
    by = int(round(ky * sy)) % sy
    return _local_max(power, by, bx)


def _both_fundamentals(power: NDArray[Any], k1: tuple[float, float]) -> tuple[float, float]:
    """Pitch (px) and rotation θ (rad, in (-π/4, π/4]) averaged over the two perpendicular peaks."""
    theta = (math.atan2(k1[1], k1[0]) + math.pi / 4) % (math.pi / 2) - math.pi / 4
    kk = math.hypot(*k1)
    c, s = math.cos(theta), math.sin(theta)
    ks = [_refine_peak(power, *_bin_of(power, (ex * kk, ey * kk))) for ex, ey in ((c, s), (-s, c))]
    pitch = 2.0 / (math.hypot(*ks[0]) + math.hypot(*ks[1]))
    offsets = [
        (math.atan2(ky, kx) - theta + math.pi / 4) % (math.pi / 2) - math.pi / 4 for kx, ky in ks
    ]
    return pitch, theta + 0.5 * sum(offsets)


def _reject_harmonic(power: NDArray[Any], k: tuple[float, float], peak: float) -> None:
    """``ValueError`` when the peak at ``k`` is a harmonic (k/2, or k/√2 at ±45°) of a coarser lattice."""
    sy = power.shape[0]
    sx = 2 * (power.shape[1] - 1)
    kx, ky = k
    for cx, cy in (
        (0.5 * kx, 0.5 * ky),
        (0.5 * (kx - ky), 0.5 * (kx + ky)),
        (0.5 * (kx + ky), 0.5 * (ky - kx)),
    ):
        if abs(cx * sx) < 1.5 and abs(cy * sy) < 1.5:
            continue  # too close to DC to tell
        if _power_at(power, (cx, cy)) > 0.05 * peak:
            raise ValueError(
                f"the periodicity found at {1.0 / math.hypot(kx, ky):.1f} px is a harmonic of a "
                f"lattice with a pitch of about {1.0 / math.hypot(cx, cy):.1f} px: check "
                "lens_pitch_px (D/δ) and pitch_guess_px"
            )


def _local_max(power: NDArray[Any], by: int, bx: int) -> tuple[int, int]:
    sy, sx = power.shape
    best = (by, bx)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            yy, xx = (by + dy) % sy, bx + dx
            if 0 <= xx < sx and power[yy, xx] > power[best]:
                best = (yy, xx)
    return best


def _refine_peak(power: NDArray[Any], ky: int, kx: int) -> tuple[float, float]:
    """Sub-bin peak position (Gaussian interpolation), as a frequency ``(kx, ky)`` in cycles/px."""
    sy, nx = power.shape
    sx = 2 * (nx - 1)

    def ln(v: float) -> float:
        return math.log(max(float(v), 1e-300))

    def interp(lm: float, l0: float, lp: float) -> float:
        den = lm - 2 * l0 + lp
        return 0.0 if den >= 0 else 0.5 * (lm - lp) / den

    l0 = ln(power[ky, kx])
    dy = interp(ln(power[(ky - 1) % sy, kx]), l0, ln(power[(ky + 1) % sy, kx]))
    dx = interp(ln(power[ky, kx - 1]), l0, ln(power[ky, kx + 1])) if 1 <= kx < nx - 1 else 0.0
    fy = (ky if ky < sy // 2 else ky - sy) + dy
    return ((kx + dx) / sx, fy / sy)


def _phase_origin(
    crop: NDArray[np.float32], x0: int, y0: int, pitch: float, theta: float
) -> tuple[float, float]:
    """A lattice node from the phases of the two fundamentals (bright discs have positive FT)."""
    sy, sx = crop.shape
    cx, cy = (sx - 1) / 2.0, (sy - 1) / 2.0
    u = np.arange(sx) - cx
    v = np.arange(sy) - cy
    c, s = math.cos(theta), math.sin(theta)
    phases = []
    for ex, ey in ((c, s), (-s, c)):
        kx, ky = ex / pitch, ey / pitch
        row = np.exp(-2j * np.pi * kx * u).astype(np.complex64)
        col = np.exp(-2j * np.pi * ky * v).astype(np.complex64)
        val = complex(col @ (crop @ row))
        phases.append(-np.angle(val) / (2 * np.pi))
    # node n: e1·(n - C) = phase1·pitch, e2·(n - C) = phase2·pitch
    ox = cx + x0 + pitch * (c * phases[0] - s * phases[1])
    oy = cy + y0 + pitch * (s * phases[0] + c * phases[1])
    return (float(ox), float(oy))
