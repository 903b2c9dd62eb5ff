"""Clusters of values on a line: neighbours joined by Ward's criterion.

:func:`cluster_on_line` serves :func:`calibration.edge_spread.frame_esf`, which bins a
corner's profiles also in groups of neighbouring levers (:class:`~calibration.edge_spread.LeverGroup`).
"""

from __future__ import annotations

import heapq

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
    within clusters first (Ward's criterion on a line; on a tie the leftmost pair), so a
    cluster never spans a gap between others; once there are few enough clusters, only
    those smaller than ``min_size`` are joined, each to the cheaper of its two neighbours.
    """
    distinct, inverse = np.unique(values, return_inverse=True)
    per_value = np.bincount(inverse, minlength=distinct.size).astype(np.float64)
    first = _join_cheapest(
        per_value.tolist(),
        (per_value * distinct).tolist(),
        (per_value * distinct * distinct).tolist(),
        max_groups,
    )
    owner = np.cumsum(first) - 1  # cluster of each distinct value
    n = np.bincount(owner, per_value)
    s1 = np.bincount(owner, per_value * distinct)
    s2 = np.bincount(owner, per_value * distinct * distinct)
    while n.size > 1 and n.min() < min_size:  # few enough: only the small ones join
        within = s2 - s1 * s1 / n
        joined = s2[:-1] + s2[1:] - (s1[:-1] + s1[1:]) ** 2 / (n[:-1] + n[1:])
        costs = joined - within[:-1] - within[1:]
        small = int(np.flatnonzero(n < min_size)[0])
        pairs = [j for j in (small - 1, small) if 0 <= j < n.size - 1]
        k = min(pairs, key=lambda j: costs[j])
        for arr in (n, s1, s2):
            arr[k] += arr[k + 1]
        n, s1, s2 = (np.delete(arr, k + 1) for arr in (n, s1, s2))
        owner = np.where(owner > k, owner - 1, owner)
    return np.asarray(owner[inverse], dtype=np.int64)


def _join_cheapest(
    n: list[float], s1: list[float], s2: list[float], max_groups: int
) -> NDArray[np.bool_]:
    """Join neighbouring clusters (counts ``n``, sums ``s1`` and ``s2`` of the values and
    their squares, in order of value) the cheapest pair first until at most ``max_groups``
    are left; returns which entries start a cluster. A heap of the pairs' costs keyed by
    their left cluster, stale entries skipped: each join changes only its two neighbouring
    pairs' costs."""
    size = len(n)
    right = list(range(1, size + 1))  # the next cluster's first entry (size: none)
    left = list(range(-1, size - 1))
    version = [0] * size
    alive = [True] * size

    def cost(a: int, b: int) -> float:
        within_a = s2[a] - s1[a] * s1[a] / n[a]
        within_b = s2[b] - s1[b] * s1[b] / n[b]
        total = s1[a] + s1[b]
        joined = s2[a] + s2[b] - total * total / (n[a] + n[b])
        return joined - within_a - within_b

    heap = [(cost(a, a + 1), a, 0, 0) for a in range(size - 1)]
    heapq.heapify(heap)
    count = size
    while count > max_groups and heap:
        c, a, va, vb = heapq.heappop(heap)
        b = right[a]
        if not alive[a] or b >= size or version[a] != va or version[b] != vb:
            continue
        n[a] += n[b]
        s1[a] += s1[b]
        s2[a] += s2[b]
        alive[b] = False
        right[a] = right[b]
        if right[a] < size:
            left[right[a]] = a
        version[a] += 1
        count -= 1
        if left[a] >= 0:
            p = left[a]
            heapq.heappush(heap, (cost(p, a), p, version[p], version[a]))
        if right[a] < size:
            q = right[a]
            heapq.heappush(heap, (cost(a, q), a, version[a], version[q]))
    return np.array(alive, dtype=bool)
