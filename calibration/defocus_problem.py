"""The numerical core of the whole-sweep defocus fit: the data and the linear sub-problems.

:mod:`calibration.defocus` fits the focus plane with it (see there for the model).
Here are the stacked edge-spread data of every observation and
:class:`DefocusProblem`: for given ``(Q0, κ, α, s)`` the design
(:class:`calibration.defocus_design.DefocusDesign`), the static kernel and each
observation's offset, gain and shift by (non-negative, regularised) least squares, the
weighted residuals, the re-weighting by each observation's reduced chi-square and the
nonlinear least squares over ``(Q0, κ, α, s)`` with its curvature and cluster-robust
covariances. Positions in pixels along the edge normal, ``Q`` dimensionless.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares, nnls

from .cluster_robust import clustered_meat
from .defocus_design import FIT_HALF_PX, DefocusDesign
from .edge_spread import ESF_BIN_PX, BinnedEsf
from .wave_defocus import DIFFRACTION_MAX_PX

Fit = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float]
"""What :meth:`DefocusProblem.fit` returns: ``theta``, its curvature and cluster-robust
covariances and the reduced chi-square."""

MODEL_FLOOR = 5e-4
"""Added in quadrature to every bin's standard error (fraction of the edge contrast): the
model's limit (thin lenses, a uniform aperture); keeps a few noiseless bins from ruling."""

SMOOTHNESS = 1e-7
"""Weight of the second-difference penalty on the static kernel (relative to the data)."""

KAPPA_MAX = 1.0
"""Upper bound of the aperture's RMS scale ``κ``: the square cell of side ``D``
(:mod:`calibration.defocus`)."""


@dataclass(frozen=True)
class EdgeObservation:
    """One corner in one frame: its measured ``Q`` and edge-spread function."""

    frame: int
    corner: str
    Q: float
    esf: BinnedEsf


def _nonnegative_solve(lhs: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
    """``argmin sᵀ·lhs·s - 2 rhsᵀ·s`` over ``s >= 0`` (NNLS on the Cholesky factor)."""
    try:
        upper = np.linalg.cholesky(lhs).T
    except np.linalg.LinAlgError:
        upper = np.linalg.cholesky(lhs + 1e-9 * np.trace(lhs) * np.eye(lhs.shape[0])).T
    target = np.linalg.solve(upper.T, rhs)
    s, _ = nnls(upper, target, maxiter=50 * lhs.shape[0])
    return s


class DefocusProblem:
    """The stacked data of every observation, its design and the linear sub-problems."""

    def __init__(
        self,
        obs: Sequence[EdgeObservation],
        lens_pitch_px: float,
        *,
        pool: Executor | None = None,
        blocks: int = 1,
    ) -> None:
        """``pool`` and ``blocks``: each evaluation's per-observation work (the design's,
        :class:`DefocusDesign`, and the normal equations) is cut into ``blocks``
        contiguous runs of observations, run on ``pool``; the result is the same as in one
        block."""
        self.obs = list(obs)
        n_bins = int(round(2 * FIT_HALF_PX / ESF_BIN_PX))
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
        self.w_data = self.w.copy()
        self.noise_scale = np.ones(n)  # each observation's errors are scaled by this
        self.xbar = xbar
        self._extra = np.zeros_like(xbar)
        self.frame = np.array([o.frame for o in self.obs])
        q = np.array([o.Q for o in self.obs])
        jitter = np.array([o.esf.jitter_px for o in self.obs])
        self.builder = DefocusDesign(q, jitter, xbar, half, lens_pitch_px, pool=pool, blocks=blocks)
        self.grid = self.builder.grid
        n_cells = self.grid.size
        second = np.zeros((n_cells - 2, n_cells))
        for r in range(n_cells - 2):
            second[r, r : r + 3] = (1.0, -2.0, 1.0)
        self.penalty = second.T @ second
        self.data_scale = float(np.mean(np.sum(self.w**2, axis=1)))

    @property
    def q(self) -> NDArray[np.float64]:
        """Each observation's measured ``Q`` (the design's)."""
        return self.builder.q

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(observations, bins, static nodes)``: the design's shape."""
        return self.builder.shape

    @property
    def blocks(self) -> list[slice]:
        """The contiguous runs of observations an evaluation is cut into."""
        return self.builder.blocks

    def design(self, theta: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.float64]:
        """``A[k, b, i]`` at ``theta = (Q0, κ, α, s)`` (:meth:`DefocusDesign.design`)."""
        return self.builder.design(theta, rows)

    def without(self, dropped: NDArray[np.int64]) -> DefocusProblem:
        """The same problem with the observations at ``dropped`` left out (their data, noise
        scales and lattice rows), in one block, as if built from the others (a jackknife's
        refit)."""
        keep = np.setdiff1d(np.arange(len(self.obs)), dropped)
        sub = copy.copy(self)
        sub.obs = [self.obs[k] for k in keep]
        for name in ("v", "w", "w_data", "noise_scale", "xbar", "frame"):
            setattr(sub, name, getattr(self, name)[keep])
        sub._extra = np.zeros_like(sub.xbar)
        sub.builder = self.builder.subset(keep)
        sub.data_scale = float(np.mean(np.sum(sub.w_data**2, axis=1)))
        return sub

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
        w = self.w[rows]
        w2 = w * w
        v = self.v[rows]
        n_obs, n_bins, n_cells = a.shape
        aw = np.empty_like(a)  # the design weighted by the errors' inverse
        gram = np.empty((n_obs, n_cells, n_cells))

        def normal_equations(block: int) -> None:
            b = self.blocks[block]
            np.multiply(a[b], w[b, :, None], out=aw[b])
            # (A·w)ᵀ(A·w), one operand transposed: numpy takes BLAS's symmetric product
            np.matmul(aw[b].transpose(0, 2, 1), aw[b], out=gram[b])

        self.builder.map_blocks(normal_equations)
        lam = SMOOTHNESS * self.data_scale * n_obs
        coef = np.zeros((n_obs, 3))
        coef[:, 1] = 1.0
        extra = np.zeros_like(v)  # the shift's contribution to the model
        s = np.zeros(self.grid.size)
        x = self.xbar[rows]
        for _ in range(3):
            offset, gain = coef[:, 0], coef[:, 1]
            # s given the per-observation terms: normal equations and a sum-to-one row
            lhs = (gain * gain) @ gram.reshape(n_obs, -1)
            lhs = lhs.reshape(n_cells, n_cells) + lam * self.penalty
            target = gain[:, None] * (v - offset[:, None] - extra) * w
            rhs = target.ravel() @ aw.reshape(-1, n_cells)
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
        self.scale_noise(np.ones(self.w.shape[0]))
        z = self.residuals(theta, rows).reshape(self.w.shape)
        filled = np.maximum(np.count_nonzero(self.w, axis=1), 1)
        chi2 = np.sum(z * z, axis=1) / filled
        self.scale_noise(np.sqrt(np.maximum(chi2, 1.0)))

    def scale_noise(self, scale: NDArray[np.float64]) -> None:
        """Each observation's standard errors multiplied by ``scale`` (one per observation)."""
        self.noise_scale = np.asarray(scale, dtype=np.float64)
        self.w = self.w_data / self.noise_scale[:, None]

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
        *,
        diffraction: bool = True,
    ) -> Fit:
        """Least squares over ``(Q0, κ, α, s)`` (``diffraction`` False: ``s`` held at 0,
        geometric optics).

        Returns ``theta``, its covariance from the curvature (scaled by the
        reduced chi² when above 1), its cluster-robust (sandwich) covariance
        with the frames as clusters, and the reduced chi².
        """
        n_fit = 4 if diffraction else 3
        lower = np.array([q_bounds[0], 0.2, 0.0, 0.0])[:n_fit]
        upper = np.array([q_bounds[1], KAPPA_MAX, 1.0, DIFFRACTION_MAX_PX])[:n_fit]
        held = np.zeros(4 - n_fit)

        def residuals(t: NDArray[np.float64]) -> NDArray[np.float64]:
            return self.residuals(np.concatenate([t, held]), rows)

        fit = least_squares(
            residuals,
            np.clip(np.asarray(theta0, dtype=np.float64)[:n_fit], lower + 1e-9, upper - 1e-9),
            bounds=(lower, upper),
            x_scale=[1e-4, 0.05, 0.1, 0.2][:n_fit],
            diff_step=[1e-6, 1e-4, 1e-3, 1e-3][:n_fit],
            ftol=1e-6,
            xtol=1e-6,
        )
        fit.x = np.concatenate([fit.x, held])
        self.nfev = fit.nfev
        n_params = n_fit + self.grid.size + 2 * rows.size
        dof = max(1, int(np.count_nonzero(self.w[rows])) - n_params)
        chi2 = float(np.sum(fit.fun**2) / dof)
        # a shape or scale parameter held at its bound (a round aperture's α = 0, a full
        # square's κ = 1) is fixed there: its Jacobian column is not a derivative (zero on
        # the bound) and it takes no part in the covariance; Q0 always does
        fitted_free = np.asarray(fit.active_mask) == 0
        fitted_free[0] = True
        jac = fit.jac[:, fitted_free]
        free = np.concatenate([fitted_free, np.zeros(4 - n_fit, dtype=bool)])
        n_theta = fit.x.size
        try:
            bread_free = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            inf = np.full((n_theta, n_theta), np.inf)
            return fit.x, inf, inf, chi2
        # sandwich: the residuals of one frame share its normalisation and noise
        n_bins = self.w.shape[1]
        score = (jac * fit.fun[:, None]).reshape(rows.size, n_bins, jac.shape[1]).sum(axis=1)
        frames = self.frame[rows]
        meat = clustered_meat(score, np.unique(frames, return_inverse=True)[1], parameters_lost=1)
        bread, robust = np.zeros((n_theta, n_theta)), np.zeros((n_theta, n_theta))
        bread[np.ix_(free, free)] = bread_free
        robust[np.ix_(free, free)] = bread_free @ meat @ bread_free
        return fit.x, bread * max(chi2, 1.0), robust, chi2
