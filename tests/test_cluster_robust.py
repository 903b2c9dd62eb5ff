"""The cluster-robust covariance's middle (:func:`calibration.cluster_robust.clustered_meat`)."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_allclose

from calibration.cluster_robust import clustered_meat


def test_sums_per_cluster_and_small_sample_factor() -> None:
    scores = np.array([[1.0, 2.0], [3.0, -1.0], [0.5, 0.5], [-2.0, 4.0], [1.0, 1.0]])
    cluster = np.array([0, 0, 2, 4, 4])  # numbers 1 and 3 unused
    sums = np.array([[4.0, 1.0], [0.5, 0.5], [-1.0, 5.0]])
    expected = sums.T @ sums
    assert_allclose(clustered_meat(scores, cluster, parameters_lost=1), expected * 3 / 2)
    assert_allclose(clustered_meat(scores, cluster, parameters_lost=2), expected * 3 / 1)
    # one sample per cluster: the heteroscedasticity-robust middle
    single = clustered_meat(scores, np.arange(5), parameters_lost=0)
    assert_allclose(single, scores.T @ scores)


def test_the_sandwich_holds_errors_shared_within_clusters() -> None:
    """A straight-line fit whose samples share an error per cluster (and whose abscissae
    cluster too): over 400 seeds the sandwich's standard error of the slope matches the
    slope's actual scatter, where the independent-samples one is several times too small."""
    rng = np.random.default_rng(0)
    n_clusters, per = 30, 25
    cluster = np.repeat(np.arange(n_clusters), per)
    slopes, robust, naive = [], [], []
    for _ in range(400):
        x = rng.normal(0.0, 1.0, n_clusters)[cluster] + rng.normal(0.0, 0.3, cluster.size)
        shared = rng.normal(0.0, 1.0, n_clusters)[cluster] * (1.0 + 0.5 * x)
        y = 2.0 + 0.7 * x + shared + rng.normal(0.0, 0.2, cluster.size)
        design = np.column_stack([np.ones_like(x), x])
        bread = np.linalg.inv(design.T @ design)
        coef = bread @ design.T @ y
        resid = y - design @ coef
        meat = clustered_meat(design * resid[:, None], cluster, parameters_lost=2)
        slopes.append(coef[1])
        robust.append(np.sqrt((bread @ meat @ bread)[1, 1]))
        naive.append(np.sqrt(bread[1, 1] * resid @ resid / (resid.size - 2)))
    actual = float(np.std(slopes))
    assert abs(float(np.mean(slopes)) - 0.7) < 3 * actual / np.sqrt(400)
    assert 0.85 < float(np.sqrt(np.mean(np.square(robust)))) / actual < 1.15
    assert float(np.sqrt(np.mean(np.square(naive)))) / actual < 0.4
