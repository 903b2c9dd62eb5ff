"""The middle of a cluster-robust (sandwich) covariance: scores summed per cluster.

A least-squares fit's parameter covariance taken as independent samples is too small
when samples share an error (the profiles of one micro-image move together with its
pixel-locked edge; the bins of one frame share its normalisation). The sandwich
``B·M·B``, with ``B`` the inverse normal matrix and ``M`` the sum over clusters of the
outer products of each cluster's summed score (``Jᵀ·r`` of its samples), holds whatever
the errors within a cluster share. Used by :mod:`calibration.edge_slope` (clusters:
micro-images) and :mod:`calibration.defocus_problem` (clusters: frames).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def clustered_meat(
    scores: NDArray[np.float64], cluster: NDArray[np.integer], *, parameters_lost: int
) -> NDArray[np.float64]:
    """``M = G/(G - parameters_lost) · Σ_g s_g·s_gᵀ``, ``s_g`` the sum of ``scores`` over cluster g.

    ``scores`` is ``(n, p)``: each sample's score (its Jacobian row times its weighted
    residual); ``cluster`` ``(n,)`` non-negative cluster numbers; ``G`` the number of
    clusters whose summed score is not zero (an empty number counts for nothing).
    ``parameters_lost`` sets the small-sample factor: the number of parameters the
    clusters' scores are not free of (1: the factor G/(G-1) of a jackknife; ``p``: that of
    a regression with ``p`` coefficients, for few clusters).
    """
    n_clusters = int(cluster.max()) + 1 if cluster.size else 0
    per = np.zeros((n_clusters, scores.shape[1]))
    for k in range(scores.shape[1]):
        per[:, k] = np.bincount(cluster, scores[:, k], minlength=n_clusters)
    used = int(np.count_nonzero(np.any(per != 0.0, axis=1)))
    return np.asarray(per.T @ per * (used / max(used - parameters_lost, 1)), dtype=np.float64)


__all__ = ["clustered_meat"]
