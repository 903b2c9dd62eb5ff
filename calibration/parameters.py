"""Geometric parameters from the disparity ``Q(u)`` and the blur (ESIF Eq. 1–5, and a global fit).

Paper estimate: ``Q`` at the focus plane, ``b = f(1+Q)``, ``a = b/Q``,
``p = Q·D/δ``.

Global estimate: ``1/Q(u) = (L - v(u))/b`` is linear in ``v(u)``; together with
the blur model of :mod:`calibration.focus` (whose minimum sits where
``L - v = a_f = f·b/(b - f)``) one weighted least-squares fit over every frame
gives ``b`` and ``L``, hence ``a = a_f``, the focus plane ``u0``, ``Q = b/a``
and ``p``. Uncertainties are propagated from the fit covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from .focus import width_squared_px2
from .optics import focused_virtual_distance, image_distance, object_distance


@dataclass(frozen=True)
class Estimate:
    """A set of calibrated parameters with 1-sigma uncertainties (mm, px)."""

    a_mm: float
    b_mm: float
    Q: float
    patch_size_px: float
    focus_object_distance_mm: float
    a_se_mm: float = float("nan")
    b_se_mm: float = float("nan")
    Q_se: float = float("nan")
    patch_size_se_px: float = float("nan")
    focus_se_mm: float = float("nan")
    L_mm: float = float("nan")
    L_se_mm: float = float("nan")

    def to_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


def paper_estimate(
    Q_focus: float,
    Q_focus_se: float,
    *,
    f: float,
    D: float,
    delta: float,
    focus_object_distance_mm: float,
    focus_se_mm: float = float("nan"),
) -> Estimate:
    """Eq. 1–5 from ``Q`` at the focus plane: ``b = f(1+Q)``, ``a = b/Q``, ``p = Q D/δ``."""
    b = f * (1.0 + Q_focus)
    a = b / Q_focus
    return Estimate(
        a_mm=a,
        b_mm=b,
        Q=Q_focus,
        patch_size_px=Q_focus * D / delta,
        focus_object_distance_mm=focus_object_distance_mm,
        a_se_mm=f * Q_focus_se / Q_focus**2,
        b_se_mm=f * Q_focus_se,
        Q_se=Q_focus_se,
        patch_size_se_px=Q_focus_se * D / delta,
        focus_se_mm=focus_se_mm,
    )


def q_at(
    object_distance_mm: ArrayLike,
    Q: ArrayLike,
    Q_se: ArrayLike,
    u_target: float,
    *,
    half_window_mm: float = 6.0,
) -> tuple[float, float]:
    """``Q`` at ``u_target`` by a weighted line through the frames within ``±half_window_mm``."""
    u = np.asarray(object_distance_mm, dtype=np.float64)
    q = np.asarray(Q, dtype=np.float64)
    se = np.asarray(Q_se, dtype=np.float64)
    near = np.isfinite(q) & np.isfinite(se) & (np.abs(u - u_target) <= half_window_mm)
    if near.sum() < 2:
        near = np.isfinite(q) & np.isfinite(se)
        order = np.argsort(np.abs(u[near] - u_target))[:3]
        idx = np.flatnonzero(near)[order]
        near = np.zeros_like(near)
        near[idx] = True
    if near.sum() == 1:
        k = int(np.flatnonzero(near)[0])
        return float(q[k]), float(se[k])
    w = 1.0 / np.maximum(se[near], 1e-9) ** 2
    x = u[near] - u_target
    design = np.stack([np.ones_like(x), x], axis=1)
    cov = np.linalg.inv((design * w[:, None]).T @ design)
    coef = cov @ ((design * w[:, None]).T @ q[near])
    resid = q[near] - design @ coef
    chi2 = float(np.sum(w * resid**2) / max(1, int(near.sum()) - 2))
    return float(coef[0]), float(np.sqrt(cov[0, 0] * max(chi2, 1.0)))


@dataclass(frozen=True)
class GlobalFit:
    """Result of the whole-sweep fit of disparity (and blur)."""

    estimate: Estimate
    inv_q_residual_rms: float
    uses_blur: bool
    inv_q_model: NDArray[np.float64]
    width_model_px: NDArray[np.float64]


def global_fit(
    object_distance_mm: ArrayLike,
    Q: ArrayLike,
    Q_se: ArrayLike,
    *,
    F: float,
    f: float,
    D: float,
    delta: float,
    edge_width_px: ArrayLike | None = None,
    width_scale: float | None = None,
) -> GlobalFit:
    """Weighted fit of ``1/Q = (L - v)/b`` (and, with widths, the blur model) over all frames.

    Parameters ``(b, L)`` or ``(b, L, A, B, C)`` (the blur model of
    :func:`calibration.focus.width_squared_px2`); the focus plane is where
    ``L - v = a_f(b)``. ``width_scale`` is the per-frame scatter of ``w²``
    (px²) used to weight the blur terms (estimated from the data when None).
    """
    u = np.asarray(object_distance_mm, dtype=np.float64)
    q = np.asarray(Q, dtype=np.float64)
    se = np.asarray(Q_se, dtype=np.float64)
    good_q = np.isfinite(q) & np.isfinite(se) & (q > 0)
    if good_q.sum() < 3:
        raise ValueError(
            f"the disparity model needs Q in at least 3 frames, got {int(good_q.sum())}"
        )
    v = np.asarray(image_distance(u, F))
    y = 1.0 / q[good_q]
    sy = np.maximum(se[good_q], 1e-9) / q[good_q] ** 2
    # linear start: y = L/b - v/b
    design = np.stack([np.ones(int(good_q.sum())), v[good_q]], axis=1)
    wts = 1.0 / sy**2
    coef = np.linalg.solve((design * wts[:, None]).T @ design, (design * wts[:, None]).T @ y)
    b0 = -1.0 / coef[1]
    L0 = coef[0] * b0
    chi_q = float(np.sqrt(np.sum(wts * (y - design @ coef) ** 2) / max(1, y.size - 2)))
    sy_eff = sy * max(chi_q, 1.0)

    widths = None if edge_width_px is None else np.asarray(edge_width_px, dtype=np.float64)
    good_w = np.zeros_like(good_q) if widths is None else np.isfinite(widths)
    use_blur = bool(good_w.sum() >= 5)

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        b, L = p[0], p[1]
        r_q = (y - (L - v[good_q]) / b) / sy_eff
        if not use_blur:
            return r_q
        assert widths is not None
        A, B, C = p[2], p[3], p[4]
        a_f = focused_virtual_distance(f, b)
        model = width_squared_px2(v[good_w], L - a_f, a_f, A, B, C)
        return np.concatenate([r_q, (model - widths[good_w] ** 2) / w_scale])

    w_scale = 1.0
    if use_blur:
        assert widths is not None
        w2 = widths[good_w] ** 2
        p0 = np.array([b0, L0, float(w2.min()), float(max(w2.max() - w2.min(), 1e-6)) * 40.0, 0.0])
        if width_scale is None:
            # scatter of w² about a smooth curve: from differences of neighbouring frames
            order = np.argsort(u[good_w])
            w_scale = float(np.std(np.diff(w2[order])) / np.sqrt(2.0)) + 1e-9
        else:
            w_scale = width_scale
    else:
        p0 = np.array([b0, L0])
    lower = [f * 1.0001, 0.0] + ([0.0, 0.0, -np.inf] if use_blur else [])
    fit = least_squares(resid, p0, bounds=(lower, [np.inf] * len(p0)), x_scale="jac")
    r = fit.fun
    s2 = max(float(np.sum(r**2) / max(1, r.size - len(p0))), 1.0)
    cov = np.linalg.pinv(fit.jac.T @ fit.jac) * s2
    b, L = float(fit.x[0]), float(fit.x[1])

    def derived(p: NDArray[np.float64]) -> NDArray[np.float64]:
        bb, LL = p[0], p[1]
        af = focused_virtual_distance(f, bb)
        v0 = LL - af
        return np.array([af, bb / af, bb / af * D / delta, float(object_distance(v0, F))])

    base = derived(fit.x)
    jac = np.zeros((4, len(p0)))
    for k in range(2):
        step = np.zeros(len(p0))
        step[k] = 1e-7 * max(abs(fit.x[k]), 1.0)
        jac[:, k] = (derived(fit.x + step) - base) / step[k]
    dcov = jac @ cov @ jac.T
    dse = np.sqrt(np.maximum(np.diag(dcov), 0.0))
    est = Estimate(
        a_mm=float(base[0]),
        b_mm=b,
        Q=float(base[1]),
        patch_size_px=float(base[2]),
        focus_object_distance_mm=float(base[3]),
        a_se_mm=float(dse[0]),
        b_se_mm=float(np.sqrt(cov[0, 0])),
        Q_se=float(dse[1]),
        patch_size_se_px=float(dse[2]),
        focus_se_mm=float(dse[3]),
        L_mm=L,
        L_se_mm=float(np.sqrt(cov[1, 1])),
    )
    inv_q_model = (L - v) / b
    width_model = np.full(u.shape, np.nan)
    if use_blur:
        a_f = focused_virtual_distance(f, b)
        width_model = np.sqrt(np.maximum(width_squared_px2(v, L - a_f, a_f, *fit.x[2:5]), 0.0))
    q_res = y - (L - v[good_q]) / b
    return GlobalFit(est, float(np.sqrt(np.mean(q_res**2))), use_blur, inv_q_model, width_model)
