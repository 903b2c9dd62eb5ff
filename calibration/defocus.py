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

Each frame contributes its binned, normalised edge-spread function
(:mod:`calibration.edge_spread`; both corners' functions centred on their own
edges and merged, :func:`pool_corners`), with a free offset and gain (tails of
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
one and the fit repeated (``ROBUST_ROUNDS``): a frame the model describes
worse than its noise (a sharp, point-sampled edge whose placement the lattice
resolves only to a fraction of the sample spacing; a defect) weighs less. The
uncertainty of ``Q0`` comes from the curvature of that fit, scaled by its
reduced chi-square, and from a cluster-robust (sandwich) estimate with the
frames as clusters (the samples of one frame share its normalisation): the
larger, with a systematic term (``DIAMETER_SYSTEMATIC_PX``) in quadrature.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, nnls

from .edge_spread import ESF_BIN_PX, BinnedEsf

STATIC_STEP_PX = 0.05
"""Spacing of the static kernel's point masses (pixels)."""

FIT_HALF_PX = 4.5
"""Only bins within this distance of the edge are fitted (pixels)."""

STATIC_HALF_PX = FIT_HALF_PX + 1.5
"""Half width of the static kernel (pixels); mass beyond it goes into the offsets. It
reaches past the fitted window: a diffraction-limited microlens (a square aperture at
f/12.5 in green light has its first zero at λN = 2.75 px of 2.5 µm) spreads light into
lobes and 1/x² tails that cross the whole window, and a kernel cut at 3 px left them to
the per-frame offset and gain, which cannot take their shape: on exact functions Q0 came
out 0.67 % low, on a Monte-Carlo sweep with that diffraction 12 % off with κ = 0.5
(tests/test_defocus.py); with the kernel 1.5 px past the window it is exact again."""

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
write."""

MODEL_FLOOR = 5e-4
"""Added in quadrature to every bin's standard error (fraction of the edge contrast): the
model's limit (thin lenses, a uniform aperture); keeps a few noiseless bins from ruling."""

SMOOTHNESS = 1e-7
"""Weight of the second-difference penalty on the static kernel (relative to the data)."""

ROBUST_ROUNDS = 2
"""Rounds of re-weighting each observation by its own reduced chi-square (see
:meth:`_Problem.downweight`)."""

KAPPA_MAX = 1.0
"""Upper bound of the aperture's RMS scale ``κ``: the square cell of side ``D`` (see above)."""


@dataclass(frozen=True)
class EdgeObservation:
    """One corner in one frame: its measured ``Q`` and edge-spread function."""

    frame: int
    corner: str
    Q: float
    esf: BinnedEsf


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
    chi2_reduced: float
    static_kernel_px: NDArray[np.float64]
    static_weights: NDArray[np.float64]
    static_rms_px: float
    blur_px: dict[int, float] = field(default_factory=dict)
    frames: int = 0
    max_blur_px: float = float("nan")
    spread_px: dict[int, float] = field(default_factory=dict)
    model_spread_px: dict[int, float] = field(default_factory=dict)

    def blur_diameter_px(
        self, Q: float | NDArray[np.float64], lens_pitch_px: float
    ) -> NDArray[np.float64]:
        """Model defocus diameter ``κ' (D/δ) |Q - Q0|`` (pixels) of the fitted aperture shape."""
        factor = _diameter(self.kappa, self.shape_box)
        return factor * lens_pitch_px * np.abs(np.asarray(Q, dtype=np.float64) - self.Q0)


class DefocusNotDetermined(ValueError):
    """The blur does not change enough over the sweep to locate the focus plane."""


def _box_integral(t: NDArray[np.floating], d: NDArray[np.floating]) -> NDArray[np.float64]:
    """``∫_{-∞}^{t} C(τ) dτ`` of the cumulative line-spread ``C`` of a box of width ``d``."""
    dd = np.maximum(d, 1e-9)
    inside = np.clip(t + 0.5 * dd, 0.0, dd)
    return np.where(t > 0.5 * dd, t, inside * inside / (2.0 * dd))


def _disk_integral(t: NDArray[np.floating], d: NDArray[np.floating]) -> NDArray[np.float64]:
    """``∫_{-∞}^{t} C(τ) dτ`` of the cumulative line-spread of a uniform disk of diameter ``d``.

    With ``u = 2t/d``: ``C = ½ + (u√(1-u²) + asin u)/π`` and its integral is
    ``(d/2)·[u/2 + (u·asin u + √(1-u²))/π - (1-u²)^{3/2}/(3π)]``: 0 below the
    disk, ``t`` above it; the special functions are evaluated only inside.
    """
    t, dd = np.broadcast_arrays(t, np.maximum(d, 1e-9))
    out = np.where(t >= 0.5 * dd, t, 0.0).astype(np.float64)
    inside = np.abs(t) < 0.5 * dd
    u = 2.0 * t[inside] / dd[inside]
    root = np.sqrt(1.0 - u * u)
    j = 0.5 * u + (u * np.arcsin(u) + root) / np.pi - root**3 / (3.0 * np.pi)
    out[inside] = 0.5 * dd[inside] * j
    return out


def _aperture_integral(
    t: NDArray[np.floating], d: NDArray[np.floating], alpha: float
) -> NDArray[np.float64]:
    """``∫C`` of the aperture's line spread at diameter ``d``: box (``α``) and disk mixture."""
    out = alpha * _box_integral(t, d) if alpha > 0.0 else np.zeros(np.broadcast(t, d).shape)
    if alpha < 1.0:
        out = out + (1.0 - alpha) * _disk_integral(t, d)
    return np.asarray(out, dtype=np.float64)


def _nonnegative_solve(lhs: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
    """``argmin sᵀ·lhs·s - 2 rhsᵀ·s`` over ``s >= 0`` (NNLS on the Cholesky factor)."""
    try:
        upper = np.linalg.cholesky(lhs).T
    except np.linalg.LinAlgError:
        upper = np.linalg.cholesky(lhs + 1e-9 * np.trace(lhs) * np.eye(lhs.shape[0])).T
    target = np.linalg.solve(upper.T, rhs)
    s, _ = nnls(upper, target, maxiter=50 * lhs.shape[0])
    return s


JITTER_NEGLIGIBLE_PX = 0.01
"""Placement jitter (px) below which an observation's model is not averaged over it (its
variance, 1e-4 px², is far below what the defocus fit resolves)."""

_HERMITE_NODES, _HERMITE_WEIGHTS = np.polynomial.hermite_e.hermegauss(5)
_JITTER_NODES = (_HERMITE_NODES, _HERMITE_WEIGHTS / np.sum(_HERMITE_WEIGHTS))
"""Gauss-Hermite nodes and weights of the standard normal: the average over the placement
jitter of an observation (:attr:`BinnedEsf.jitter_px`)."""


def _diameter(kappa: float, alpha: float) -> float:
    """Aperture diameter factor for RMS scale ``κ`` and shape ``α``.

    ``κ`` scales the kernel's RMS width to that of a box of diameter ``κ·d``
    whatever the shape, so ``κ`` and ``α`` are nearly uncorrelated: a box of
    width ``d`` has variance ``d²/12``, a uniform disk's projection ``d²/16``.
    """
    return kappa * float(np.sqrt((1.0 / 12.0) / (alpha / 12.0 + (1.0 - alpha) / 16.0)))


class _Problem:
    """The stacked data of every observation and the linear sub-problems.

    The static kernel is a set of point masses at ``g_i = i·STATIC_STEP_PX``
    (mirrored: it is symmetric). Each bin of the data is the mean of samples
    spread about its mean position ``x̄`` with standard deviation ``σ``; the
    model of a bin is the function averaged over the uniform interval of the
    same mean and spread, ``x̄ ± w`` with ``w = √3·σ`` (a point value when the
    profiles share one sub-pixel phase, the bin average when their phases
    cover it). For the mass at ``±g`` that is ``[IC(x̄+w∓g) - IC(x̄-w∓g)]/(2w)``
    with ``IC`` the integral of the defocus kernel's cumulative line spread,
    tabulated per observation on a fine lattice and interpolated.
    """

    LATTICE_PX = 0.005

    def __init__(self, obs: Sequence[EdgeObservation], lens_pitch_px: float) -> None:
        self.obs = list(obs)
        self.pitch = lens_pitch_px
        h = STATIC_STEP_PX
        n_bins = int(round(2 * FIT_HALF_PX / ESF_BIN_PX))
        n_cells = int(round(STATIC_HALF_PX / h)) + 1
        self.grid = np.arange(n_cells) * h
        n = len(self.obs)
        self.v = np.zeros((n, n_bins))
        self.w = np.zeros((n, n_bins))  # sqrt of the weights; 0 where a bin is empty
        xbar = np.tile(-FIT_HALF_PX + (np.arange(n_bins) + 0.5) * ESF_BIN_PX, (n, 1))
        half = np.full((n, n_bins), 0.5 * ESF_BIN_PX)
        for k, o in enumerate(self.obs):
            b = np.floor((o.esf.x + FIT_HALF_PX) / ESF_BIN_PX).astype(np.int64)
            inside = (b >= 0) & (b < n_bins)
            bi = b[inside]
            self.v[k, bi] = o.esf.value[inside]
            se = np.hypot(o.esf.se[inside], MODEL_FLOOR)
            self.w[k, bi] = 1.0 / se
            xbar[k, bi] = o.esf.x[inside]
            half[k, bi] = np.sqrt(3.0) * o.esf.position_sd_px[inside]
        half = np.maximum(half, 2 * self.LATTICE_PX)
        self.w_data = self.w.copy()
        self.xbar = xbar
        self._extra = np.zeros_like(xbar)
        self.q = np.array([o.Q for o in self.obs])
        self.jitter = np.array([o.esf.jitter_px for o in self.obs])
        self.frame = np.array([o.frame for o in self.obs])
        # the four interval ends of every (observation, bin, mass), as fine-lattice positions
        g = self.grid[None, None, :]
        xb, wb = xbar[:, :, None], half[:, :, None]
        self.start = -FIT_HALF_PX - STATIC_HALF_PX - 1.0
        ends = (xb + wb - g, xb - wb - g, xb + wb + g, xb - wb + g)
        self.n_lattice = (
            int(np.ceil(2 * (FIT_HALF_PX + STATIC_HALF_PX + 1.0) / self.LATTICE_PX)) + 2
        )
        row_start = (np.arange(n) * self.n_lattice)[:, None, None]
        self.index, self.frac = [], []
        for e in ends:
            t = (e - self.start) / self.LATTICE_PX
            j = np.floor(t)
            self.index.append((row_start + j).astype(np.int32).ravel())
            self.frac.append((t - j).ravel().astype(np.float32))
        self.shape = (n, n_bins, n_cells)
        self.lattice = self.start + np.arange(self.n_lattice) * self.LATTICE_PX
        self.norm = (4.0 * half)[:, :, None].astype(np.float32)  # 2w (bin average) x 2 (mirror)
        second = np.zeros((n_cells - 2, n_cells))
        for r in range(n_cells - 2):
            second[r, r : r + 3] = (1.0, -2.0, 1.0)
        self.penalty = second.T @ second
        self.data_scale = float(np.mean(np.sum(self.w**2, axis=1)))

    def design(self, theta: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.float64]:
        """``A[k, b, i]``: bin ``b`` of observation ``k`` for a unit static mass at ``±g_i``."""
        q0, kappa, alpha = theta
        d = _diameter(kappa, alpha) * self.pitch * np.abs(self.q[rows] - q0)
        t = self.lattice[None, :]
        integral = _aperture_integral(t, d[:, None], alpha)
        # the placement jitter of an observation: a Gauss-Hermite average over it (only where
        # it is not negligible against the lattice)
        jittered = np.flatnonzero(self.jitter > JITTER_NEGLIGIBLE_PX)
        if jittered.size:
            dj = d[jittered, None]
            smooth = np.zeros((jittered.size, self.lattice.size))
            for node, weight in zip(*_JITTER_NODES, strict=True):
                smooth += weight * _aperture_integral(
                    t + node * self.jitter[jittered, None], dj, alpha
                )
            integral[jittered] = smooth
        if rows.size != self.shape[0]:
            raise ValueError("the design is built for every observation at once")
        flat = integral.ravel().astype(np.float32)
        out = np.zeros(self.index[0].size, dtype=np.float32)
        for sign, j, f in zip((1.0, -1.0, 1.0, -1.0), self.index, self.frac, strict=True):
            lo = flat.take(j)
            hi = flat.take(j + 1)
            hi -= lo
            hi *= f
            hi += lo
            if sign > 0:
                out += hi
            else:
                out -= hi
        return (out.reshape(self.shape) / self.norm).astype(np.float64)

    def solve_linear(
        self, a: NDArray[np.float64], rows: NDArray[np.int64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Static weights ``s`` and, per observation, offset, gain and shift.

        Alternating (3 rounds): ``s`` by non-negative least squares given the
        rest, then per observation a small weighted least squares for its
        offset, gain and the coefficient of ``E'(x)``: a shift of the whole
        function (its samples are placed by the corner lattice, whose common
        error moves them all alike, :mod:`calibration.edge_profiles`). Returns
        ``s``, ``offset`` and ``gain``; the shift's part of the model is kept in
        ``_extra``.
        """
        w2 = self.w[rows] ** 2
        v = self.v[rows]
        aw = a * w2[:, :, None]
        gram = np.matmul(a.transpose(0, 2, 1), aw)
        atv = np.einsum("kbi,kb->ki", aw, v)
        n_obs = rows.size
        lam = SMOOTHNESS * self.data_scale * n_obs
        coef = np.zeros((n_obs, 3))
        coef[:, 1] = 1.0
        extra = np.zeros_like(v)  # the shift's contribution to the model
        s = np.zeros(self.grid.size)
        x = self.xbar[rows]
        for _ in range(3):
            offset, gain = coef[:, 0], coef[:, 1]
            # s given the per-observation terms: normal equations and a sum-to-one row
            lhs = np.einsum("k,kij->ij", gain * gain, gram) + lam * self.penalty
            resid = offset[:, None] + extra
            rhs = (gain[:, None] * (atv - np.einsum("kbi,kb->ki", aw, resid))).sum(axis=0)
            big = 1e3 * float(np.trace(lhs)) / lhs.shape[0]
            s = _nonnegative_solve(lhs + big, rhs + big)
            # per observation: offset, gain and shift by weighted least squares
            e = a @ s
            columns = [np.ones_like(e), e, np.gradient(e, axis=1) / np.gradient(x, axis=1)]
            design = np.stack(columns, axis=2)  # (n_obs, n_bins, n_coef)
            dw = design * w2[:, :, None]
            normal = np.matmul(design.transpose(0, 2, 1), dw)
            normal += (
                1e-12
                * np.eye(normal.shape[1])[None]
                * np.trace(normal, axis1=1, axis2=2)[:, None, None]
            )
            coef = np.linalg.solve(normal, np.einsum("kbc,kb->kc", dw, v)[:, :, None])[:, :, 0]
            extra = np.einsum("kbc,kc->kb", design[:, :, 2:], coef[:, 2:])
        self._extra = extra
        return s, coef[:, 0], coef[:, 1]

    def downweight(self, theta: NDArray[np.float64], rows: NDArray[np.int64]) -> None:
        """Each observation's errors scaled by its own reduced chi-square at ``theta`` (when
        above one): a frame the model describes worse than its noise (placement it cannot
        resolve, a sharp point-sampled edge, a defect) weighs accordingly less."""
        self.w = self.w_data.copy()
        z = self.residuals(theta, rows).reshape(self.w.shape)
        filled = np.maximum(np.count_nonzero(self.w, axis=1), 1)
        chi2 = np.sum(z * z, axis=1) / filled
        self.w = self.w_data / np.sqrt(np.maximum(chi2, 1.0))[:, None]

    def residuals(self, theta: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.float64]:
        a = self.design(theta, rows)
        s, offset, gain = self.solve_linear(a, rows)
        model = offset[:, None] + gain[:, None] * (a @ s) + self._extra
        return ((self.v[rows] - model) * self.w[rows]).ravel()

    def fit(
        self,
        theta0: NDArray[np.float64],
        rows: NDArray[np.int64],
        q_bounds: tuple[float, float],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float]:
        """Least squares over ``(Q0, κ, α)``.

        Returns ``theta``, its covariance from the curvature (scaled by the
        reduced chi² when above 1), its cluster-robust (sandwich) covariance
        with the frames as clusters, and the reduced chi².
        """
        lower = [q_bounds[0], 0.2, 0.0]
        upper = [q_bounds[1], KAPPA_MAX, 1.0]
        fit = least_squares(
            lambda t: self.residuals(t, rows),
            np.clip(theta0, np.array(lower) + 1e-9, np.array(upper) - 1e-9),
            bounds=(lower, upper),
            x_scale=[1e-4, 0.05, 0.1],
            diff_step=[1e-6, 1e-4, 1e-3],
            ftol=1e-6,
            xtol=1e-6,
        )
        self.nfev = fit.nfev
        n_params = 3 + self.grid.size + 2 * rows.size
        dof = max(1, int(np.count_nonzero(self.w[rows])) - n_params)
        chi2 = float(np.sum(fit.fun**2) / dof)
        jac = fit.jac
        try:
            bread = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            inf = np.full((3, 3), np.inf)
            return fit.x, inf, inf, chi2
        cov = bread * max(chi2, 1.0)
        # sandwich: the residuals of one frame share its normalisation and noise
        n_bins = self.w.shape[1]
        score = (jac * fit.fun[:, None]).reshape(rows.size, n_bins, 3).sum(axis=1)
        frames = self.frame[rows]
        clusters = np.unique(frames)
        per = np.zeros((clusters.size, 3))
        np.add.at(per, np.searchsorted(clusters, frames), score)
        g = clusters.size
        meat = per.T @ per * (g / max(g - 1, 1))
        robust = bread @ meat @ bread
        return fit.x, cov, robust, chi2


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
    start: tuple[float, float, float] | None = None,
) -> DefocusFit:
    """Fit ``Q0`` (and the static kernel) to the edge-spread functions of a sweep.

    ``lens_pitch_px`` is ``D/δ``; ``start`` an earlier fit's ``(Q0, κ, α)`` to start
    from instead of the coarse scan (a refit on a refined ``Q(u)``). Raises
    :class:`DefocusNotDetermined` when fewer than 5 frames have edge-spread functions, or when the model's
    defocus never exceeds ``min_blur_px`` pixels anywhere in the sweep (the
    blur does not change measurably: the focus plane cannot be located).
    """
    obs = pool_corners([o for o in observations if np.isfinite(o.Q) and o.esf.x.size >= 10])
    frames = sorted({o.frame for o in obs})
    if len(frames) < 5:
        raise DefocusNotDetermined(
            f"edge-spread functions in only {len(frames)} frames (need 5): the focus plane "
            "cannot be located"
        )
    prob = _Problem(obs, lens_pitch_px)
    rows = np.arange(len(obs))
    q_lo, q_hi = float(prob.q.min()), float(prob.q.max())
    span = q_hi - q_lo
    q_bounds = (q_lo - span, q_hi + span)
    if start is not None and np.all(np.isfinite(start)):
        theta0 = np.asarray(start, dtype=np.float64)
    else:
        # Q0 where the frames' edge spread is smallest (coarse scan of the projected fit)
        spreads = np.array([o.esf.spread_px() for o in obs])
        start_q = float(prob.q[np.nanargmin(spreads)]) if np.isfinite(spreads).any() else q_lo
        candidates = np.concatenate([np.linspace(q_lo, q_hi, 6), [start_q]])
        costs = [
            float(np.sum(prob.residuals(np.array([c, 1.0, 0.5]), rows) ** 2)) for c in candidates
        ]
        theta0 = np.array([float(candidates[int(np.argmin(costs))]), 1.0, 0.5])
    theta, cov, robust, chi2 = prob.fit(theta0, rows, q_bounds)
    for _ in range(ROBUST_ROUNDS):
        prob.downweight(theta, rows)
        theta, cov, robust, chi2 = prob.fit(theta, rows, q_bounds)
    se_curv = float(np.sqrt(max(cov[0, 0], 0.0)))
    se_cluster = float(np.sqrt(max(robust[0, 0], 0.0)))
    q0_systematic = DIAMETER_SYSTEMATIC_PX / (_diameter(theta[1], theta[2]) * lens_pitch_px)
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
    rms = float(np.sqrt(np.sum(weights * prob.grid**2) / max(np.sum(weights), 1e-12)))
    blur = _diameter(theta[1], theta[2]) * lens_pitch_px * np.abs(prob.q - theta[0])
    per_frame: dict[int, float] = {}
    for f, b in zip(prob.frame, blur, strict=True):
        per_frame.setdefault(int(f), float(b))
    result = DefocusFit(
        Q0=float(theta[0]),
        Q0_se=float(np.hypot(max(se_curv, se_cluster), q0_systematic)),
        Q0_se_curvature=se_curv,
        Q0_se_cluster=se_cluster,
        Q0_se_systematic=q0_systematic,
        kappa=float(theta[1]),
        shape_box=float(theta[2]),
        chi2_reduced=chi2,
        static_kernel_px=np.asarray(prob.grid, dtype=np.float64),
        static_weights=s,
        static_rms_px=rms,
        blur_px=per_frame,
        frames=len(frames),
        max_blur_px=float(blur.max()),
        spread_px={f: float(np.nanmean(v)) for f, v in measured_spreads.items()},
        model_spread_px={f: float(np.nanmean(v)) for f, v in model_spreads.items()},
    )
    if result.max_blur_px < min_blur_px:
        raise DefocusNotDetermined(
            f"the defocus blur never exceeds {result.max_blur_px:.2f} px over the sweep "
            f"(need {min_blur_px:.1f} px): the focus plane cannot be located; extend the "
            "sweep or use a faster main lens"
        )
    return result


def pool_corners(observations: Sequence[EdgeObservation]) -> list[EdgeObservation]:
    """One observation per frame: its corners' functions, each centred on its own edge, merged.

    The corners of a frame see the same defocus (their Q agree to ~1e-4, which
    the result checks) and share the static kernel, but each corner's function
    is placed by its own lattice, so their origins may differ by a fraction of
    the placement error: each is centred on the centroid of its line spread
    before merging (a symmetric blur's centroid is the edge). ``Q`` is the
    profile-weighted mean of the corners'.
    """
    by_frame: dict[int, list[EdgeObservation]] = {}
    for o in observations:
        by_frame.setdefault(o.frame, []).append(o)
    pooled = []
    for frame, parts in sorted(by_frame.items()):
        if len(parts) == 1:
            pooled.append(parts[0])
            continue
        centres = [p.esf.centre_px() for p in parts]
        esfs = [
            p.esf.shifted(-c) if np.isfinite(c) else p.esf
            for p, c in zip(parts, centres, strict=True)
        ]
        weights = np.array([p.esf.profiles for p in parts], dtype=np.float64)
        q = float(np.sum(weights * np.array([p.Q for p in parts])) / np.sum(weights))
        pooled.append(EdgeObservation(frame, "both", q, BinnedEsf.merge(esfs)))
    return pooled
