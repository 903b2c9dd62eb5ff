"""Per-micro-image centres of a white image: patches, background, thresholds, centroids.

Step 2 of :func:`calibration.mla_grid.fit_mla_grid` (see its module docstring for the
method): each micro-image is cut out as a square patch around its predicted centre,
the dark gaps' level is subtracted, a plane fitted to the flat top models the
vignetting gradient, and the centre is the centroid of the clipped, normalised
intensity inside the circle of radius ``pitch/2``. Also the radial profile of the
discs, the thresholds read off it (plateau radius, centroid ramp, half-maximum
radius) and the flat-top non-uniformity that screens out board frames.

Conventions as in :mod:`calibration.mla_grid`: positions ``(x, y)`` in pixels, pixel
centres at integers, arrays indexed ``[y, x]``. Vectorized over micro-images (chunks
of ``_CHUNK_LENSES`` on an optional thread pool).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from .mla_spectrum import Lattice

_CHUNK_LENSES = 256
"""Micro-images measured per work item."""


@dataclass(frozen=True)
class CentroidParams:
    """Measurement settings shared by every patch."""

    half: int  # patch half-width (px); patches are (2·half+1)²
    pitch: float
    background: float
    noise: float
    plateau_radius: float
    lo: float
    hi: float


@dataclass
class MeasuredCentres:
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    level: NDArray[np.float64]  # background-subtracted plateau level at the centre
    spread: NDArray[np.float64]  # flat-top non-uniformity (block_spread), NaN if not computed
    # lit area: sum of the clipped, normalised intensity (px²), NaN if unlit
    area: NDArray[np.float64]


def gather_patches(
    img: NDArray[Any], xi: NDArray[np.int64], yi: NDArray[np.int64], half: int
) -> NDArray[np.float32]:
    """Square patches of side ``2·half+1`` centred on integer pixels ``(xi, yi)``, as float32."""
    n = 2 * half + 1
    view = sliding_window_view(img, (n, n))
    return view[yi - half, xi - half].astype(np.float32)


@dataclass(frozen=True)
class _Kernels:
    """Linear operators on flattened ``(2·half+1)²`` patches (local integer coordinates ``u, v``)."""

    u: NDArray[np.float32]  # (P,) local coordinate -half..half
    plane_op: NDArray[np.float32]  # (P², 3): least-squares plane c0 + gx·u + gy·v on the plateau
    moments: NDArray[np.float32]  # (P², 3): window · [1, u, v]


def _kernels(prm: CentroidParams) -> _Kernels:
    half = prm.half
    u = np.arange(-half, half + 1, dtype=np.float64)
    uu, vv = np.meshgrid(u, u, indexing="xy")
    r2 = (uu**2 + vv**2).ravel()
    plateau_idx = np.nonzero(r2 <= prm.plateau_radius**2)[0]
    design = np.stack(
        [np.ones(plateau_idx.size), uu.ravel()[plateau_idx], vv.ravel()[plateau_idx]], axis=1
    )
    plane_op = np.zeros((r2.size, 3))
    plane_op[plateau_idx] = np.linalg.pinv(design).T
    window = (r2 <= (0.5 * prm.pitch - 0.5) ** 2).astype(np.float64)
    moments = np.stack([window, window * uu.ravel(), window * vv.ravel()], axis=1)
    return _Kernels(
        u.astype(np.float32),
        plane_op.astype(np.float32),
        moments.astype(np.float32),
    )


def _measure_chunk(
    img: NDArray[Any],
    xp: NDArray[np.float64],
    yp: NDArray[np.float64],
    prm: CentroidParams,
    ker: _Kernels,
    flatness: bool,
) -> MeasuredCentres:
    """Centres of the micro-images predicted at ``(xp, yp)`` (see the module docstring).

    The centroid window is the circle of radius ``pitch/2 - 0.5`` about the
    nearest integer pixel; the ramp thresholds keep the weights zero near it.
    """
    n = xp.size
    xi = np.rint(xp).astype(np.int64)
    yi = np.rint(yp).astype(np.int64)
    patch = gather_patches(img, xi, yi, prm.half)
    patch -= np.float32(prm.background)
    flat = patch.reshape(n, -1)
    coef = (flat @ ker.plane_op).astype(np.float64)  # (n, 3): level, d/du, d/dv
    level = coef[:, 0]
    if flatness:
        spread = block_spread(patch, level, prm.pitch)
    else:
        spread = np.full(n, np.nan)
    ok = level > max(5.0 * prm.noise, 1e-12)
    safe = np.where(ok, level, 1.0)
    u = ker.u
    gx = (coef[:, 1] / safe).astype(np.float32)[:, None, None]
    gy = (coef[:, 2] / safe).astype(np.float32)[:, None, None]
    plane = gx * u[None, None, :] + gy * u[None, :, None]
    plane += np.float32(1.0)
    plane *= (safe * (prm.hi - prm.lo)).astype(np.float32)[:, None, None]
    patch /= plane  # J / (hi - lo)
    del plane
    patch -= np.float32(prm.lo / (prm.hi - prm.lo))
    np.maximum(patch, np.float32(0.0), out=patch)
    np.minimum(patch, np.float32(1.0), out=patch)
    mom = (flat @ ker.moments).astype(np.float64)
    good = ok & (mom[:, 0] > 0)
    wsum = np.where(good, mom[:, 0], 1.0)
    x = np.where(good, xi + mom[:, 1] / wsum, np.nan)
    y = np.where(good, yi + mom[:, 2] / wsum, np.nan)
    area = np.where(good, mom[:, 0], np.nan)
    level = np.where(np.isfinite(level), level, 0.0)
    return MeasuredCentres(x, y, level, spread, area)


def measure_centres(
    img: NDArray[Any],
    xp: NDArray[np.float64],
    yp: NDArray[np.float64],
    prm: CentroidParams,
    pool: ThreadPoolExecutor | None,
    *,
    flatness: bool = False,
) -> MeasuredCentres:
    ker = _kernels(prm)
    bounds = [(k, min(k + _CHUNK_LENSES, xp.size)) for k in range(0, xp.size, _CHUNK_LENSES)]

    def work(b: tuple[int, int]) -> MeasuredCentres:
        return _measure_chunk(img, xp[b[0] : b[1]], yp[b[0] : b[1]], prm, ker, flatness)

    parts = list(pool.map(work, bounds)) if pool is not None else [work(b) for b in bounds]
    return MeasuredCentres(
        np.concatenate([p.x for p in parts]),
        np.concatenate([p.y for p in parts]),
        np.concatenate([p.level for p in parts]),
        np.concatenate([p.spread for p in parts]),
        np.concatenate([p.area for p in parts]),
    )


def local_radius(
    xp: NDArray[np.float64], yp: NDArray[np.float64], half: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float32]]:
    """Integer patch centres and each patch pixel's distance from its sub-pixel centre."""
    xi = np.rint(xp).astype(np.int64)
    yi = np.rint(yp).astype(np.int64)
    u = np.arange(-half, half + 1, dtype=np.float32)
    du = u[None, None, :] - (xp - xi).astype(np.float32)[:, None, None]
    dv = u[None, :, None] - (yp - yi).astype(np.float32)[:, None, None]
    return xi, yi, np.sqrt(du * du + dv * dv)


def central_stats(
    patch: NDArray[np.float32], r: NDArray[np.float32], pitch: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per background-subtracted patch: mean level within ``0.15·pitch`` and :func:`block_spread`."""
    centre = r <= 0.15 * pitch
    level = (patch * centre).sum(axis=(1, 2), dtype=np.float64) / np.maximum(
        centre.sum(axis=(1, 2)), 1
    )
    return level, block_spread(patch, level, pitch)


def block_spread(
    patch: NDArray[np.float32], level: NDArray[np.float64], pitch: float
) -> NDArray[np.float64]:
    """Non-uniformity of each micro-image's flat top, insensitive to pixel noise and gradients.

    The central square (side ≈ 0.4·pitch) is split into 4×4 blocks; the block
    means minus their best-fit plane, RMS, divided by ``level``. A white image
    gives a few 0.1 %; edges or texture inside the disc give tens of %.
    """
    n, p, _ = patch.shape
    half = p // 2
    s = max(2, int(0.1 * pitch))
    sq = patch[:, half - 2 * s : half + 2 * s, half - 2 * s : half + 2 * s]
    blocks = sq.reshape(n, 4, s, 4, s).mean(axis=(2, 4), dtype=np.float64).reshape(n, 16)
    c = np.arange(4.0) - 1.5
    by, bx = np.meshgrid(c, c, indexing="ij")
    design = np.stack([np.ones(16), bx.ravel(), by.ravel()], axis=1)
    resid = blocks - blocks @ (design @ np.linalg.pinv(design)).T
    return np.sqrt(np.mean(resid**2, axis=1)) / np.maximum(np.abs(level), 1e-12)


def radial_profile(
    patch: NDArray[np.float32],
    r: NDArray[np.float32],
    level: NDArray[np.float64],
    pitch: float,
    bin_px: float = 0.5,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean profile ``J(r)`` of background-subtracted patches divided by their level, ``r ≤ pitch/2``."""
    if level.size == 0:
        raise ValueError("not a white (flat-field) image: no lit micro-images")
    j = patch / level.astype(np.float32)[:, None, None]
    sel = r <= 0.5 * pitch
    b = (r[sel] / bin_px).astype(np.int64)
    prof = np.bincount(b, j[sel]) / np.maximum(np.bincount(b), 1)
    radii = (np.arange(prof.size, dtype=np.float64) + 0.5) * bin_px
    return radii, prof


def background_level(
    img: NDArray[Any], xp: NDArray[np.float64], yp: NDArray[np.float64], half: int, pitch: float
) -> tuple[float, float]:
    """Level and noise (robust σ) of the dark gaps: pixels ≥ 0.64·pitch from the centres."""
    xi, yi, r = local_radius(xp, yp, half)
    patch = gather_patches(img, xi, yi, half)
    vals = patch[r >= 0.64 * pitch].astype(np.float64)
    if vals.size < 16:
        raise ValueError(
            "white image: no dark gaps between micro-images to estimate the black level"
        )
    med = float(np.median(vals))
    noise = 1.4826 * float(np.median(np.abs(vals - med)))
    return med, max(noise, 1e-6)


def thresholds(
    radii: NDArray[np.float64], prof: NDArray[np.float64], pitch: float
) -> tuple[float, float, float, float]:
    """Plateau radius, centroid ramp ``lo``/``hi`` and the half-maximum disc radius."""
    r_half = half_radius(radii, prof)
    if not math.isfinite(r_half):
        raise ValueError(
            "white image: the micro-images do not fall to half their brightness within half a "
            "pitch (no dark gaps between the discs, or dark disc centres)"
        )
    under90 = np.nonzero(prof < 0.9)[0]
    r90 = float(radii[under90[0]]) if under90.size else r_half
    plateau = float(np.clip(0.85 * r90, 0.12 * pitch, 0.4 * pitch))
    edge = prof[radii >= 0.5 * pitch - 1.5]
    j_edge = float(edge.max()) if edge.size else 0.0
    lo = float(np.clip(j_edge + 0.15, 0.4, 0.8))
    hi = min(0.95, lo + 0.35)
    return plateau, lo, hi, r_half


def radial_profile_normalized(
    img: NDArray[Any],
    lat: Lattice,
    ii: NDArray[np.int64],
    jj: NDArray[np.int64],
    prm: CentroidParams,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Profile of ≤ 64 used lenses spread over the sensor, in 0.25 px bins."""
    x, y = lat.centre(ii, jj)
    if x.size > 64:
        pick = np.linspace(0, x.size - 1, 64).astype(np.int64)
        x, y = x[pick], y[pick]
    xi, yi, r = local_radius(x, y, prm.half)
    patch = gather_patches(img, xi, yi, prm.half)
    patch -= np.float32(prm.background)
    level, _ = central_stats(patch, r, prm.pitch)
    lit = level > 0
    return radial_profile(patch[lit], r[lit], level[lit], prm.pitch, bin_px=0.25)


def half_radius(radii: NDArray[np.float64], prof: NDArray[np.float64]) -> float:
    """Radius (px) where the profile first falls below 0.5 (linear interpolation); NaN if never."""
    below = np.nonzero(prof < 0.5)[0]
    if below.size == 0 or below[0] == 0:
        return float("nan")
    k = int(below[0])
    r0, r1, p0, p1 = radii[k - 1], radii[k], prof[k - 1], prof[k]
    return float(r0 + (p0 - 0.5) / (p0 - p1) * (r1 - r0))
