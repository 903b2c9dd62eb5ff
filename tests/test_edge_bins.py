"""Bin means of an edge's samples (calibration.edge_bins) against known functions.

The bins' means, positions and standard errors are checked against samples drawn from a
known line with known noise: the mean at the bin's weighted mean position is the line
there, and the stated standard errors describe the means' scatter over many draws, also
where the line is steep within a bin (the slope is not noise).
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from calibration.edge_bins import MIN_BIN_SAMPLES, bin_means


def test_the_means_lie_on_a_line_at_the_bins_weighted_positions() -> None:
    rng = np.random.default_rng(3)
    x = rng.uniform(-1.0, 1.0, 4000)
    weight = rng.uniform(0.2, 2.0, x.size)
    value = 0.3 + 0.7 * x  # exact, no noise
    bins = bin_means(x, value, weight, bin_px=0.1, half_px=1.0)
    assert bins.x.size == 20
    assert_allclose(bins.value, 0.3 + 0.7 * bins.x, atol=1e-12)
    assert_allclose(bins.se, 0.0, atol=1e-12)  # the slope within a bin is not scatter
    # the weighted mean position, not the plain mean
    first = (x >= -1.0) & (x < -0.9)
    assert_allclose(bins.x[0], np.sum(weight[first] * x[first]) / np.sum(weight[first]))
    assert_allclose(bins.weight[0], np.sum(weight[first]))
    assert bins.count[0] == int(first.sum())


def test_samples_outside_the_range_or_not_finite_are_left_out() -> None:
    x = np.array([-2.0, -0.95, -0.95, -0.95, 0.05, 0.05, 0.05, 0.05, 1.0, 3.0])
    value = np.array([9.0, 1.0, 1.0, 1.0, 2.0, 2.0, np.nan, 2.0, 9.0, 9.0])
    bins = bin_means(x, value, np.ones_like(x), bin_px=0.1, half_px=1.0)
    assert_allclose(bins.x, [-0.95, 0.05])
    assert_allclose(bins.value, [1.0, 2.0])
    assert_array_equal(bins.count, [3, 3])


def test_bins_with_too_few_samples_are_dropped() -> None:
    x = np.array([0.01, 0.02, 0.11, 0.12, 0.13])
    bins = bin_means(x, np.ones_like(x), np.ones_like(x), bin_px=0.1, half_px=1.0)
    assert MIN_BIN_SAMPLES == 3
    assert_allclose(bins.x, [0.12])


@pytest.mark.parametrize("inverse_variance", [True, False])
def test_standard_errors_describe_the_scatter_of_the_means_on_a_steep_edge(
    inverse_variance: bool,
) -> None:
    rng = np.random.default_rng(11)
    n_draws, n_samples, noise = 2000, 600, 0.02
    x = rng.uniform(-0.5, 0.5, n_samples)  # fixed positions; 10 bins of 0.1 px
    weight = rng.uniform(0.5, 1.5, n_samples)
    truth = 0.5 + 0.5 * np.tanh(4.0 * x)  # slope up to 2 per px: 0.2 across a bin
    # the weights the samples' inverse variances, or unrelated to their equal noise
    sigma = noise / np.sqrt(weight) if inverse_variance else np.full(n_samples, noise)
    means, ses = [], []
    for _ in range(n_draws):
        bins = bin_means(
            x, truth + sigma * rng.standard_normal(n_samples), weight, bin_px=0.1, half_px=0.5
        )
        means.append(bins.value)
        ses.append(bins.se)
    spread = np.std(np.array(means), axis=0)
    claimed = np.sqrt(np.mean(np.array(ses) ** 2, axis=0))
    # 2000 draws: the spread is known to ~1.6 %; the claim within 5 % in every bin
    assert_allclose(claimed / spread, 1.0, atol=0.05)
