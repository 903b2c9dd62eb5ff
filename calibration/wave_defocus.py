"""Defocus and diffraction of a microlens together, as wave optics forms them.

Geometric optics blurs a defocused edge with the microlens aperture scaled to the
diameter ``d = (D/δ)·|Q − Q0|`` px (:mod:`calibration.defocus`), and diffraction spreads
it further; convolving the two (what a ray tracer that deflects each ray by the
aperture's diffraction pattern forms) is not what light does. Within the microlens's
diffraction-limited depth of focus (``d`` up to about twice the pattern's first zero
``s = λN/δ`` px, which is where a microlens at f/12 with 2.5 µm pixels stays over a whole
100 mm sweep) the defocus moves light from the pattern's core into its rings rather than
widening the core: edges widen far less than the convolution says.

For an aperture of width ``c`` (in units of its full width) along the edge normal, a
defocus phase ``π·d·t²/s`` over the pupil coordinate ``t`` gives the line-spread transfer
function (Hopkins) ``(c − |f|s)₊ · sinc(d·f·(c − |f|s))`` at ``f`` cycles/px (normalised
``sinc(x) = sin(πx)/(πx)``): a square aperture is one such slit (``c = 1``), a round one
the chords ``c(η) = √(1 − 4η²)`` of its rows averaged (the row's own phase drops out of
the line spread). At ``d = 0`` it is the diffraction pattern alone; as ``s → 0`` it is
the geometric box or half-ellipse of diameter ``d``. The focus fit keeps the pattern at
focus in its non-parametric static kernel and convolves it with the *effective* defocus
kernel ``K`` whose transfer function is the ratio of the two, ``T(f; d)/T(f; 0)``, up to
the cut-off ``1/s`` (beyond it the pattern passes nothing and ``K`` is taken as a point).
:func:`defocus_integral_rest` gives ``K``'s integrated cumulative line spread less the
ramp ``max(t, 0)``, what :class:`calibration.defocus_design.DefocusDesign` interpolates,
by a cosine transform over ``0 ≤ f < 1/s``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

WAVE_MIN_PX = 0.5
"""Smallest diffraction scale ``s`` (px) the transform is evaluated at; below it the kernel
is the geometric one blended linearly towards ``s = WAVE_MIN_PX`` (a pattern narrower than
half a pixel is within what the static kernel and the pixel response take)."""

DIFFRACTION_MAX_PX = 8.0
"""Upper bound of the fitted ``s`` (px): ``λN/δ`` of f/30 in red light on 2.5 µm pixels."""

_CHORDS_ETA, _CHORDS_WEIGHT = np.polynomial.legendre.leggauss(12)
# rows of a round aperture of unit diameter, η = sin(θ)/2 over θ ∈ (−π/2, π/2): chords
# c = cos θ with the row measure dη = cos θ dθ / 2 (smooth in θ, so Gauss-Legendre is exact
# to ~1e-9 for the smooth integrands here)
_THETA = 0.5 * np.pi * _CHORDS_ETA
_CHORD = np.cos(_THETA)
_ROW_WEIGHT = _CHORDS_WEIGHT * 0.5 * np.pi * 0.5 * np.cos(_THETA) / (np.pi / 4.0)


def line_spread_transfer(
    f: NDArray[np.floating], d: NDArray[np.floating], s: float, alpha: float
) -> NDArray[np.float64]:
    """The defocused aperture's line-spread transfer function ``T(f; d)`` (1 at ``f = 0``).

    ``f`` (cycles/px, ≥ 0) and ``d`` (geometric diameter, px) broadcast; ``s`` the
    diffraction scale ``λN/δ`` (px); ``alpha`` the share of the square aperture in a
    square/round mixture (1 square, 0 round).
    """
    f = np.asarray(f, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    out = np.zeros(np.broadcast(f, d).shape)
    if alpha > 0.0:
        width = np.maximum(1.0 - f * s, 0.0)
        out = out + alpha * width * np.sinc(d * f * width)
    if alpha < 1.0:
        round_part = np.zeros_like(out)
        for chord, weight in zip(_CHORD, _ROW_WEIGHT, strict=True):
            width = np.maximum(chord - f * s, 0.0)
            round_part += weight * width * np.sinc(d * f * width)
        out = out + (1.0 - alpha) * round_part
    return out


def defocus_integral_rest(
    t: NDArray[np.floating],
    d: NDArray[np.floating],
    s: float,
    alpha: float,
    jitter: NDArray[np.floating] | None = None,
) -> NDArray[np.float64]:
    """``∫C_K − ∫C_δ`` at ``t`` (px) for each diameter in ``d`` (px): one row each.

    ``K`` is the effective defocus kernel of diffraction scale ``s ≥ WAVE_MIN_PX`` (module
    docstring); ``C_K`` its cumulative line spread; ``jitter`` (px, one per row, or None)
    a Gaussian placement spread the row's kernel is convolved with. ``∫C_δ`` is the point
    part's, the ramp under the same jitter: :func:`jittered_ramp_rest` adds what that ramp
    differs from ``max(t, 0)`` by. The result is bounded and even in ``t``.
    """
    t = np.asarray(t, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    f, cosines = _frequencies_and_cosines(float(s), t.tobytes())
    df = 2.0 * f[0]
    focused = line_spread_transfer(f[None, :], np.zeros((1, 1)), s, alpha)
    # where the pattern passes nothing (a round aperture's rows all narrower than f·s at the
    # sampled chords) K is a point, as beyond the cut-off
    passes = focused > 1e-12
    ratio = np.where(
        passes,
        line_spread_transfer(f[None, :], d[:, None], s, alpha) / np.where(passes, focused, 1.0),
        1.0,
    )
    # ∫∫R for R = K - δ: its transform (T_K - 1)/(2πif)², even, band-limited to 1/s
    h = (1.0 - ratio) / (4.0 * np.pi**2 * f[None, :] ** 2)
    if jitter is not None:
        h = h * np.exp(-2.0 * np.pi**2 * f[None, :] ** 2 * np.asarray(jitter)[:, None] ** 2)
    return np.asarray((2.0 * df) * (h @ cosines), dtype=np.float64)


def jittered_ramp_rest(
    t: NDArray[np.floating], jitter: NDArray[np.floating]
) -> NDArray[np.float64]:
    """``E[max(t + σZ, 0)] − max(t, 0)`` at ``t`` (px) for each ``σ`` in ``jitter`` (px, one
    row each; 0 where ``σ`` is 0): the ramp of a point kernel under the placement jitter."""
    t = np.asarray(t, dtype=np.float64)[None, :]
    sigma = np.maximum(np.asarray(jitter, dtype=np.float64)[:, None], 1e-12)
    z = t / sigma
    smooth = t * ndtr(z) + sigma * np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)
    return np.asarray(smooth - np.maximum(t, 0.0), dtype=np.float64)


@lru_cache(maxsize=4)
def _frequencies_and_cosines(
    s: float, t_bytes: bytes
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The cosine transform's frequencies below the cut-off ``1/s`` (midpoints, 8 a cycle of
    the widest ``t``) and ``cos(2πft)`` at ``t`` (float64 bytes): the same for every
    evaluation at one ``s`` (a fit's Jacobian varies the other parameters)."""
    t = np.frombuffer(t_bytes, dtype=np.float64)
    extent = float(np.max(np.abs(t))) + 1.0
    cutoff = 1.0 / s
    n_freq = max(32, int(np.ceil(8.0 * extent * cutoff)))
    f = (np.arange(n_freq, dtype=np.float64) + 0.5) * (cutoff / n_freq)
    cosines = np.asarray(np.cos(2.0 * np.pi * f[:, None] * t[None, :]), dtype=np.float64)
    f.flags.writeable = False
    cosines.flags.writeable = False
    return f, cosines
