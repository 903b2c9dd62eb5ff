"""Focus-plane confirmation (ESIF Eq. 7–9) and a blur model fitted to the whole sweep.

Per frame: ``Ls``, ``Lr`` (corner pixel sizes of the standard and reference
corner), ``Lp = Cr/(Lr - Ls)`` (object mm per pixel, Eq. 7), ``La = Lp·Ls``
(corner size in mm, Eq. 8). The paper's focus plane is ``argmin La`` (Eq. 9);
here it is refined below the rail step by a weighted quadratic through the
frames around the minimum.

The blur minimum is shallow (ESIF.md, known weak points), so the delivered
focus plane comes from a model fitted to the edge-spread widths of every frame:

    w(v)² = A + B·s² + C·s⁴,   s = (v0 - v) / (a_f + v0 - v),

the PSF and pixel (``A``) plus the geometric defocus blur, which is
proportional to ``|s| ∝ |1/a_f - 1/a(u)|`` with ``a = L - v = a_f + v0 - v``.
``v0`` is the main-image distance of the focus plane; ``u0 = v0 F/(v0 - F)``.

The quartic term is there because the fitted edge-spread width of a blur that
is a box (the microlens aperture) convolved with the PSF and the pixel does not
add in quadrature exactly: ``(w² - A)/s²`` grows by a few per cent over a
sweep. The sweep is not symmetric in ``s`` (uniform rail steps, ``s`` is
nonlinear in ``u``), so a purely quadratic model leans towards the side with
more frames: on noise-free renders of the paper's optics it put the focus plane
0.17 mm too far; with the symmetric ``s⁴`` term it is within 0.03 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from .optics import image_distance, object_distance


class FocusAtSweepEdge(ValueError):
    """The blur minimum is not inside the sweep: extend the rail range."""


@dataclass(frozen=True)
class PaperFocus:
    """Eq. 9: the frame with the smallest ``La`` and the refined argmin (mm)."""

    best_index: int
    object_distance_mm: float


@dataclass(frozen=True)
class BlurModelFocus:
    """The whole-sweep blur model fit."""

    object_distance_mm: float
    object_distance_se_mm: float
    v0_mm: float
    A_px2: float
    B_px2: float
    C_px2: float
    residual_rms_px2: float
    width_model_px: NDArray[np.float64]


def corner_size_mm(
    Ls_px: ArrayLike, Lr_px: ArrayLike, reference_gap_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``Lp = Cr/(Lr - Ls)`` (mm/px, Eq. 7) and ``La = Lp·Ls`` (mm, Eq. 8); NaN where undefined."""
    ls = np.asarray(Ls_px, dtype=np.float64)
    lr = np.asarray(Lr_px, dtype=np.float64)
    diff = lr - ls
    with np.errstate(divide="ignore", invalid="ignore"):
        lp = np.where(diff > 0, reference_gap_mm / diff, np.nan)
    return lp, lp * ls


def paper_focus(
    object_distance_mm: ArrayLike, La_mm: ArrayLike, *, half_window: int = 6
) -> PaperFocus | None:
    """Eq. 9: ``argmin La(u)``, refined by a quadratic over ``±half_window`` frames.

    Returns None when fewer than 3 frames have a finite ``La``.
    """
    u = np.asarray(object_distance_mm, dtype=np.float64)
    la = np.asarray(La_mm, dtype=np.float64)
    good = np.flatnonzero(np.isfinite(la))
    if good.size < 3:
        return None
    order = good[np.argsort(u[good])]
    us, las = u[order], la[order]
    # a light median smoothing so that one noisy frame cannot win the argmin
    k = int(np.argmin(_median3(las)))
    lo, hi = max(0, k - half_window), min(len(us), k + half_window + 1)
    u_best = float(us[k])
    if hi - lo >= 3:
        c = np.polyfit(us[lo:hi] - us[k], las[lo:hi], 2)
        if c[0] > 0:
            vertex = -c[1] / (2 * c[0])
            if abs(vertex) <= (us[hi - 1] - us[lo]) / 2:
                u_best = float(us[k] + vertex)
    return PaperFocus(int(order[k]), u_best)


def _median3(x: NDArray[np.float64]) -> NDArray[np.float64]:
    if x.size < 3:
        return x
    padded = np.concatenate([[x[0]], x, [x[-1]]])
    return np.median(np.stack([padded[:-2], padded[1:-1], padded[2:]]), axis=0)


def blur_shape(v: ArrayLike, v0: float, a_f: float) -> NDArray[np.float64]:
    """``(v0 - v)/(a_f + v0 - v)``: the geometric blur up to a constant factor."""
    v_arr = np.asarray(v, dtype=np.float64)
    return (v0 - v_arr) / (a_f + v0 - v_arr)


def width_squared_px2(
    v: ArrayLike, v0: float, a_f: float, A: float, B: float, C: float
) -> NDArray[np.float64]:
    """The blur model ``w² = A + B·s² + C·s⁴`` (px²) at main-image distances ``v`` (mm)."""
    s2 = blur_shape(v, v0, a_f) ** 2
    return A + s2 * (B + C * s2)


def fit_blur_model(
    object_distance_mm: ArrayLike, edge_width_px: ArrayLike, *, F: float, a_f: float
) -> BlurModelFocus:
    """Fit ``w² = A + B·s² + C·s⁴`` over the sweep; raise :class:`FocusAtSweepEdge`.

    ``a_f`` (mm) only sets the weak curvature of the blur shape; its error has
    a negligible effect on ``v0``.
    """
    u = np.asarray(object_distance_mm, dtype=np.float64)
    w = np.asarray(edge_width_px, dtype=np.float64)
    good = np.isfinite(u) & np.isfinite(w)
    if good.sum() < 5:
        raise ValueError(
            f"the blur model needs at least 5 frames with edges, got {int(good.sum())}"
        )
    v = np.asarray(image_distance(u[good], F))
    w2 = w[good] ** 2
    v_lo, v_hi = float(v.min()), float(v.max())
    k = int(np.argmin(w2))
    v_k = float(v[k])

    def resid(p: NDArray[np.float64]) -> NDArray[np.float64]:
        A, B, v0, C = p
        return width_squared_px2(v, v0, a_f, A, B, C) - w2

    span = v_hi - v_lo
    s_max = max(
        float(abs(blur_shape(v_lo, v_k, a_f))), float(abs(blur_shape(v_hi, v_k, a_f))), 1e-9
    )
    p0 = np.array([w2.min(), max(float(w2.max() - w2.min()), 1e-6) / s_max**2, v_k, 0.0])
    fit = least_squares(
        resid,
        p0,
        loss="soft_l1",
        f_scale=float(np.std(w2)) + 1e-9,
        bounds=([0.0, 0.0, v_lo - span, -np.inf], [np.inf, np.inf, v_hi + span, np.inf]),
        x_scale="jac",
    )
    A, B, v0, C = fit.x
    r = fit.fun
    dof = max(1, r.size - 4)
    s2 = float(np.sum(r**2) / dof)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
        v0_se = float(np.sqrt(max(cov[2, 2], 0.0)))
    except np.linalg.LinAlgError:
        v0_se = float("inf")
    margin = 0.02 * span
    if not (v_lo + margin <= v0 <= v_hi - margin):
        raise FocusAtSweepEdge(
            f"focus plane at the sweep edge (blur model minimum at u = "
            f"{float(object_distance(v0, F)):.1f} mm, sweep covers u = {u[good].min():.1f}.."
            f"{u[good].max():.1f} mm): extend the range"
        )
    u0 = float(object_distance(v0, F))
    du_dv = (F / (v0 - F)) ** 2  # |du/dv|
    model = np.full(u.shape, np.nan)
    model[good] = np.sqrt(np.maximum(width_squared_px2(v, v0, a_f, A, B, C), 0.0))
    return BlurModelFocus(
        u0, v0_se * du_dv, float(v0), float(A), float(B), float(C), float(np.sqrt(s2)), model
    )
