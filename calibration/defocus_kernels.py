"""The choice between the two defocus kernels of :func:`calibration.defocus.fit_defocus`.

Geometric optics (the microlens aperture scaled to the defocus diameter, convolved with a
static kernel) is fitted first; the wave-optical kernel (:mod:`calibration.wave_defocus`,
the microlens's diffraction pattern defocused) is tried beside it when it could describe
the edges better (:func:`wave_fit`) and taken when the chi-square says so
(``WAVE_SELECT_CHI2``), or whatever the chi-square says when the white image's rims rule
geometric optics out (:func:`rims_exclude_geometric`): the rims are the same microlens
aperture far from focus (:mod:`calibration.white_rim`), and a geometric fit with a much
smaller aperture than theirs imitates diffraction. Every fit is re-weighted frame by frame
(:func:`robust_fit`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .defocus_problem import DefocusProblem, Fit
from .wave_defocus import WAVE_MIN_PX
from .white_rim import WhiteRim

WAVE_SELECT_CHI2 = 9.0
"""The chi-square the wave-optical defocus kernel (one parameter more, the diffraction scale)
must gain over the geometric one to be taken (:func:`wave_fit`): three sigma.

The choice is not trusted further than that. Whenever both kernels were fitted, ``Q0``'s
uncertainty includes their disagreement, ``|Q0_geometric - Q0_wave|`` in quadrature
(``DefocusFit.Q0_se_kernel``): within the microlens's diffraction-limited depth of focus
the edges widen by a few per cent of their width over a whole sweep, both models fit
that to within their noise and the model floor, and the chi-square prefers one by
chance of shape (on 19 Fourier-optics sweeps geometric optics was kept on 15, with ``κ``
0.26-0.46 and ``Q0`` up to 1.9 % off, while the wave kernel's was within 1.1σ on all;
their difference is what the data cannot settle). Where the edges are far
from diffraction-limited the wave kernel is not tried and the term is zero."""

WAVE_TRIAL_COST_RATIO = 2.0
"""The wave-optical fit is tried only when one of its starts (:func:`wave_fit`) costs less
than this times the geometric fit's chi-square: a saving of time, not a choice of model
(on exact wave-optical edges the best start cost 0.2-1.8 times the geometric fit, on edges
formed the convolution's way 1e4-1e6 times; noise brings both towards 1, where the fit is
tried and the chi-square decides)."""

RIM_KAPPA_MIN_FRACTION = 0.7
"""Geometric optics is ruled out when its aperture scale ``κ``, even ``RIM_KAPPA_SIGMAS``
standard errors larger, is below this fraction of the one the white image's rims show
(:mod:`calibration.white_rim`, far from focus, where the microlens aperture and not its
diffraction blurs them): the edges near focus are then formed by something the geometric
kernel can only imitate with a smaller aperture (a diffraction-limited microlens: on
Fourier-optics sweeps geometric optics fitted κ 0.32-0.47 where the rims show 0.8-0.9),
and the wave-optical kernel is taken. Where both describe the same aperture they agree to
within 12 %: the rims read 0.98-1.05 of the fit's κ on square and round lenses of three
renderers and 20 random cameras, 1.12-1.14 where ray-traced diffraction widens the rims
(the fit's κ 0.88-0.89 of theirs). The fraction lies 2.5 times that largest disagreement
below agreement; at 0.5 (session 54) noisy Fresnel edges that fitted κ 0.41-0.44 against
rims of 0.81-0.84 kept geometric optics, their ``Q0`` up to 0.8 % off, where the
wave-optical kernel's was within 0.35 %."""

RIM_KAPPA_SIGMAS = 3.0
"""Standard errors of the geometric fit's ``κ`` (the larger of its curvature and
cluster-robust ones) it must lie below ``RIM_KAPPA_MIN_FRACTION`` of the rims' to be
ruled out: a sweep that fixes ``κ`` poorly rules nothing out."""

RIM_MIN_DEFOCUS_PX = 4.0
"""The rims decide only where their defocus ``(D/δ)·|Q0 - b/L|`` is at least this (px):
a smaller one is not told from the static blur."""

ROBUST_ROUNDS = 2
"""Rounds of re-weighting each observation by its own reduced chi-square (see
:meth:`DefocusProblem.downweight`)."""


def robust_fit(
    prob: DefocusProblem,
    theta0: NDArray[np.float64],
    rows: NDArray[np.int64],
    q_bounds: tuple[float, float],
    *,
    diffraction: bool,
) -> Fit:
    """The fit from ``theta0``, then re-weighted (:func:`reweighted`)."""
    fitted = prob.fit(theta0, rows, q_bounds, diffraction=diffraction)
    return reweighted(prob, fitted, rows, q_bounds, diffraction=diffraction)


def reweighted(
    prob: DefocusProblem,
    fitted: Fit,
    rows: NDArray[np.int64],
    q_bounds: tuple[float, float],
    *,
    diffraction: bool,
) -> Fit:
    """``ROBUST_ROUNDS`` of re-weighting each frame by its own reduced chi-square at the
    last fit and fitting again (the problem keeps the last weights)."""
    for _ in range(ROBUST_ROUNDS):
        prob.downweight(fitted[0], rows)
        fitted = prob.fit(fitted[0], rows, q_bounds, diffraction=diffraction)
    return fitted


def kernel_rms(weights: NDArray[np.floating], grid: NDArray[np.floating]) -> float:
    """RMS (px) of a static kernel of non-negative ``weights`` at the offsets ``grid``."""
    return float(np.sqrt(np.sum(weights * grid**2) / max(np.sum(weights), 1e-12)))


def static_rms(prob: DefocusProblem, theta: NDArray[np.float64], rows: NDArray[np.int64]) -> float:
    """RMS (px) of the static kernel the fit at ``theta`` solves for."""
    weights = np.maximum(prob.solve_linear(prob.design(theta, rows), rows)[0], 0.0)
    return kernel_rms(weights, prob.grid)


def rim_kappa(
    prob: DefocusProblem,
    theta: NDArray[np.float64],
    rows: NDArray[np.int64],
    rim: tuple[WhiteRim | None, float],
    lens_pitch_px: float,
) -> float:
    """``κ`` the white's rims show with the static blur of the fit at ``theta`` taken off
    (:meth:`WhiteRim.aperture_scale`); NaN without rims or where their defocus is below
    ``RIM_MIN_DEFOCUS_PX``."""
    white_rim, q_rim = rim
    if white_rim is None or not np.isfinite(q_rim):
        return float("nan")
    if not lens_pitch_px * abs(float(theta[0]) - q_rim) >= RIM_MIN_DEFOCUS_PX:
        return float("nan")
    return white_rim.aperture_scale(
        q0=float(theta[0]),
        q_rim=q_rim,
        lens_pitch_px=lens_pitch_px,
        static_rms_px=static_rms(prob, theta, rows),
    )


def wave_fit(
    prob: DefocusProblem,
    geometric: Fit,
    rows: NDArray[np.int64],
    q_bounds: tuple[float, float],
    *,
    start_scale: float,
    forced: bool = False,
) -> tuple[Fit | None, float]:
    """The fit with the microlens's diffraction (:mod:`calibration.wave_defocus`), when it
    describes the edges better than geometric optics; None (and the problem's weights as
    the geometric fit left them) when it does not.

    It starts from the geometric fit's ``Q0`` and a full square or round aperture with the
    diffraction scale ``s`` that fits best of a few (``start_scale``, an earlier fit's, among
    them), from f/4 to f/20 in green light, when that start costs less than
    ``WAVE_TRIAL_COST_RATIO`` times the geometric fit (geometric optics fitted ``κ`` to make up
    for the diffraction it does not have: on exact wave-optical edges 0.4-0.7). It is taken
    when, weighed alike (the geometric fit's frame weights), it lowers the chi-square by more
    than ``WAVE_SELECT_CHI2`` (one parameter more, at three sigma) and its scale ``s`` is at
    least ``WAVE_MIN_PX``, and then re-weighted as the geometric fit was (and kept if ``s``
    stays there). Below ``WAVE_MIN_PX`` the kernel is the geometric one blended towards the
    pattern at ``WAVE_MIN_PX`` (:mod:`calibration.wave_defocus`): a shape between the two
    models, not a diffraction pattern the edges resolve, and not a reason to leave geometric
    optics (a ray-traced sweep whose diffraction is a fixed pattern per ray, exactly the
    geometric model with a static kernel, took the blend at ``s`` 0.16-0.29 px by 45 of
    chi-square, the focus plane 1.2-2.3 mm off on four seeds; geometric optics 0.13-0.48 mm,
    tests/test_defocus_blend.py).
    ``forced`` (geometric optics ruled out by the white's rims, :data:`RIM_KAPPA_MIN_FRACTION`):
    tried and taken whatever its cost and chi-square, when its scale reaches ``WAVE_MIN_PX``.
    Also returns the wave-optical fit's ``Q0`` whether taken or not (NaN when it was not
    tried), whose difference from the taken one is in ``Q0``'s uncertainty."""
    theta_g = geometric[0]
    geometric_cost = float(np.sum(prob.residuals(theta_g, rows) ** 2))
    scales = np.unique(np.array([1.0, 2.0, 3.0, 4.5, max(start_scale, 1.0)]))
    trials = [np.array([theta_g[0], 1.0, shape, sc]) for sc in scales for shape in (0.0, 1.0)]
    costs = [float(np.sum(prob.residuals(t, rows) ** 2)) for t in trials]
    if not forced and min(costs) > WAVE_TRIAL_COST_RATIO * geometric_cost:
        return None, float("nan")
    trial = prob.fit(trials[int(np.argmin(costs))], rows, q_bounds, diffraction=True)
    trial_q0 = float(trial[0][0]) if trial[0][3] > 0.0 else float("nan")
    gain = geometric_cost - float(np.sum(prob.residuals(trial[0], rows) ** 2))
    if not (trial[0][3] >= WAVE_MIN_PX and (forced or gain > WAVE_SELECT_CHI2)):
        return None, trial_q0
    kept_scale = prob.noise_scale.copy()
    wave = reweighted(prob, trial, rows, q_bounds, diffraction=True)
    if wave[0][3] >= WAVE_MIN_PX:
        return wave, float(wave[0][0])
    prob.scale_noise(kept_scale)
    return None, trial_q0


def rims_exclude_geometric(geometric: Fit, rim_kappa: float) -> bool:
    """Whether the white image's rims (their ``κ``, NaN when not measured) rule the
    geometric fit out: its ``κ`` plus ``RIM_KAPPA_SIGMAS`` standard errors below
    ``RIM_KAPPA_MIN_FRACTION`` of theirs."""
    if not rim_kappa > 0:
        return False
    theta, cov, robust, _ = geometric
    kappa_se = float(np.sqrt(max(cov[1, 1], robust[1, 1], 0.0)))
    return bool(float(theta[1]) + RIM_KAPPA_SIGMAS * kappa_se < RIM_KAPPA_MIN_FRACTION * rim_kappa)
