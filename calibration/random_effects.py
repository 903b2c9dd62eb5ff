"""A weighted mean of measurements whose stated errors are too small: random effects.

Measurements ``y_k`` of one quantity (vectors of ``d`` coordinates, each coordinate with
the stated variance ``v_k``) often scatter more than ``v_k`` allow, and not in proportion
to it: an edge fit's standard error states the noise, not how far the edge's position
locks to the pixel grid when the pixels do not resolve it, and the sharpest, most locked
edge claims the smallest error. Weighing by ``1/v_k`` then hands the mean to the
measurement that is most wrong, and scaling its variance by the scatter (a Birge ratio)
keeps that mean. The random-effects model adds one unknown variance ``τ²`` to every
measurement, ``y_k = μ + e_k + b_k`` with ``var e_k = v_k``, ``var b_k = τ²``, and weighs
by ``1/(v_k + τ²)``. :func:`paule_mandel` estimates ``τ²`` by Paule and Mandel's rule
(J. Res. NBS 87, 377, 1982): the weighted scatter about the weighted mean equals its
degrees of freedom, ``Σ w_k |y_k - ȳ|² = d·(n - 1)``; 0 when the stated errors already
explain it. The weighted mean's variance (per coordinate) is then ``1/Σ w_k``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq


def _scatter(values: NDArray[np.float64], variances: NDArray[np.float64], tau2: float) -> float:
    """``Σ w |y - ȳ|²`` with ``w = 1/(v + τ²)`` and ``ȳ`` the mean weighted by ``w``."""
    w = 1.0 / (variances + tau2)
    mean = w @ values / float(np.sum(w))
    return float(np.sum(w * np.sum((values - mean) ** 2, axis=1)))


def paule_mandel(values: NDArray[np.floating], variances: NDArray[np.floating]) -> float:
    """The variance ``τ²`` between measurements beyond their stated ones (units of
    ``values`` squared).

    ``values``: ``(n, d)``, one measurement per row; ``variances``: ``(n,)``, each
    measurement's stated variance per coordinate (positive). 0 with fewer than two
    measurements or when their weighted scatter is within its ``d·(n - 1)`` degrees of
    freedom.
    """
    y = np.asarray(values, dtype=np.float64)
    v = np.asarray(variances, dtype=np.float64)
    if y.ndim != 2 or v.shape != (y.shape[0],) or not np.all(v > 0):
        raise ValueError("values (n, d) with one positive variance per measurement")
    n, d = y.shape
    dof = float(d * (n - 1))
    if n < 2 or _scatter(y, v, 0.0) <= dof:
        return 0.0
    # the scatter falls monotonically with τ²; find an upper end where it is below dof
    high = float(np.sum((y - y.mean(axis=0)) ** 2)) / dof + float(np.max(v))
    while _scatter(y, v, high) > dof:
        high *= 4.0
    return float(brentq(lambda t: _scatter(y, v, t) - dof, 0.0, high, xtol=1e-12 * high))
