"""Clusters of values on a line: neighbours joined by Ward's criterion.

:func:`cluster_on_line` serves :func:`calibration.edge_spread.frame_esf`, which bins a
corner's profiles also in groups of neighbouring levers (:class:`~calibration.edge_spread.LeverGroup`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def cluster_on_line(
    values: NDArray[np.float64], *, max_groups: int, min_size: int
) -> NDArray[np.int64]:
    """Label (0, 1, ... in increasing order of value) of every entry of ``values``: at most
    ``max_groups`` clusters of neighbouring values, each of at least ``min_size`` entries
    where possible.

    Equal values share a cluster. The distinct values start as one cluster each and are
    joined pairwise, neighbours only, the pair whose joining least increases the spread
    within clusters first (Ward's criterion on a line), so a cluster never spans a gap
    between others; once there are few enough clusters, only those smaller than
    ``min_size`` are joined, each to the cheaper of its two neighbours.
    """
    distinct, inverse = np.unique(values, return_inverse=True)
    owner = np.arange(distinct.size)  # cluster of each distinct value
    per_value = np.bincount(inverse, minlength=distinct.size).astype(np.float64)
    n = np.bincount(owner, per_value)
    s1 = np.bincount(owner, per_value * distinct)
    s2 = np.bincount(owner, per_value * distinct * distinct)
    while n.size > 1 and (n.size > max_groups or n.min() < min_size):
        within = s2 - s1 * s1 / n
        joined = s2[:-1] + s2[1:] - (s1[:-1] + s1[1:]) ** 2 / (n[:-1] + n[1:])
        costs = joined - within[:-1] - within[1:]
        small = np.flatnonzero(n < min_size)
        if n.size <= max_groups and small.size:  # only the small ones must join
            pairs = [j for j in (small[0] - 1, small[0]) if 0 <= j < n.size - 1]
            k = min(pairs, key=lambda j: costs[j])
        else:
            k = int(np.argmin(costs))
        for arr in (n, s1, s2):
            arr[k] += arr[k + 1]
        n, s1, s2 = (np.delete(arr, k + 1) for arr in (n, s1, s2))
        owner = np.where(owner > k, owner - 1, owner)
    return np.asarray(owner[inverse], dtype=np.int64)
