"""Paule–Mandel's between-measurement variance (:mod:`calibration.random_effects`)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from calibration.random_effects import paule_mandel


def _scatter(y: np.ndarray, v: np.ndarray, tau2: float) -> float:
    w = 1.0 / (v + tau2)
    mean = w @ y / w.sum()
    return float(np.sum(w * np.sum((y - mean) ** 2, axis=1)))


def test_equal_stated_errors_give_the_sample_variance_beyond_them() -> None:
    """With one stated variance for all, Paule–Mandel is the moment estimator in closed
    form: ``τ² = Σ|y - ȳ|²/(d(n-1)) - v`` (when positive)."""
    y = np.array([[0.0, 1.0], [0.4, 0.7], [-0.3, 1.2], [0.2, 0.8]])
    v = np.full(4, 1e-4)
    expected = float(np.sum((y - y.mean(axis=0)) ** 2)) / (2 * 3) - 1e-4
    assert_allclose(paule_mandel(y, v), expected, rtol=1e-9)


def test_the_weighted_scatter_then_equals_its_degrees_of_freedom() -> None:
    rng = np.random.default_rng(3)
    y = rng.normal(0.0, 0.2, (6, 2))
    v = np.array([1e-6, 4e-4, 1e-3, 2e-5, 5e-4, 1e-4])  # uneven, all far below 0.04
    tau2 = paule_mandel(y, v)
    assert tau2 > 0
    assert_allclose(_scatter(y, v, tau2), 2 * 5, rtol=1e-8)


def test_no_excess_when_the_stated_errors_explain_the_scatter() -> None:
    rng = np.random.default_rng(4)
    v = np.full(8, 0.01)
    y = rng.normal(0.0, 0.1, (8, 1)) * 0.3  # scatter well within the stated 0.1
    assert paule_mandel(y, v) == 0.0
    assert paule_mandel(np.array([[1.0, 2.0]]), np.array([0.1])) == 0.0  # one: nothing to see


def test_coverage_of_the_random_effects_mean_over_seeds() -> None:
    """Measurements off by a shared unknown spread (0.1) while claiming 0.001-0.02: the
    mean weighted by ``1/(v + τ²)`` with variance ``1/Σw`` covers the truth, where
    ``1/v`` weights scaled by the Birge ratio do not (the smallest claim takes the mean)."""
    rng = np.random.default_rng(5)
    z_re, z_birge = [], []
    for _ in range(2000):
        n = 4
        v = rng.uniform(0.001, 0.02, n) ** 2
        y = rng.normal(0.0, 0.1, (n, 2)) + rng.normal(0.0, np.sqrt(v)[:, None], (n, 2))
        w = 1.0 / (v + paule_mandel(y, v))
        z_re.append((w @ y / w.sum()) / np.sqrt(1.0 / w.sum()))
        w0 = 1.0 / v
        mean0 = w0 @ y / w0.sum()
        chi2 = float(np.sum(w0 * np.sum((y - mean0) ** 2, axis=1))) / (2 * (n - 1))
        z_birge.append(mean0 / np.sqrt(max(chi2, 1.0) / w0.sum()))
    z_re_a, z_birge_a = np.concatenate(z_re), np.concatenate(z_birge)
    assert 0.62 < np.mean(np.abs(z_re_a) <= 1) < 0.80
    assert np.mean(np.abs(z_re_a) <= 3) > 0.97
    assert np.mean(np.abs(z_birge_a) <= 1) < 0.55  # what the weighting fixes


def test_bad_variances_are_refused() -> None:
    with pytest.raises(ValueError, match="positive variance"):
        paule_mandel(np.zeros((3, 2)), np.array([1.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="positive variance"):
        paule_mandel(np.zeros((3, 2)), np.ones(2))
