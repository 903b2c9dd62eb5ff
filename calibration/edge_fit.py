"""Batched sub-pixel edge fits: the edge-spread model of ESIF step 3.

Each profile is a run of grey values sampled across an edge at integer
positions ``t = 0 .. K-1`` (pixels). The model is a blurred step,

    I(t) = B + C · ∫ Φ((τ - t0) / w) dτ   over the pixel τ ∈ [t - ½, t + ½],

Φ the standard normal CDF: a Gaussian-blurred step integrated over the pixel
area, with background ``B``, signed contrast ``C``, edge position ``t0`` (the
point of largest derivative of the fitted curve, the sub-pixel edge point) and
edge spread ``w`` (the Gaussian sigma of the blur *before* pixel integration,
pixels). Modelling the pixel area keeps ``w`` free of the sampling phase, which
otherwise dominates the fitted width of a nearly sharp edge. All
profiles are fitted at once with a damped Gauss–Newton (Levenberg–Marquardt)
iteration vectorized over profiles. :func:`fit_edges_symmetric` fits each profile on
the samples whose mirror image about its edge is fitted too (the corners' fits: a
window cut unevenly reads a long-tailed edge towards its longer side).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

_SQRT_2PI = np.sqrt(2.0 * np.pi)


@dataclass(frozen=True)
class EdgeFits:
    """Per-profile fit results (arrays of length N; positions in profile pixels)."""

    position: NDArray[np.float64]
    width: NDArray[np.float64]
    background: NDArray[np.float64]
    contrast: NDArray[np.float64]
    rms_residual: NDArray[np.float64]
    position_se: NDArray[np.float64]
    ok: NDArray[np.bool_]


def _model(t: NDArray[np.float64], p: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Pixel-integrated blurred step and its Jacobian ``(N, K, 4)``.

    With ``G(z) = z Φ(z) + φ(z)`` (so ``G' = Φ``), the pixel integral is
    ``w [G(z+) - G(z-)]``, ``z± = (t ± ½ - t0)/w``.
    """
    B, C, t0, w = (p[:, k : k + 1] for k in range(4))
    # the K samples share their K+1 pixel boundaries: evaluate the special functions once
    z = (np.append(t, t[-1] + 1.0)[None, :] - 0.5 - t0) / w
    phi = np.exp(-0.5 * z * z) / _SQRT_2PI
    Phi = ndtr(z)
    g = z * Phi + phi
    zp = z[:, 1:]
    phi_p, phi_m = phi[:, 1:], phi[:, :-1]
    Phi_p, Phi_m = Phi[:, 1:], Phi[:, :-1]
    box = w * (g[:, 1:] - g[:, :-1])
    value = B + C * box
    jac = np.stack([np.ones_like(zp), box, -C * (Phi_p - Phi_m), C * (phi_p - phi_m)], axis=-1)
    return value, jac


def _filled(y: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """``y`` with every invalid sample replaced by the nearest valid one of its row (for the
    initial guesses only: the fit gives invalid samples no weight)."""
    k = y.shape[1]
    idx = np.where(valid, np.arange(k)[None, :], -1)
    last = np.maximum.accumulate(idx, axis=1)  # nearest valid to the left
    idx_r = np.where(valid, np.arange(k)[None, :], k)
    nxt = np.minimum.accumulate(idx_r[:, ::-1], axis=1)[:, ::-1]  # nearest valid to the right
    source = np.where(last >= 0, last, np.minimum(nxt, k - 1))
    return np.take_along_axis(y, source, axis=1)


def fit_edges(
    profiles: NDArray[np.floating],
    *,
    valid: NDArray[np.bool_] | None = None,
    initial: EdgeFits | None = None,
    max_iter: int = 12,
    min_width: float = 0.0,
    max_width: float = 6.0,
) -> EdgeFits:
    """Fit the blurred-step model to every row of ``profiles`` (shape ``(N, K)``).

    ``valid`` (same shape) marks the samples a fit uses (default all): a profile
    whose ends reach into a micro-image's vignetted rim leaves them out rather
    than fitting a step to a falling level. ``initial`` (N fits) starts every fit
    from those parameters (where they are finite) instead of a guess from the
    profile. ``ok`` is False when a fit did not converge, left the profile, or has a
    width outside ``[min_width, max_width]`` pixels.
    """
    y = np.asarray(profiles, dtype=np.float64)
    if y.ndim != 2 or y.shape[1] < 5:
        raise ValueError("profiles must be a 2-D array with at least 5 samples per profile")
    n, k = y.shape
    t = np.arange(k, dtype=np.float64)
    weight: NDArray[np.float64] | None = None
    if valid is not None:
        mask = np.asarray(valid, dtype=bool)
        if mask.shape != y.shape:
            raise ValueError("valid must have the shape of profiles")
        if not mask.all():
            weight = mask.astype(np.float64)
            y = _filled(y, mask)
    # a guess: step from the ends, position at the steepest gradient
    ends = max(1, k // 5)
    B = y[:, :ends].mean(axis=1)
    C = y[:, -ends:].mean(axis=1) - B
    grad = np.abs(np.diff(y, axis=1))
    t0 = np.argmax(grad, axis=1) + 0.5
    w = np.full(n, 0.8)
    p = np.stack([B, C, t0, w], axis=1)
    if initial is not None:  # where its parameters are finite
        start = np.stack(
            [initial.background, initial.contrast, initial.position, initial.width], axis=1
        ).astype(np.float64)
        finite = np.all(np.isfinite(start), axis=1, keepdims=True)
        p = np.where(finite, start, p)
    lam = np.full(n, 1e-3)
    value, jac = _model(t, p)
    r = y - value
    if weight is not None:
        jac *= weight[:, :, None]
        r *= weight
    cost = np.einsum("nk,nk->n", r, r)
    eye = np.eye(4)[None]
    active = np.arange(n)
    for _ in range(max_iter):
        if active.size == 0:
            break
        every = active.size == n  # no copies while every profile still iterates
        ja = jac if every else jac[active]
        ra = r if every else r[active]
        jt = ja.transpose(0, 2, 1)
        jtj = jt @ ja
        jtr = (jt @ ra[:, :, None])[:, :, 0]
        diag = np.maximum(np.einsum("nii->ni", jtj), 1e-12)
        a = jtj + (lam[active, None] * diag)[:, :, None] * eye
        try:
            step = np.linalg.solve(a, jtr[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            step = np.stack(
                [np.linalg.lstsq(m, v, rcond=None)[0] for m, v in zip(a, jtr, strict=True)]
            )
        trial = (p if every else p[active]) + step
        trial[:, 3] = np.clip(trial[:, 3], 0.02, 50.0)
        t_value, t_jac = _model(t, trial)
        t_r = (y if every else y[active]) - t_value
        if weight is not None:
            w_active = weight if every else weight[active]
            t_jac *= w_active[:, :, None]
            t_r *= w_active
        t_cost = np.einsum("nk,nk->n", t_r, t_r)
        better = t_cost < cost[active]
        if every and better.all():
            p, jac, r, cost = trial, t_jac, t_r, t_cost
        else:
            idx = active[better]
            p[idx] = trial[better]
            jac[idx], r[idx], cost[idx] = t_jac[better], t_r[better], t_cost[better]
        lam[active] = np.where(better, lam[active] * 0.3, lam[active] * 10.0)
        done = (np.abs(step[:, 2]) < 1e-5) & (np.abs(step[:, 3]) < 1e-5) | (lam[active] > 1e8)
        active = active[~done]
    used = np.full(n, float(k)) if weight is None else weight.sum(axis=1)
    sigma2 = cost / np.maximum(used - 4.0, 1.0)
    jt = jac.transpose(0, 2, 1)
    jtj = jt @ jac
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # singular: inf cov
        det = np.linalg.det(jtj)
    position_var = np.full(n, np.inf)  # a singular fit (even a noise-free one): undetermined
    good = np.isfinite(det) & (np.abs(det) > 1e-300)
    if np.any(good):
        cov = np.linalg.inv(jtj[good])
        position_var[good] = sigma2[good] * cov[:, 2, 2]
    position_se = np.sqrt(np.maximum(position_var, 0.0))
    width = np.abs(p[:, 3])
    ok = (
        np.isfinite(p).all(axis=1)
        & (p[:, 2] > 1.0)
        & (p[:, 2] < k - 2.0)
        & (width >= min_width)
        & (width <= max_width)
        & np.isfinite(position_se)
    )
    return EdgeFits(
        position=p[:, 2],
        width=width,
        background=p[:, 0],
        contrast=p[:, 1],
        rms_residual=np.sqrt(cost / np.maximum(used, 1.0)),
        position_se=position_se,
        ok=ok,
    )


def symmetric_about_edges(
    valid: NDArray[np.bool_], position: NDArray[np.floating]
) -> NDArray[np.bool_]:
    """The samples of ``valid`` (shape ``(N, K)``) whose mirror image about their row's
    edge is valid too: sample ``t`` mirrors to ``m − t``, ``m = round(2·position)``
    (``position`` in profile pixels, so the mirror is about the nearest whole or half
    sample); a mirror outside the profile counts as not valid."""
    k = valid.shape[1]
    centre = np.asarray(position, dtype=np.float64)
    centre = np.where(np.isfinite(centre), np.clip(centre, -k, 2 * k), -k)  # -k: no mirror
    mirror = np.rint(2.0 * centre)[:, None].astype(np.intp)
    mirror = mirror - np.arange(k)[None, :]
    inside = (mirror >= 0) & (mirror < k)
    mirrored = np.take_along_axis(valid, np.clip(mirror, 0, k - 1), axis=1) & inside
    return valid & mirrored


def fit_edges_symmetric(
    profiles: NDArray[np.floating],
    *,
    valid: NDArray[np.bool_],
    min_samples: int,
    locating_iterations: int = 2,
    max_width: float = 6.0,
) -> EdgeFits:
    """:func:`fit_edges` on windows symmetric about each profile's edge.

    A window cut unevenly about the edge (by the profile's end, or by ``valid`` at a
    micro-image's rim) biases the edge towards the longer side wherever the blur is not
    the model's Gaussian: the shorter side's level is read where a long-tailed blur
    (diffraction) has not yet settled. With the samples mirrored about the edge
    (:func:`symmetric_about_edges`) a symmetric blur's departures from the model pull
    both ways equally. A first fit of ``locating_iterations`` steps locates each edge;
    every profile is then fitted from it on its symmetric window, or on ``valid`` where
    that window keeps fewer than ``min_samples`` samples or the first fit failed.
    """
    located = fit_edges(profiles, valid=valid, max_iter=locating_iterations, max_width=max_width)
    window = symmetric_about_edges(valid, located.position)
    mirrored = located.ok & (window.sum(axis=1) >= min_samples)
    window = np.where(mirrored[:, None], window, valid)
    return fit_edges(profiles, valid=window, initial=located, max_width=max_width)
