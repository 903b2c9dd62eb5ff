"""Weighted bin means of an edge's samples, each with its standard error, and weighted means by group.

The samples of many profiles of an edge (positions ``x`` in pixels from the edge, dark
side negative; normalised values, 0 dark and 1 light; weights) are pooled into bins of a
fixed width over ``[-half_px, half_px)``. Within a bin the values also change with the
position (the edge's slope): the scatter that gives a bin's standard error is taken
about the bin's weighted straight line, not its mean, so a steep edge's bins do not claim
the slope as noise. Used for a frame's edge-spread function
(:mod:`calibration.edge_spread`) and for the half-edges' functions whose centroids
centre them (:mod:`calibration.edge_centres`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

MIN_BIN_SAMPLES = 3
"""Fewest samples a bin must hold to be kept: its standard error removes the slope within
the bin (two parameters) from the samples' scatter."""


@dataclass(frozen=True)
class BinMeans:
    """Per kept bin, ascending: ``x`` the weighted mean position (px), ``value`` the
    weighted mean value, ``se`` its standard error, ``count`` the samples, ``weight`` the
    summed weights and ``x_sd`` the weighted standard deviation of the positions (px)."""

    x: NDArray[np.float64]
    value: NDArray[np.float64]
    se: NDArray[np.float64]
    count: NDArray[np.int64]
    weight: NDArray[np.float64]
    x_sd: NDArray[np.float64]


def bin_means(
    x: NDArray[np.float64],
    value: NDArray[np.float64],
    weight: NDArray[np.float64],
    *,
    bin_px: float,
    half_px: float,
) -> BinMeans:
    """Weighted means of ``value`` in bins of ``bin_px`` over ``[-half_px, half_px)``.

    ``x``, ``value`` and ``weight`` are flat arrays of the same length (samples with a
    non-finite value are left out). A bin is kept when it holds at least
    ``MIN_BIN_SAMPLES`` samples. Its standard error is that of a weighted mean from the
    residuals ``r`` about the bin's weighted line in ``x``: ``√(Σw²r²/(Σw)² · n/(n - 2))``,
    right whether the weights are the samples' inverse variances (a profile's weight is
    its contrast squared) or not.
    """
    n_bins = int(round(2.0 * half_px / bin_px))
    idx = np.floor((x + half_px) / bin_px).astype(np.int64)
    inside = (idx >= 0) & (idx < n_bins) & np.isfinite(value)
    idx, xs, zs, ws = idx[inside], x[inside], value[inside], weight[inside]
    count = np.bincount(idx, minlength=n_bins)
    sw = np.bincount(idx, ws, n_bins)
    swx = np.bincount(idx, ws * xs, n_bins)
    swz = np.bincount(idx, ws * zs, n_bins)
    keep = count >= MIN_BIN_SAMPLES
    safe = np.maximum(sw, 1e-300)
    # weighted scatter about the bin mean, after removing the slope within the bin
    dev = zs - (swz / safe)[idx]
    dx = xs - (swx / safe)[idx]
    sdx = np.bincount(idx, ws * dx * dx, n_bins)
    sdz = np.bincount(idx, ws * dx * dev, n_bins)
    slope = np.where(sdx > 0, sdz / np.maximum(sdx, 1e-300), 0.0)
    resid = dev - slope[idx] * dx
    # the weighted mean's variance Σw²r²/(Σw)² (sandwich: right whether the weights are
    # inverse variances or not), n/(n-2) for the line's two parameters
    spread = np.bincount(idx, ws * ws * resid * resid, n_bins) / np.maximum(sw * sw, 1e-300)
    se = np.sqrt(spread * count / np.maximum(count - 2, 1))
    return BinMeans(
        x=swx[keep] / sw[keep],
        value=swz[keep] / sw[keep],
        se=se[keep],
        count=count[keep].astype(np.int64),
        weight=np.asarray(sw[keep], dtype=np.float64),
        x_sd=np.sqrt(sdx[keep] / sw[keep]),
    )


def group_means(
    values: NDArray[np.float64], weights: NDArray[np.float64], label: NDArray[np.int64]
) -> NDArray[np.float64]:
    """Per entry of ``values`` (``(P,)`` or rows of ``(P, k)``), the ``weights``-weighted mean
    of the entries with its ``label``, in the shape of ``values`` (0 for a group without
    weight)."""
    columns = values.reshape(values.shape[0], -1)
    _, index = np.unique(label, return_inverse=True)
    groups = int(index.max()) + 1
    total = np.bincount(index, weights=weights, minlength=groups)
    sums = np.stack(
        [np.bincount(index, weights=weights * column, minlength=groups) for column in columns.T],
        axis=1,
    )
    means = np.divide(sums, total[:, None], out=np.zeros_like(sums), where=total[:, None] > 0)
    return np.asarray(means[index], dtype=np.float64).reshape(values.shape)
