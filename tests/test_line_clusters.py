"""Clusters of values on a line (:func:`calibration.line_clusters.cluster_on_line`)."""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_array_equal

from calibration.line_clusters import cluster_on_line


def test_separated_groups_are_found_whole_and_labelled_in_order() -> None:
    rng = np.random.default_rng(1)
    centres = np.array([-100.0, -20.0, 50.0])
    truth = rng.integers(0, 3, size=300)
    values = centres[truth] + rng.normal(0.0, 2.0, size=300)
    labels = cluster_on_line(values, max_groups=3, min_size=8)
    assert_array_equal(labels, truth)


def test_equal_values_share_a_cluster_and_the_count_is_capped() -> None:
    values = np.repeat(np.arange(20, dtype=np.float64), 10)
    labels = cluster_on_line(values, max_groups=6, min_size=8)
    assert np.unique(labels).size == 6
    for v in range(20):
        assert np.unique(labels[values == v]).size == 1
    assert np.all(np.diff(labels) >= 0)  # clusters of neighbouring values


def test_a_small_cluster_joins_its_cheaper_neighbour() -> None:
    # 3 entries at 10.5 (too few) between a group at 0 and one at 100: they join the near one
    values = np.concatenate([np.zeros(20), np.full(3, 10.5), np.full(20, 100.0)])
    labels = cluster_on_line(values, max_groups=6, min_size=8)
    assert_array_equal(labels, np.repeat([0, 0, 1], [20, 3, 20]))


def test_the_cheapest_pair_joins_first_and_the_leftmost_on_a_tie() -> None:
    # gaps 1, 1, 1, 5, 1: the three unit gaps tie (equal weights), so they join from the
    # left; a cost recomputed only where a join happened must still see the merged
    # cluster's larger cost (2 entries + 1 costs more than 1 + 1)
    values = np.array([0.0, 1.0, 2.0, 3.0, 8.0, 9.0])
    assert_array_equal(cluster_on_line(values, max_groups=5, min_size=1), [0, 0, 1, 2, 3, 4])
    assert_array_equal(cluster_on_line(values, max_groups=3, min_size=1), [0, 0, 1, 1, 2, 2])
    assert_array_equal(cluster_on_line(values, max_groups=2, min_size=1), [0, 0, 0, 0, 1, 1])


def test_equally_spaced_values_cluster_the_same_wherever_the_origin_lies() -> None:
    """Levers of micro-images on a lattice are equally spaced with equal counts, so many
    joining costs tie; the clusters were decided by each cost's rounding, which moves
    with the values' origin (the weighted mean they are taken from): 200 origins gave 20
    different clusterings, of 4 to 6 clusters. Ties are now ties."""
    base = np.repeat(np.arange(12) * 0.37, 20)
    rng = np.random.default_rng(0)
    first = cluster_on_line(base, max_groups=6, min_size=30)
    for origin in rng.uniform(-50.0, 50.0, 200):
        assert_array_equal(cluster_on_line(base + origin, max_groups=6, min_size=30), first)
    assert np.unique(first).size == 6
