"""The camera calibrated from the sweep itself: F, the rail zero, L, b, Q0, hence a, f and the focus plane.

Thin-lens model of OPTICS.md §1 and §4. At rail position ``x`` (mm) the board
is at ``u = u_rail0 + direction·x``; the main lens images it at ``v = uF/(u-F)``
with magnification ``M = v/u``, the main image lies ``a = L - v`` in front of
the MLA, and the disparity measures ``Q = b/a``. So over the sweep

    1/M(x) = (u(x) - F)/F           (linear in x: slope direction/F, intercept (u_rail0 - F)/F)
    1/Q(x) = (L - v(u(x)))/b         (linear in v)

``M`` comes from the main-image positions of the standard corner (0, 0) and
the reference corner (2s, 0), which are ``2s`` apart on the board; ``Q`` from
the disparity of either. The focus plane is where ``Q = Q0``, the value the
whole-sweep defocus model measures (:mod:`calibration.defocus`); there
``a = a_f = b/Q0`` and the microlens focal length is ``f = a_f·b/(a_f + b) =
b/(1 + Q0)``.

A third observation ties ``b`` to ``L`` without the sweep's slope: the
micro-image centres are the projections of the main-lens centre through the
lens centres, so the white image's micro-image pitch over the lens pitch ``D/δ``
is ``(L+b)/L`` (OPTICS.md §1; :attr:`MlaGrid.scale`). The lattice fit reads it
slightly low: the shading that biases the disparity also pulls the shaded rims
of the discs toward the lens centres, and the measured scale is
``1 + β·(1 + (β - Q0)·η_s)`` with ``η_s`` the shading's ``η`` (about -1.5e-5;
:mod:`calibration.mla_grid`); the model includes that, with the shading's
uncertainty and a residual of :data:`IMAGE_SCALE_RESIDUAL`. With
it, ``b`` follows from each frame's ``Q`` and ``v`` (``1/Q = (1/β) - v/b``, ``β = b/L``)
instead of from the change of ``1/Q`` over the ~2 mm that ``v`` moves in a sweep.
That change is not the camera's alone: the disparity reads ``Q·(1 + η·(Q - Q0))``,
a bias that grows with defocus, and ``η`` depends on how the image is formed
(the angular shading of :mod:`calibration.shading` predicts part of it; the
corner fits' response to a blur that is not point-symmetric adds more, of
either sign: measured ``η`` from -1.3e-2 to +6e-3 on three renderers whose shading
predicts +1.6e-3 to +2e-3). An error of 1e-2 in ``η`` tilts ``b`` from the slope by
about ``η·Q0``, several tenths of a percent. So when the pitch is used, ``η`` is
a free parameter, measured by the tilt of ``1/Q(v)`` and reported beside the
shading's prediction; without it ``η`` is the shading's prediction with an
uncertainty of at least :data:`DISPARITY_BIAS_SE`, which ``b`` then carries. The
pitch enters only when it agrees with the sweep's own ``b/L`` (with that
uncertainty) within :data:`IMAGE_SCALE_Z_MAX` combined sigmas; a real thick
lens whose exit pupil (which centres the micro-images) is far from its
principal plane fails that test, and ``b`` and ``L`` then come from the sweep
alone (the result says so).

One weighted least-squares fit over every frame estimates ``(F, u_rail0, L, b,
Q0)``. Only ``D``, ``δ``, the board's ``s`` and ``Cr`` and the rail's steps are
taken as exact. The data-sheet values ``F``, ``f`` and ``u_rail0`` (with their
tolerances, read as 1-sigma) enter only where the sweep cannot fix the
quantity: a prior is used when the sweep alone would determine it to no
better than a third of its tolerance (for example ``F`` and ``u_rail0`` when the
reference corner is never in view, which leaves only the weak curvature of
``1/Q(x)``), and the result says which ones were.

Uncertainties come from the fit's covariance, each block of observations
(magnification, disparity) scaled by its own reduced chi-square when that
exceeds one, and propagated to every derived quantity.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

PARAMETERS = ("main_focal_mm", "rail_zero_object_distance_mm", "L_mm", "b_mm", "Q0", "eta")
"""The fitted parameters, in order."""

PRIORS = ("main_focal_mm", "mla_focal_mm", "rail_zero_object_distance_mm")
"""The data-sheet values the sweep can confirm or replace."""

DISPARITY_BIAS_SE = 1e-2
"""1σ of the disparity's defocus bias ``η`` beyond the angular-shading model (the spread
measured on three independent renderers, module docstring)."""

IMAGE_SCALE_RESIDUAL = 5e-6
"""1σ of the measured ``(L+b)/L`` beyond its statistical error and the rim-shading model:
the plane normalization of :mod:`calibration.mla_grid` and the model's first order."""

IMAGE_SCALE_Z_MAX = 3.0
"""The micro-image pitch's ``(L+b)/L`` is used when it is within this many combined sigmas
of the sweep's own ``1 + b/L``."""

PRIOR_NEEDED_FRACTION = 1.0 / 3.0
"""A prior is used when the sweep alone determines its quantity to worse than this
fraction of the prior's tolerance."""


class ModelError(ValueError):
    """The priors or the data do not admit the thin-lens model (the message names the prior)."""


@dataclass(frozen=True)
class Priors:
    """Data-sheet values (mm) and their tolerances (mm, read as 1 sigma)."""

    main_focal_mm: float
    main_focal_tolerance_mm: float
    mla_focal_mm: float
    mla_focal_tolerance_mm: float
    rail_zero_object_distance_mm: float
    rail_zero_tolerance_mm: float
    direction: int

    def value(self, name: str) -> float:
        return float(getattr(self, name))

    def tolerance(self, name: str) -> float:
        key = {
            "main_focal_mm": "main_focal_tolerance_mm",
            "mla_focal_mm": "mla_focal_tolerance_mm",
            "rail_zero_object_distance_mm": "rail_zero_tolerance_mm",
        }[name]
        return float(getattr(self, key))


@dataclass(frozen=True)
class SweepMeasurements:
    """Per frame: rail position (mm), ``Q`` and ``1/M`` with 1-sigma errors; ``Q0`` of the blur.

    ``eta``: the angular-shading bias of the disparity, which reads
    ``Q·(1 + η·(Q - Q0))`` (:mod:`calibration.shading`), and its uncertainty.
    ``image_scale``: the white image's micro-image pitch over the lens pitch,
    ``(L+b)/L`` as the lattice fit reads it, and its statistical 1σ (NaN when not
    measured).
    """

    rail_mm: NDArray[np.float64]
    Q: NDArray[np.float64]
    Q_se: NDArray[np.float64]
    inv_magnification: NDArray[np.float64]
    inv_magnification_se: NDArray[np.float64]
    Q0: float
    Q0_se: float
    eta: float = 0.0
    eta_se: float = 0.0
    image_scale: float = float("nan")
    image_scale_se: float = float("nan")


@dataclass
class CameraModelFit:
    """The calibrated camera: values and 1-sigma uncertainties (mm; ``Q0`` dimensionless)."""

    values: dict[str, float]
    uncertainty: dict[str, float]
    determined_by: dict[str, str]
    sweep_only_uncertainty: dict[str, float]
    chi2_reduced: dict[str, float]
    magnification_frames: int
    inv_q_model: NDArray[np.float64] = field(repr=False)
    inv_magnification_model: NDArray[np.float64] = field(repr=False)
    parameters: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.zeros(6))
    covariance: NDArray[np.float64] = field(repr=False, default_factory=lambda: np.zeros((6, 6)))
    direction: int = 1
    image_scale: dict[str, Any] = field(default_factory=dict)
    disparity_error_scale: NDArray[np.float64] = field(
        repr=False, default_factory=lambda: np.ones(0)
    )
    """Per frame (NaN where no disparity): the factor the fit applied to the frame's Q error
    (its block's scatter times its robust inflation)."""

    def q_at_rail(
        self, rail_mm: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The calibrated camera's ``Q = b/(L - v(u))`` at rail positions (mm), with 1σ."""
        rail = np.asarray(rail_mm, dtype=np.float64)

        def q(p: NDArray[np.float64]) -> NDArray[np.float64]:
            F, u_rail0, L, b = p[0], p[1], p[2], p[3]
            u = u_rail0 + self.direction * rail
            return np.asarray(b / (L - u * F / (u - F)), dtype=np.float64)

        jac = _jacobian(q, self.parameters)
        var = np.einsum("ij,jk,ik->i", jac, self.covariance, jac)
        return q(self.parameters), np.sqrt(np.maximum(var, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "values": dict(self.values),
            "uncertainty": dict(self.uncertainty),
            "determined_by": dict(self.determined_by),
            "sweep_only_uncertainty": dict(self.sweep_only_uncertainty),
            "chi2_reduced": dict(self.chi2_reduced),
            "magnification_frames": self.magnification_frames,
            "image_scale": dict(self.image_scale),
        }


def _derived(p: NDArray[np.float64], direction: int) -> dict[str, float]:
    """Every reported quantity from the parameters ``(F, u_rail0, L, b, Q0, η)``."""
    F, u_rail0, L, b, q0, eta = (float(v) for v in p)
    a_f = b / q0
    v0 = L - a_f
    u0 = v0 * F / (v0 - F) if v0 > F else float("nan")
    return {
        "main_focal_mm": F,
        "rail_zero_object_distance_mm": u_rail0,
        "L_mm": L,
        "b_mm": b,
        "Q0": q0,
        "a_mm": a_f,
        "mla_focal_mm": b / (1.0 + q0),
        "focus_object_distance_mm": u0,
        "focus_rail_mm": (u0 - u_rail0) / direction,
        "eta": eta,
    }


class _Model:
    def __init__(self, data: SweepMeasurements, priors: Priors) -> None:
        self.d = data
        self.priors = priors
        self.dir = priors.direction
        self.q_ok = np.isfinite(data.Q) & np.isfinite(data.Q_se) & (data.Q > 0)
        self.m_ok = np.isfinite(data.inv_magnification) & np.isfinite(data.inv_magnification_se)
        # per frame: the block's scatter (reduced chi-square) times the frame's robust inflation
        self.q_scale: NDArray[np.float64] | float = 1.0
        self.m_scale: NDArray[np.float64] | float = 1.0
        self.use_prior: dict[str, bool] = {name: False for name in PRIORS}
        self.use_scale = False

    def u(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        return p[1] + self.dir * self.d.rail_mm

    def inv_q(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """``1/Q`` the disparity measures: the camera's ``(L - v)/b`` with the shading bias."""
        F, _, L, b, q0, eta = p
        u = self.u(p)
        v = u * F / (u - F)
        q = b / (L - v)
        return 1.0 / (q * (1.0 + eta * (q - q0)))

    def inv_m(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        F = p[0]
        return (self.u(p) - F) / F

    def blocks(
        self, p: NDArray[np.float64], *, priors: bool = True
    ) -> dict[str, NDArray[np.float64]]:
        d = self.d
        iq = 1.0 / d.Q[self.q_ok]
        iq_se = d.Q_se[self.q_ok] / d.Q[self.q_ok] ** 2 * self.q_scale
        out = {
            "disparity": (iq - self.inv_q(p)[self.q_ok]) / iq_se,
            "magnification": (
                (d.inv_magnification[self.m_ok] - self.inv_m(p)[self.m_ok])
                / (d.inv_magnification_se[self.m_ok] * self.m_scale)
            ),
            "focus": np.array([(d.Q0 - p[4]) / d.Q0_se]),
        }
        if self.use_scale:
            # the pitch fixes b/L, and the tilt of 1/Q(v) then measures the bias eta
            predicted, se = self.image_scale(p)
            out["image_pitch"] = np.array([(predicted - d.image_scale) / se])
        else:
            eta_se = float(np.hypot(d.eta_se, DISPARITY_BIAS_SE))
            out["shading"] = np.array([(d.eta - p[5]) / eta_se])
        if priors:
            pr = self.priors
            values = {
                "main_focal_mm": p[0],
                "rail_zero_object_distance_mm": p[1],
                "mla_focal_mm": p[3] / (1.0 + p[4]),
            }
            out["priors"] = np.array(
                [(values[n] - pr.value(n)) / pr.tolerance(n) for n in PRIORS if self.use_prior[n]]
            )
        return out

    def image_scale(self, p: NDArray[np.float64]) -> tuple[float, float]:
        """The ``(L+b)/L`` the lattice fit reads for parameters ``p``, and its 1σ.

        ``1 + β·(1 + (β - Q0)·η_s)``: the rims' shading pull with the
        shading's ``η_s`` (not the fitted disparity bias ``p[5]``).
        """
        d = self.d
        beta = p[3] / p[2]
        rim = beta * (beta - p[4])
        predicted = float(1.0 + beta + rim * d.eta)
        se = float(np.sqrt(d.image_scale_se**2 + (rim * d.eta_se) ** 2 + IMAGE_SCALE_RESIDUAL**2))
        return predicted, se

    def residuals(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.concatenate(list(self.blocks(p).values()))


HUBER_C = 2.5
"""Frames whose residual exceeds this many robust sigmas of their block get their error
inflated to match (Huber weights): a frame whose corners lock to the pixel grid near focus
(point-sampled or very sharp micro-images) measures Q and the magnification with errors
its own fit does not show, and must not pull the camera."""


def _reweight(model: _Model, p: NDArray[np.float64]) -> None:
    """Per-frame error scales of the disparity and magnification blocks at parameters ``p``.

    Each block's residuals in units of the frames' own errors, ``z``: a robust
    scale ``s = 1.4826·median|z|``; a frame with ``|z| > HUBER_C·s`` has its error
    multiplied by ``|z|/(HUBER_C·s)``; then the whole block by its reduced
    chi-square when that exceeds one.
    """
    model.q_scale, model.m_scale = 1.0, 1.0
    blocks = model.blocks(p, priors=False)
    scales = []
    for name, n_par in (("disparity", 3), ("magnification", 2)):
        z = blocks[name]
        if z.size <= n_par:
            scales.append(np.ones(z.size))
            continue
        robust = 1.4826 * float(np.median(np.abs(z)))
        inflation = np.maximum(1.0, np.abs(z) / max(HUBER_C * robust, 1e-12))
        chi2 = float(np.sum((z / inflation) ** 2) / (z.size - n_par))
        scales.append(inflation * np.sqrt(max(chi2, 1.0)))
    model.q_scale, model.m_scale = scales


def check_priors(priors: Priors, rail_mm: NDArray[np.float64]) -> None:
    """Refuse data-sheet values that leave no real image (a clear line naming the prior)."""
    problems = []
    for name in PRIORS:
        if not np.isfinite(priors.value(name)) or priors.value(name) <= 0:
            problems.append(f"{name} = {priors.value(name)} mm must be a positive number")
        if not np.isfinite(priors.tolerance(name)) or priors.tolerance(name) <= 0:
            problems.append(
                f"the tolerance of {name} = {priors.tolerance(name)} mm must be positive"
            )
    if problems:
        raise ModelError("; ".join(problems))
    if np.size(rail_mm) == 0:
        return
    u = priors.rail_zero_object_distance_mm + priors.direction * np.asarray(rail_mm)
    u_min = float(np.min(u))
    if priors.main_focal_mm >= u_min:
        raise ModelError(
            f"main_focal_mm = {priors.main_focal_mm:g} mm is not shorter than the nearest object "
            f"distance of the sweep, u = {u_min:.1f} mm (rail_zero_object_distance_mm "
            f"{priors.rail_zero_object_distance_mm:g} + direction·rail): the board would be "
            "inside the focal length; check the main-lens focal length and the rail zero distance"
        )


def _start(model: _Model) -> NDArray[np.float64]:
    """Starting parameters: linear fits where the data allow, the priors elsewhere."""
    d, pr = model.d, model.priors
    F, u_rail0 = pr.main_focal_mm, pr.rail_zero_object_distance_mm
    if model.m_ok.sum() >= 3:
        slope, intercept = np.polyfit(d.rail_mm[model.m_ok], d.inv_magnification[model.m_ok], 1)
        F_fit = model.dir / slope if slope * model.dir > 0 else float("nan")
        if np.isfinite(F_fit) and F_fit > 0:
            F, u_rail0 = F_fit, F_fit * (1.0 + intercept)
    u = u_rail0 + model.dir * d.rail_mm[model.q_ok]
    if np.min(u) <= F:
        F, u_rail0 = pr.main_focal_mm, pr.rail_zero_object_distance_mm
        u = u_rail0 + model.dir * d.rail_mm[model.q_ok]
    v = u * F / (u - F)
    slope, intercept = np.polyfit(v, 1.0 / d.Q[model.q_ok], 1)
    b = -1.0 / slope if slope < 0 else pr.mla_focal_mm * (1.0 + d.Q0)
    L = intercept * b
    return np.array([F, u_rail0, L, b, d.Q0, d.eta])


def _solve(model: _Model, p0: NDArray[np.float64]) -> NDArray[np.float64]:
    lower = [1e-3, 1e-3, 1e-3, 1e-4, 1e-6, -np.inf]
    fit = least_squares(
        model.residuals,
        p0,
        bounds=(lower, [np.inf] * 6),
        x_scale=np.maximum(np.abs(p0) * 1e-3, 1e-6),
        xtol=1e-14,
        ftol=1e-14,
        gtol=1e-14,
        max_nfev=2000,
    )
    return np.asarray(fit.x, dtype=np.float64)


def _covariance(jac: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(JᵀJ)⁻¹`` computed on Jacobi-scaled columns (the parameters span 1e-3..1e3 mm and
    their information spans twenty decades, which a plain inverse does not survive)."""
    norms = np.linalg.norm(jac, axis=0)
    scale = 1.0 / np.where(norms > 0, norms, 1.0)
    scaled = jac * scale[None, :]
    inner = np.linalg.inv(scaled.T @ scaled)
    return inner * scale[:, None] * scale[None, :]


def _jacobian(fun: Any, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Central-difference Jacobian of a vector function (relative steps)."""
    base = np.asarray(fun(p), dtype=np.float64)
    jac = np.zeros((base.size, p.size))
    for k in range(p.size):
        h = 1e-6 * max(abs(p[k]), 1e-3)
        up, down = p.copy(), p.copy()
        up[k] += h
        down[k] -= h
        jac[:, k] = (np.asarray(fun(up)) - np.asarray(fun(down))) / (2 * h)
    return jac


def _propagate(
    model: _Model, p: NDArray[np.float64], cov: NDArray[np.floating]
) -> dict[str, float]:
    names = list(_derived(p, model.dir))
    jac = _jacobian(lambda q: np.array(list(_derived(q, model.dir).values())), p)
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    return {n: float(np.sqrt(max(v, 0.0))) for n, v in zip(names, var, strict=True)}


def fit_camera_model(data: SweepMeasurements, priors: Priors) -> CameraModelFit:
    """Calibrate ``F``, ``u_rail0``, ``L``, ``b``, ``Q0`` (and ``a``, ``f``, the focus plane).

    Raises :class:`ModelError` naming the prior when the data-sheet values
    leave no real image, or when fewer than 3 frames have a disparity.
    """
    check_priors(priors, data.rail_mm)
    model = _Model(data, priors)
    if model.q_ok.sum() < 3:
        raise ModelError(f"the disparity was measured in only {int(model.q_ok.sum())} frames")
    # a first fit with every prior (always well posed), then decide which priors the sweep needs
    model.use_prior = {n: True for n in PRIORS}
    p = _solve(model, _start(model))
    for _ in range(3):
        # each observation block at its own (robust) scatter
        _reweight(model, p)
        sweep_se = _sweep_only_uncertainty(model, p)
        model.use_prior = {
            n: bool(sweep_se[n] > PRIOR_NEEDED_FRACTION * priors.tolerance(n)) for n in PRIORS
        }
        p = _solve(model, p)
    scale_check = _image_scale_check(model, p)
    if scale_check["used"]:
        model.use_scale = True
        sweep_se = _sweep_only_uncertainty(model, p)
        model.use_prior = {
            n: bool(sweep_se[n] > PRIOR_NEEDED_FRACTION * priors.tolerance(n)) for n in PRIORS
        }
        p = _solve(model, p)
    cov = _covariance(_jacobian(model.residuals, p))
    se = _propagate(model, p, cov)
    values = _derived(p, model.dir)
    if not np.isfinite(values["focus_object_distance_mm"]):
        raise ModelError(
            "the calibrated camera has no focus plane (L - a_f does not exceed F): check "
            "main_focal_mm and rail_zero_object_distance_mm"
        )
    blocks = model.blocks(p, priors=False)
    return CameraModelFit(
        values=values,
        uncertainty=se,
        determined_by={n: "prior" if model.use_prior[n] else "sweep" for n in PRIORS},
        sweep_only_uncertainty=_sweep_only_uncertainty(model, p),
        chi2_reduced={
            "disparity": float(
                np.sum(blocks["disparity"] ** 2) / max(1, blocks["disparity"].size - 3)
            ),
            "magnification": float(
                np.sum(blocks["magnification"] ** 2) / max(1, blocks["magnification"].size - 2)
            )
            if blocks["magnification"].size > 2
            else float("nan"),
            "disparity_scale": _median_scale(model.q_scale),
            "magnification_scale": _median_scale(model.m_scale),
        },
        magnification_frames=int(model.m_ok.sum()),
        inv_q_model=model.inv_q(p),
        inv_magnification_model=model.inv_m(p),
        parameters=p,
        covariance=cov,
        direction=model.dir,
        image_scale=scale_check,
        disparity_error_scale=_per_frame(model.q_ok, model.q_scale),
    )


def _median_scale(scale: NDArray[np.float64] | float) -> float:
    """The typical error scale a block's frames got (1 for an empty block)."""
    values = np.atleast_1d(np.asarray(scale, dtype=np.float64))
    return float(np.median(values)) if values.size else 1.0


def _per_frame(ok: NDArray[np.bool_], values: NDArray[np.float64] | float) -> NDArray[np.float64]:
    out = np.full(ok.size, np.nan)
    out[ok] = values
    return out


def _image_scale_check(model: _Model, p: NDArray[np.float64]) -> dict[str, Any]:
    """The measured ``(L+b)/L`` against the sweep's own ``1 + b/L`` (fit ``p`` without it).

    ``used`` when they agree within :data:`IMAGE_SCALE_Z_MAX` combined sigmas.
    """
    d = model.d
    if not (np.isfinite(d.image_scale) and np.isfinite(d.image_scale_se) and d.image_scale_se >= 0):
        return {"measured": None, "used": False}
    cov = _covariance(_jacobian(model.residuals, p))
    jac = _jacobian(lambda q: np.array([model.image_scale(q)[0]]), p)
    sweep, measured_se = model.image_scale(p)
    sweep_se = float(np.sqrt(max(float((jac @ cov @ jac.T)[0, 0]), 0.0)))
    z = (d.image_scale - sweep) / float(np.hypot(measured_se, sweep_se))
    return {
        "measured": float(d.image_scale),
        "measured_se": measured_se,
        "rim_shading": sweep - 1.0 - float(p[3] / p[2]),
        "sweep": sweep,
        "sweep_se": sweep_se,
        "z": float(z),
        "used": bool(abs(z) <= IMAGE_SCALE_Z_MAX),
    }


def _sweep_only_uncertainty(model: _Model, p: NDArray[np.float64]) -> dict[str, float]:
    """How well the sweep alone fixes each prior's quantity (mm; inf when it cannot).

    The Fisher information of the observations, plus the priors at a
    millionth of their weight (tolerances a thousand times wider) so that
    directions the sweep leaves free come out as enormous, not singular.
    """
    saved = dict(model.use_prior)
    model.use_prior = {n: True for n in PRIORS}
    try:
        data_jac = _jacobian(
            lambda q: np.concatenate(list(model.blocks(q, priors=False).values())), p
        )
        prior_jac = _jacobian(lambda q: model.blocks(q)["priors"], p)
    finally:
        model.use_prior = saved
    stacked = np.vstack([data_jac, 1e-3 * prior_jac])
    try:
        cov = _covariance(stacked)
    except np.linalg.LinAlgError:
        return {n: float("inf") for n in PRIORS}
    names = list(_derived(p, model.dir))
    jac = _jacobian(lambda q: np.array(list(_derived(q, model.dir).values())), p)
    var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    # a variance the inversion could not resolve (negative) means: not determined
    return {
        n: float(np.sqrt(v)) if v > 0 else float("inf")
        for n, v in zip(names, var, strict=True)
        if n in PRIORS
    }
