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
    Costs equal to :data:`TIE_DIGITS` significant digits are ties: equally spaced values
    (micro-images on a lattice) then cluster the same wherever the line's origin lies,
    not by the rounding of each cost.
    """
    distinct, inverse = np.unique(values, return_inverse=True)
    per_value = np.bincount(inverse, minlength=distinct.size).astype(np.float64)
    sums = _Sums(per_value.tolist(), (per_value * (distinct - distinct[0])).tolist())
    alive = _join_cheapest(sums, max_groups)
    _join_small(sums, alive, min_size)
    owner = np.cumsum(alive) - 1  # cluster of each distinct value
    return np.asarray(owner[inverse], dtype=np.int64)


TIE_DIGITS = 9
"""Significant digits to which two joining costs are compared."""


class _Sums:
    """Per cluster, keyed by its first entry: the count ``n`` and the sum ``s1`` of the
    values (from the smallest value)."""

    def __init__(self, n: list[float], s1: list[float]) -> None:
        self.n, self.s1 = n, s1

    def cost(self, a: int, b: int) -> float:
        """Ward's cost of joining clusters ``a`` and ``b``, the growth of the spread
        ``n_a·n_b/(n_a + n_b)·(mean_b - mean_a)²``, to :data:`TIE_DIGITS` digits."""
        n, s1 = self.n, self.s1
        gap = s1[b] / n[b] - s1[a] / n[a]
        cost = n[a] * n[b] / (n[a] + n[b]) * gap * gap
        return float(f"{cost:.{TIE_DIGITS}g}")

    def join(self, a: int, b: int) -> None:
        """Cluster ``b`` into ``a``."""
        self.n[a] += self.n[b]
        self.s1[a] += self.s1[b]


def _join_cheapest(sums: _Sums, max_groups: int) -> list[bool]:
    """Join neighbouring clusters (in order of value) the cheapest pair first until at most
    ``max_groups`` are left; returns which entries still start a cluster. A heap of the
    pairs' costs keyed by their left cluster, stale entries skipped: each join changes only
    its two neighbouring pairs' costs."""
    size = len(sums.n)
    right = list(range(1, size + 1))  # the next cluster's first entry (size: none)
    left = list(range(-1, size - 1))
    version = [0] * size
    alive = [True] * size
    heap = [(sums.cost(a, a + 1), a, 0, 0) for a in range(size - 1)]
    heapq.heapify(heap)
    count = size
    while count > max_groups and heap:
        _, a, va, vb = heapq.heappop(heap)
        b = right[a]
        if not alive[a] or b >= size or version[a] != va or version[b] != vb:
            continue
        sums.join(a, b)
        alive[b] = False
        right[a] = right[b]
        if right[a] < size:
            left[right[a]] = a
        version[a] += 1
        count -= 1
        if left[a] >= 0:
            p = left[a]
            heapq.heappush(heap, (sums.cost(p, a), p, version[p], version[a]))
        if right[a] < size:
            q = right[a]
            heapq.heappush(heap, (sums.cost(a, q), a, version[a], version[q]))
    return alive


def _join_small(sums: _Sums, alive: list[bool], min_size: int) -> None:
    """Join each cluster smaller than ``min_size`` (the leftmost first) to the cheaper of its
    two neighbours (the left one on a tie), while there are two clusters or more."""
    ids = [i for i, a in enumerate(alive) if a]
    while len(ids) > 1 and min(sums.n[i] for i in ids) < min_size:
        small = next(j for j, i in enumerate(ids) if sums.n[i] < min_size)
        pairs = [j for j in (small - 1, small) if 0 <= j < len(ids) - 1]
        k = min(pairs, key=lambda j: sums.cost(ids[j], ids[j + 1]))
        sums.join(ids[k], ids[k + 1])
        alive[ids[k + 1]] = False
        del ids[k + 1]
