"""The focus plane from the geometric defocus of the micro-images, fitted to the whole sweep.

OPTICS.md §1: a microlens images the main image, at distance ``a`` in front of
it, onto the sensor with magnification ``-b/a = -Q`` and blurs every point
into the microlens aperture scaled to the diameter

    d = D·b·|1/a_f - 1/a| / δ = (D/δ)·|Q - Q0|   pixels,   Q0 = b/a_f,

exactly, for any object distance (thin lenses). ``Q`` is what the disparity
measures in every frame to about 1e-4, so the only unknown of the defocus is
``Q0``, the value of ``Q`` at the focus plane. An edge in a micro-image is
therefore the step convolved with

- the projection of the aperture onto the edge normal, scaled to ``d``: a box
  for a square aperture whose sides are parallel to the edge, a half-ellipse
  ``√(1 - (2t/d)²)`` for a round one (shape ``α``: 1 box, 0 round, between:
  their mixture, e.g. a hexagon); the scale ``κ`` (1 for a fill factor of 1)
  is fitted too, so an aperture smaller than the pitch does not bias ``Q0``.
  ``κ`` is bounded by 1 (``KAPPA_MAX``): it scales the kernel's RMS width to
  that of a box of the full pitch, and no microlens aperture is wider in RMS
  than the square cell of side ``D`` its lens occupies (a round lens of
  diameter ``D`` has ``κ = 0.87``, a hexagonal cell ``0.91``; vignetting only
  shrinks it). Without the bound the ray noise of a Monte-Carlo renderer let
  ``κ`` drift to 1.02-1.04, trading it against ``Q0``;
- a static kernel ``S`` shared by every frame: the pixel response (area or
  point sampling), the lens PSF, diffraction, the sensor. ``S`` is not given
  a shape: it is a symmetric, non-parametric density on a grid of
  ``STATIC_STEP_PX`` out to ``STATIC_HALF_PX``, estimated with the rest.

That is geometric optics. Light is a wave: within the microlens's diffraction-limited
depth of focus a defocus moves light from the diffraction pattern's core into its rings
instead of widening the core, which the convolution above does not describe (exact
Fresnel edges of the paper's camera fitted ``κ`` 0.43 and put ``Q0`` 0.36 % off).
:func:`fit_defocus` therefore also fits the wave-optical kernel
(:mod:`calibration.wave_defocus`, one parameter more: the pattern's scale ``s = λN/δ``)
and takes it when it describes the edges better by more than ``WAVE_SELECT_CHI2`` with a
pattern of at least ``WAVE_MIN_PX`` (:mod:`calibration.defocus_kernels`); whenever both were
fitted, the two models' disagreement on ``Q0`` is part of its uncertainty. Unless the white
image's rims rule geometric optics out: they are blurred by the same microlens aperture
far from focus (:mod:`calibration.white_rim`), and a geometric fit whose aperture is
clearly less than theirs (``RIM_KAPPA_MIN_FRACTION``) is imitating diffraction; the
wave-optical kernel is then taken, and the disagreement is not an uncertainty.

Each frame contributes its binned, normalised edge-spread function
(:mod:`calibration.edge_spread`; of the same corners throughout the sweep,
:func:`calibration.defocus_corners.sweep_corners`), with a free offset and gain (tails of
the static blur beyond the profile) and a free shift (the corner lattice that
placed the samples has a common error, :mod:`calibration.edge_profiles`). The
lattice's placement error also spreads the samples: the function is the edge
spread convolved with a Gaussian of the recorded ``jitter_px``, and the model
is too. ``Q`` per frame is the calibrated camera's ``Q(u)``
(:mod:`calibration.combine`), which is more precise near focus than any one
frame's disparity. For given ``(Q0, κ, α)`` the model is linear in ``S`` and,
separately, in each frame's offset, gain and shift; these are solved exactly
(alternating, smoothness-regularised least squares), and ``(Q0, κ, α)`` by
nonlinear least squares on the projected residuals (variable projection).
Each frame's errors are then scaled by its own reduced chi-square when above
one and the fit repeated (``ROBUST_ROUNDS`` of :mod:`calibration.defocus_kernels`): a
frame the model describes worse than its noise (a sharp, point-sampled edge whose
placement the lattice resolves only to a fraction of the sample spacing; a defect) weighs
less. The
uncertainty of ``Q0`` comes from the curvature of that fit, scaled by its
reduced chi-square, and from a cluster-robust (sandwich) estimate with the
frames as clusters (the samples of one frame share its normalisation): the
larger, with a systematic term (``DIAMETER_SYSTEMATIC_PX``) in quadrature. Then
:func:`jackknife_defocus` leaves out contiguous blocks of the sweep in turn: when the
refits move ``Q0`` more than the model allows, the jackknife's uncertainty is taken (and
the result warns). The numerical core is :mod:`calibration.defocus_problem`.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.stats import norm

from .defocus_corners import sweep_corners
from .defocus_design import FIT_HALF_PX, diameter_factor
from .defocus_kernels import (
    kernel_rms,
    rim_kappa,
    rims_exclude_geometric,
    robust_fit,
    wave_fit,
)
from .defocus_problem import DefocusProblem, EdgeObservation
from .edge_spread import ESF_BIN_PX, BinnedEsf
from .white_rim import WhiteRim

__all__ = [
    "DIAMETER_SYSTEMATIC_PX",
    "DefocusFit",
    "DefocusNotDetermined",
    "EdgeObservation",
    "blur_model_warning",
    "fit_defocus",
    "jackknife_defocus",
    "jackknife_warning",
    "rough_focus",
]

DIAMETER_SYSTEMATIC_PX = 0.0076
"""Systematic uncertainty of the defocus diameter near the focus plane (px), added in
quadrature to ``Q0``'s statistical one as ``DIAMETER_SYSTEMATIC_PX/(κ·D/δ)``. It is not
the fit's: on exact edge-spread functions the fit recovers ``Q0`` to 3e-6 (relative,
tests/test_defocus.py), and over seeds its noise averages out. It is the renderer's: the
mean error of ``Q0`` over 20 seeded sweeps of each of three independently written
renderers (the project's simulator, the analytic indsim, the Monte-Carlo mcsim) and their
accuracy sweeps is 0.0002-0.0076 px of diameter, where the statistical uncertainty alone
is 0.001-0.004 px; the edge-spread functions a frame yields differ from the model by that
much depending on how its image was formed. The largest of those means is taken, so that
none of the three renderers' biases exceeds it: a camera is one more renderer we did not
write. (Since the corners' rim samples are left out of their fits, 2026-12-05, the means
over the coverage sweeps are 0.0001-0.0032 px; the constant is kept at the largest
measured.)"""

JACKKNIFE_BLOCKS = 8
"""Contiguous blocks of the sweep (in ``Q``, i.e. along the rail) left out in turn by
:func:`jackknife_defocus`; each refit keeps 7/8 of the frames, and the jackknife variance
has 7 degrees of freedom."""

JACKKNIFE_THREADS = 2
"""The jackknife's refits run on this many threads (numpy releases the GIL in most of a
refit's array work)."""

FIT_THREADS = 2
"""The whole-sweep fit's evaluations run on this many threads, each on a contiguous block
of the observations (:class:`DefocusProblem`'s ``blocks``; the jackknife's refits, already
parallel, run their evaluations in one block)."""

JACKKNIFE_FALSE_ALARM = 0.01
"""Probability that a sweep the blur model describes is called inconsistent by the
jackknife: each block's shift of ``Q0`` is tested at ``JACKKNIFE_FALSE_ALARM/G`` (two-sided,
Bonferroni over the G blocks) against the uncertainty of the difference between the refit
and the full fit (:func:`jackknife_defocus`)."""


JACKKNIFE_WARN_FACTOR = 2.0
"""The result warns when an inconsistent jackknife more than doubles ``Q0``'s uncertainty
(below that the larger uncertainty is reported without a warning: on the Monte-Carlo
renderer's sweeps the blocks' shifts reach 3-4 times the statistical uncertainty, which
the systematic term already covers)."""


@dataclass(frozen=True)
class DefocusFit:
    """The whole-sweep defocus model (``Q0`` dimensionless, widths in pixels)."""

    Q0: float
    Q0_se: float
    Q0_se_curvature: float
    Q0_se_cluster: float
    Q0_se_systematic: float
    kappa: float
    shape_box: float
    diffraction_px: float
    """The microlens's diffraction scale ``s = λN/δ`` (px) the wave-optical defocus kernel
    fitted (:mod:`calibration.wave_defocus`); 0: geometric optics describes the edges."""
    chi2_reduced: float
    static_kernel_px: NDArray[np.float64]
    static_weights: NDArray[np.float64]
    static_rms_px: float
    blur_px: dict[int, float] = field(default_factory=dict)
    frames: int = 0
    max_blur_px: float = float("nan")
    spread_px: dict[int, float] = field(default_factory=dict)
    model_spread_px: dict[int, float] = field(default_factory=dict)
    frame_noise_scale: dict[int, float] = field(default_factory=dict)
    Q0_se_model: float = float("nan")
    Q0_se_jackknife: float = float("nan")
    jackknife_Q0: tuple[float, ...] = ()
    jackknife_z: tuple[float, ...] = ()
    jackknife_consistent: bool | None = None
    Q0_se_kernel: float = 0.0
    """``|Q0 - Q0_other_kernel|``, in ``Q0_se_model`` (quadrature): the two blur models, when
    both were fitted, put the focus plane this far apart
    (:data:`~calibration.defocus_kernels.WAVE_SELECT_CHI2`)."""
    Q0_other_kernel: float = float("nan")
    """``Q0`` of the blur model not taken (geometric or wave-optical); NaN when the
    wave-optical one was not tried (edges far from diffraction-limited)."""
    rim_kappa: float = float("nan")
    """``κ`` the white image's rims show (:meth:`WhiteRim.aperture_scale`, with the geometric
    fit's static blur; NaN: not measured)."""
    geometric_excluded: bool = False
    """Geometric optics was ruled out by the rims
    (:data:`~calibration.defocus_kernels.RIM_KAPPA_MIN_FRACTION`) and the wave-optical kernel
    taken without the chi-square's say, and without the two kernels' disagreement in the
    uncertainty."""
    corners: str = ""
    """Whose edge-spread functions were fitted (:func:`sweep_corners`): ``both`` (merged in
    every frame), ``standard`` or ``reference`` (that corner alone throughout)."""

    def blur_diameter_px(
        self, Q: float | NDArray[np.float64], lens_pitch_px: float
    ) -> NDArray[np.float64]:
        """Model defocus diameter ``κ' (D/δ) |Q - Q0|`` (pixels) of the fitted aperture shape."""
        factor = diameter_factor(self.kappa, self.shape_box)
        return factor * lens_pitch_px * np.abs(np.asarray(Q, dtype=np.float64) - self.Q0)


class DefocusNotDetermined(ValueError):
    """The blur does not change enough over the sweep to locate the focus plane."""


def rough_focus(observations: Sequence[EdgeObservation]) -> tuple[float, float, float]:
    """``(Q0, σ, κ)`` before the fit: ``Q`` of the sharpest edge spread, uncertain by half the
    sweep's range of ``Q``, a full aperture (NaN Q0 when no observation has a width)."""
    obs = [o for o in observations if np.isfinite(o.Q) and o.esf.x.size >= 10]
    spreads = np.array([o.esf.spread_px() for o in obs], dtype=np.float64)
    if not np.isfinite(spreads).any():
        return float("nan"), float("inf"), 1.0
    q = np.array([o.Q for o in obs])
    span = float(np.ptp(q)) if q.size > 1 else float(q[0])
    return float(q[int(np.nanargmin(spreads))]), max(0.5 * span, 1e-6), 1.0


def fit_defocus(
    observations: Sequence[EdgeObservation],
    *,
    lens_pitch_px: float,
    min_blur_px: float = 0.4,
    start: tuple[float, float, float, float] | None = None,
    rim: WhiteRim | None = None,
    rim_q: float = float("nan"),
) -> DefocusFit:
    """Fit ``Q0`` (and the static kernel) to the edge-spread functions of a sweep.

    ``lens_pitch_px`` is ``D/δ``; ``start`` an earlier fit's ``(Q0, κ, α, s)`` to start
    from instead of the coarse scan (a refit on a refined ``Q(u)``); ``rim`` the white
    image's rims and ``rim_q`` the ``Q = b/L`` they are imaged with (the white's scale less
    one), which can rule geometric optics out
    (:data:`~calibration.defocus_kernels.RIM_KAPPA_MIN_FRACTION`). Raises
    :class:`DefocusNotDetermined` when fewer than 5 frames have edge-spread functions, or
    when the model's defocus never exceeds ``min_blur_px`` pixels anywhere in the sweep (the
    blur does not change measurably: the focus plane cannot be located).
    """
    obs = _usable(observations)
    frames = sorted({o.frame for o in obs})
    if len(frames) < 5:
        raise DefocusNotDetermined(
            f"edge-spread functions in only {len(frames)} frames (need 5): the focus plane "
            "cannot be located"
        )
    with ThreadPoolExecutor(FIT_THREADS) as pool:
        prob = DefocusProblem(obs, lens_pitch_px, pool=pool, blocks=FIT_THREADS)
        return _fit_problem(prob, lens_pitch_px, min_blur_px, start, (rim, rim_q))


def _fit_problem(
    prob: DefocusProblem,
    lens_pitch_px: float,
    min_blur_px: float,
    start: tuple[float, float, float, float] | None,
    rim: tuple[WhiteRim | None, float] = (None, float("nan")),
) -> DefocusFit:
    """:func:`fit_defocus` of the problem built from its usable observations."""
    obs = prob.obs
    frames = sorted({o.frame for o in obs})
    rows = np.arange(len(obs))
    q_lo, q_hi = float(prob.q.min()), float(prob.q.max())
    q_bounds = _q_bounds(prob.q)
    if start is not None and np.all(np.isfinite(start)):
        theta0 = np.asarray(start, dtype=np.float64)
    else:
        # Q0 where the frames' edge spread is smallest (coarse scan of the projected fit)
        spreads = np.array([o.esf.spread_px() for o in obs])
        start_q = float(prob.q[np.nanargmin(spreads)]) if np.isfinite(spreads).any() else q_lo
        candidates = np.concatenate([np.linspace(q_lo, q_hi, 6), [start_q]])
        costs = [
            float(np.sum(prob.residuals(np.array([c, 1.0, 0.5, 0.0]), rows) ** 2))
            for c in candidates
        ]
        theta0 = np.array([float(candidates[int(np.argmin(costs))]), 1.0, 0.5, 0.0])
    # geometric optics first (from a start with diffraction, its geometric part): whether the
    # edges widen measurably at all (the wave kernel alone could put Q0 anywhere when they do
    # not, its diffraction hiding a defocus within the depth of focus)
    geometric = np.concatenate([theta0[:3], [0.0]])
    optics = robust_fit(prob, geometric, rows, q_bounds, diffraction=False)
    _check_blur(optics[0], prob, lens_pitch_px, min_blur_px)
    rims_kappa = rim_kappa(prob, optics[0], rows, rim, lens_pitch_px)
    excluded = rims_exclude_geometric(optics, rims_kappa)
    wave, wave_q0 = wave_fit(
        prob, optics, rows, q_bounds, start_scale=float(theta0[3]), forced=excluded
    )
    excluded = excluded and wave is not None
    theta, cov, robust, chi2 = wave if wave is not None else optics
    se_curv = float(np.sqrt(max(cov[0, 0], 0.0)))
    se_cluster = float(np.sqrt(max(robust[0, 0], 0.0)))
    q0_systematic = DIAMETER_SYSTEMATIC_PX / (diameter_factor(theta[1], theta[2]) * lens_pitch_px)
    # the blur model not taken, when both were fitted: their disagreement is uncertain too
    other_q0 = float(optics[0][0]) if wave is not None else wave_q0
    q0_kernel = abs(float(theta[0]) - other_q0) if np.isfinite(other_q0) and not excluded else 0.0
    q0_se_model = float(np.hypot(np.hypot(max(se_curv, se_cluster), q0_systematic), q0_kernel))
    a = prob.design(theta, rows)
    s, offset, gain = prob.solve_linear(a, rows)
    weights = np.maximum(s, 0.0)
    # the live plot's quantity: the windowed RMS width of each frame's edge spread, measured
    # and as the model predicts it (the same estimator on the model's function)
    model = offset[:, None] + gain[:, None] * (a @ s) + prob._extra
    centres = -FIT_HALF_PX + (np.arange(prob.w.shape[1]) + 0.5) * ESF_BIN_PX
    measured_spreads: dict[int, list[float]] = {}
    model_spreads: dict[int, list[float]] = {}
    for k, o in enumerate(obs):
        filled = prob.w[k] > 0
        x = centres[filled]
        g_k = gain[k] if gain[k] != 0 else 1.0
        ones, counts = np.ones_like(x), np.ones(x.size, dtype=np.int64)
        data = BinnedEsf(x, (prob.v[k, filled] - offset[k]) / g_k, ones, counts, 0)
        fitted = BinnedEsf(x, (model[k, filled] - offset[k]) / g_k, ones, counts, 0)
        measured_spreads.setdefault(o.frame, []).append(data.spread_px())
        model_spreads.setdefault(o.frame, []).append(fitted.spread_px())
    rms = kernel_rms(weights, prob.grid)
    blur = diameter_factor(theta[1], theta[2]) * lens_pitch_px * np.abs(prob.q - theta[0])
    per_frame: dict[int, float] = {}
    for f, b in zip(prob.frame, blur, strict=True):
        per_frame.setdefault(int(f), float(b))
    result = DefocusFit(
        Q0=float(theta[0]),
        Q0_se=q0_se_model,
        Q0_se_model=q0_se_model,
        Q0_se_curvature=se_curv,
        Q0_se_cluster=se_cluster,
        Q0_se_systematic=q0_systematic,
        Q0_se_kernel=q0_kernel,
        Q0_other_kernel=other_q0,
        rim_kappa=rims_kappa,
        geometric_excluded=excluded,
        corners=obs[0].corner,
        kappa=float(theta[1]),
        shape_box=float(theta[2]),
        diffraction_px=float(theta[3]),
        chi2_reduced=chi2,
        static_kernel_px=np.asarray(prob.grid, dtype=np.float64),
        static_weights=s,
        static_rms_px=rms,
        blur_px=per_frame,
        frames=len(frames),
        max_blur_px=float(blur.max()),
        spread_px={f: float(np.nanmean(v)) for f, v in measured_spreads.items()},
        model_spread_px={f: float(np.nanmean(v)) for f, v in model_spreads.items()},
        frame_noise_scale={
            int(f): float(sc) for f, sc in zip(prob.frame, prob.noise_scale, strict=True)
        },
    )
    _check_blur(theta, prob, lens_pitch_px, min_blur_px)
    return result


def _check_blur(
    theta: NDArray[np.float64], prob: DefocusProblem, lens_pitch_px: float, min_blur_px: float
) -> None:
    """:class:`DefocusNotDetermined` when the geometric fit ``theta`` defocuses no frame by
    more than ``min_blur_px`` pixels."""
    factor = diameter_factor(theta[1], theta[2]) * lens_pitch_px
    max_blur = float(np.max(factor * np.abs(prob.q - theta[0])))
    if max_blur < min_blur_px:
        raise DefocusNotDetermined(
            f"the defocus blur never exceeds {max_blur:.2f} px over the sweep "
            f"(need {min_blur_px:.1f} px): the focus plane cannot be located; extend the "
            "sweep or use a faster main lens"
        )


def _usable(observations: Sequence[EdgeObservation]) -> list[EdgeObservation]:
    """The observations the fit uses (a finite ``Q``, at least 10 bins), one per frame, of
    the same corners throughout the sweep (:func:`sweep_corners`)."""
    return sweep_corners([o for o in observations if np.isfinite(o.Q) and o.esf.x.size >= 10])


def _q_bounds(q: NDArray[np.float64]) -> tuple[float, float]:
    """Bounds of ``Q0``: the sweep's range of ``Q`` widened by itself on each side."""
    q_lo, q_hi = float(q.min()), float(q.max())
    span = q_hi - q_lo
    return q_lo - span, q_hi + span


def jackknife_defocus(
    observations: Sequence[EdgeObservation],
    fit: DefocusFit,
    *,
    lens_pitch_px: float,
    blocks: int = JACKKNIFE_BLOCKS,
) -> DefocusFit:
    """``fit`` with a delete-a-block jackknife of ``Q0`` over contiguous parts of the sweep.

    The observations (the ones ``fit`` was made from) are sorted by ``Q`` (along the rail)
    and cut into ``G = blocks`` contiguous blocks (fewer when the sweep has fewer than
    2·G frames; none below 3, and ``fit`` is returned as it is); each block is left out in
    turn and ``(Q0, κ, α)`` refitted from ``fit``'s values, with each frame's noise scale
    of the full fit. This sees what the model's uncertainty cannot: edges that depart
    from the blur model differently along the sweep (coherent departures, which the
    frame-clustered uncertainty treats as independent and the reduced chi-square hides
    in the noise of thousands of bins), or a cost with several minima that leaving out
    a block moves between.

    Each refit is tested against the full fit: under the model, ``Q0_g - Q0`` has the
    variance ``se_g² - se²`` (the full fit holds the refit's data; at least ``se²/(G-1)``,
    a block of average weight), so ``z_g = (Q0_g - Q0)/√(se_g² - se²)`` is standard
    normal, whatever the leverage of the block (an end of the sweep carries much of the
    information on its arm of the V). When every ``|z_g|`` is within the two-sided
    ``JACKKNIFE_FALSE_ALARM/G`` quantile the sweep is consistent and ``Q0_se`` stays the
    model's; otherwise ``Q0_se`` becomes the larger of the model's (statistical and
    systematic) and the jackknife's standard error ``√((G-1)/G·Σ(Q0_g - mean)²)``.
    ``Q0`` is never changed.
    """
    obs = _usable(observations)
    n_blocks = min(blocks, len(obs) // 2)
    if n_blocks < 3:
        return fit
    q = np.array([o.Q for o in obs])
    bounds = _q_bounds(q)
    start = np.array([fit.Q0, fit.kappa, fit.shape_box, fit.diffraction_px])

    full = DefocusProblem(obs, lens_pitch_px)

    def left_out(block: NDArray[np.int64]) -> tuple[float, float]:
        prob = full.without(block)
        prob.scale_noise(np.array([fit.frame_noise_scale.get(o.frame, 1.0) for o in prob.obs]))
        theta, cov, robust, _ = prob.fit(
            start, np.arange(len(prob.obs)), bounds, diffraction=fit.diffraction_px > 0.0
        )
        return float(theta[0]), float(np.sqrt(max(cov[0, 0], robust[0, 0], 0.0)))

    with ThreadPoolExecutor(JACKKNIFE_THREADS) as pool:
        refits = list(pool.map(left_out, np.array_split(np.argsort(q), n_blocks)))
    q0 = np.array([r[0] for r in refits])
    jackknife = float(np.sqrt((n_blocks - 1) / n_blocks * np.sum((q0 - q0.mean()) ** 2)))
    # each refit against the full fit: under the model their difference has the variance
    # se_g² - se² (the full fit contains the refit's data), at least that of a block of
    # average weight, se²/(G-1)
    se_full = max(fit.Q0_se_curvature, fit.Q0_se_cluster)
    se_left = np.array([r[1] for r in refits])
    floor = se_full**2 / (n_blocks - 1)
    z = (q0 - fit.Q0) / np.sqrt(np.maximum(se_left**2 - se_full**2, floor))
    critical = float(norm.isf(JACKKNIFE_FALSE_ALARM / (2 * n_blocks)))
    consistent = bool(np.all(np.abs(z) <= critical))
    return replace(
        fit,
        Q0_se=fit.Q0_se_model if consistent else max(fit.Q0_se_model, jackknife),
        Q0_se_jackknife=jackknife,
        jackknife_Q0=tuple(q0.tolist()),
        jackknife_z=tuple(z.tolist()),
        jackknife_consistent=consistent,
    )


def jackknife_warning(fit: DefocusFit, lens_pitch_px: float) -> str | None:
    """A warning when the jackknife found the sweep inconsistent with the blur model and
    its uncertainty is more than ``JACKKNIFE_WARN_FACTOR`` times the model's."""
    if fit.jackknife_consistent is not False:
        return None
    if not fit.Q0_se_jackknife > JACKKNIFE_WARN_FACTOR * fit.Q0_se_model:
        return None
    factor = diameter_factor(fit.kappa, fit.shape_box) * lens_pitch_px
    return (
        f"the focus plane's Q0 moves by up to {np.ptp(fit.jackknife_Q0):.2g} "
        f"({factor * np.ptp(fit.jackknife_Q0):.2f} px of defocus diameter) when parts of the "
        f"sweep are left out (jackknife over {len(fit.jackknife_Q0)} blocks: ±"
        f"{fit.Q0_se_jackknife:.2g} against the blur model's ±{fit.Q0_se_model:.2g}): the "
        "edges depart from the blur model differently along the sweep, and the focus "
        "plane's uncertainty is the jackknife's"
    )


def blur_model_warning(fit: DefocusFit) -> str | None:
    """A warning when the two blur models disagree on ``Q0`` by more than its statistical
    uncertainty (``Q0_se_kernel`` above the curvature's and the clusters'): the sweep stays
    where the edges barely widen, and which physics forms them decides the focus plane."""
    statistical = max(fit.Q0_se_curvature, fit.Q0_se_cluster)
    if not fit.Q0_se_kernel > statistical:
        return None
    models = ("wave-optical", "geometric")
    taken, other = models if fit.diffraction_px > 0.0 else models[::-1]
    return (
        f"the {taken} blur model (taken) and the {other} one put the focus plane's Q0 at "
        f"{fit.Q0:.5f} and {fit.Q0_other_kernel:.5f}, {fit.Q0_se_kernel:.1g} apart against "
        f"±{statistical:.1g} from the data: the edges widen too little over the sweep to tell "
        "the microlenses' diffraction from their defocus, and the focus plane's uncertainty "
        "includes the difference; a sweep reaching farther from the focus plane decides it"
    )
