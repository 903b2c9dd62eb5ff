"""Edge-spread functions of one frame: the blur signal behind the focus plane.

Every well-resolved edge profile of a corner's micro-images (ESIF step 3) is a
sampled blurred step. Its samples are placed at their signed distance ``x``
from the edge (pixels; ``x < 0`` on the dark side), the edge position taken
from the block's straight-line fit (so the phase of each profile is known to
a few thousandths of a pixel), and normalised to the unit step:

    y = (1 + γ_k·x)·(B_p + C_p·E(x))

``B_p``, ``C_p``: dark level and contrast of profile ``p``; ``γ_k``: the
relative drift of both levels across the edge in block ``k`` (vignetting and
cos⁴ make the brightness change across a micro-image, and the change
multiplies dark and light alike).
``E`` is the frame's own edge-spread function, estimated from the data
(starting from the blurred-step fits and refined twice), so no blur shape is
imposed here. Pooling the profiles of every micro-image with their different
sub-pixel phases samples ``E`` far below the pixel: the result is binned in
``ESF_BIN_PX`` bins (mean position, weighted mean value and its standard
error per bin), a few hundred numbers per corner and frame, which is what the
whole-sweep defocus model (:mod:`calibration.defocus`) fits.

``E`` is the step convolved with everything that blurs the micro-image: the
pixel response (area or point sampling), the static blur (lens PSF,
diffraction, sensor) and the geometric defocus disk of OPTICS.md §1.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

ESF_HALF_PX = 6.0
"""Half width of the binned edge-spread function (pixels)."""

ESF_BIN_PX = 0.1
"""Bin width of the binned edge-spread function (pixels)."""

MAX_SHIFT_PX = 0.3
"""Largest shift of a block's edge position when aligning it to the frame's function (px)."""

MIN_PROFILES = 8
"""Fewest profiles for an edge-spread function of one corner in one frame."""


@dataclass
class EdgeProfiles:
    """Edge profiles of one corner in one frame, samples placed relative to their edge.

    ``x``: signed distance of each sample from the edge (pixels, dark side
    negative), shape ``(P, K)``; ``y``: the raw counts; ``block``: the edge
    block of each profile (profiles of one block share the drift terms).
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    block: NDArray[np.int64]

    @property
    def count(self) -> int:
        return int(self.x.shape[0])

    @staticmethod
    def concatenate(parts: Sequence[EdgeProfiles]) -> EdgeProfiles:
        """One set from many (block labels kept distinct)."""
        parts = [p for p in parts if p.count]
        if not parts:
            return EdgeProfiles(np.empty((0, 0)), np.empty((0, 0)), np.empty(0, dtype=np.int64))
        widths = {p.x.shape[1] for p in parts}
        if len(widths) != 1:
            raise ValueError(f"profiles of different lengths {sorted(widths)} cannot be pooled")
        blocks = []
        offset = 0
        for p in parts:
            blocks.append(p.block + offset)
            offset += int(p.block.max()) + 1 if p.block.size else 0
        return EdgeProfiles(
            np.concatenate([p.x for p in parts]),
            np.concatenate([p.y for p in parts]),
            np.concatenate(blocks),
        )


@dataclass(frozen=True)
class BinnedEsf:
    """The normalised edge-spread function of one corner in one frame.

    Per bin of ``ESF_BIN_PX``: ``x`` the mean position of its samples
    (pixels from the edge), ``value`` their weighted mean (0 dark, 1 light),
    ``se`` its standard error, ``count`` the number of samples. Bins without
    samples are dropped. ``profiles``: how many profiles were pooled.
    """

    x: NDArray[np.float64]
    value: NDArray[np.float64]
    se: NDArray[np.float64]
    count: NDArray[np.int64]
    profiles: int
    x_sd: NDArray[np.float64] | None = None

    @property
    def position_sd_px(self) -> NDArray[np.float64]:
        """Standard deviation of the sample positions within each bin (px).

        Profiles of a frame can share only a few sub-pixel phases (micro-images
        an integer number of pixels apart), so a bin may hold samples at one
        position or spread over its width: the model averages over this.
        """
        if self.x_sd is None:
            return np.full(self.x.shape, ESF_BIN_PX / np.sqrt(12.0))
        return self.x_sd

    def to_dict(self) -> dict[str, Any]:
        return {
            "x_px": np.round(self.x, 5).tolist(),
            "x_sd_px": np.round(self.position_sd_px, 5).tolist(),
            "value": np.round(self.value, 6).tolist(),
            "se": np.round(self.se, 7).tolist(),
            "count": self.count.tolist(),
            "profiles": self.profiles,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BinnedEsf:
        sd = data.get("x_sd_px")
        return cls(
            np.asarray(data["x_px"], dtype=np.float64),
            np.asarray(data["value"], dtype=np.float64),
            np.asarray(data["se"], dtype=np.float64),
            np.asarray(data["count"], dtype=np.int64),
            int(data["profiles"]),
            None if sd is None else np.asarray(sd, dtype=np.float64),
        )

    @staticmethod
    def merge(parts: Sequence[BinnedEsf]) -> BinnedEsf:
        """Inverse-variance weighted mean of functions binned on the same bins."""
        n_bins = int(round(2 * ESF_HALF_PX / ESF_BIN_PX))
        sw = np.zeros(n_bins)
        swx = np.zeros(n_bins)
        swxx = np.zeros(n_bins)
        swv = np.zeros(n_bins)
        count = np.zeros(n_bins, dtype=np.int64)
        for p in parts:
            b = np.clip(np.floor((p.x + ESF_HALF_PX) / ESF_BIN_PX).astype(np.int64), 0, n_bins - 1)
            w = 1.0 / np.maximum(p.se, 1e-6) ** 2
            np.add.at(sw, b, w)
            np.add.at(swx, b, w * p.x)
            np.add.at(swxx, b, w * (p.x**2 + p.position_sd_px**2))
            np.add.at(swv, b, w * p.value)
            np.add.at(count, b, p.count)
        keep = sw > 0
        mean = swx[keep] / sw[keep]
        return BinnedEsf(
            mean,
            swv[keep] / sw[keep],
            1.0 / np.sqrt(sw[keep]),
            count[keep],
            sum(p.profiles for p in parts),
            np.sqrt(np.maximum(swxx[keep] / sw[keep] - mean**2, 0.0)),
        )

    def spread_px(self, *, half_window_px: float = 3.0) -> float:
        """RMS width of the line-spread function within ``±half_window_px`` (pixels).

        A display quantity (the live focus plot): the second moment of the
        derivative of the binned function, ``sqrt(-2∫x(E - H)dx)`` over the
        window (``H`` the unit step), which grows with the defocus blur.
        """
        inside = np.abs(self.x) <= half_window_px
        if inside.sum() < 10:
            return float("nan")
        x, e = self.x[inside], self.value[inside]
        edges = np.concatenate([[-half_window_px], 0.5 * (x[1:] + x[:-1]), [half_window_px]])
        widths = np.diff(edges)
        deficit = e - (x > 0)
        var = -2.0 * float(np.sum(x * deficit * widths))
        return float(np.sqrt(var)) if var > 0 else 0.0


def _gaussian_step(width_px: float) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """Pixel-integrated Gaussian step of sigma ``width_px``: the starting shape."""
    sigma = float(np.sqrt(max(width_px, 0.05) ** 2 + 1.0 / 12.0))
    return lambda x: ndtr(x / sigma)


def _interpolator(
    esf: BinnedEsf,
) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
    """Linear interpolation of a binned function, clamped at its ends."""
    x, v = esf.x, esf.value
    return lambda q: np.interp(q, x, v)


def _normalise(
    prof: EdgeProfiles,
    esf: Callable[[NDArray[np.float64]], NDArray[np.float64]],
    *,
    iterations: int = 3,
    align: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``(x, z, C, rms)``: sample positions and values mapped to the unit step.

    Least squares of ``y = (1 + γ_k·x)·(B_p + C_p·E(x - δ_k))`` by
    Gauss–Newton, the per-profile level ``B_p`` and contrast ``C_p``
    eliminated in closed form (Schur complement), so each step solves a small
    system per block ``k`` for its drift ``γ_k`` and, with ``align``, its
    edge shift ``δ_k``. Aligning every block to ``E`` itself removes the
    pixel-locking of the blurred-step fits (their positions depend on the
    sampling phase when the edge is not Gaussian); the mean shift is held at
    zero (a shift common to all blocks is a shift of ``E``'s origin) and each
    shift is limited to ``MAX_SHIFT_PX``.
    """
    x, y, block = prof.x, prof.y, prof.block
    n_blocks = int(block.max()) + 1
    grid = np.arange(-ESF_HALF_PX - 1.0, ESF_HALF_PX + 1.0, 0.02)
    grid_slope = np.gradient(esf(grid), grid)

    def slope_of(q: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.interp(q, grid, grid_slope)

    gamma = np.zeros(n_blocks)
    delta = np.zeros(n_blocks)
    e = esf(x)
    b, c = _levels(y, np.ones_like(x), e)
    n_par = 2 if align else 1
    for _ in range(iterations):
        xs = x - delta[block][:, None]
        e = esf(xs)
        one = 1.0 + gamma[block][:, None] * x
        level = b[:, None] + c[:, None] * e
        r = y - one * level
        col_b, col_c = one, one * e
        extra = [x * level]
        if align:
            extra.append(-one * c[:, None] * slope_of(xs))
        aa, ab, bb = _dot(col_b, col_b), _dot(col_b, col_c), _dot(col_c, col_c)
        det = aa * bb - ab * ab
        det = np.where(np.abs(det) > 1e-12 * aa * bb, det, np.nan)
        rb, rc = _dot(r, col_b), _dot(r, col_c)
        # per profile: the block columns projected off the (B, C) columns
        gb = [_dot(g, col_b) for g in extra]
        gc = [_dot(g, col_c) for g in extra]
        pb = [(bb * gb[i] - ab * gc[i]) / det for i in range(n_par)]
        pc = [(aa * gc[i] - ab * gb[i]) / det for i in range(n_par)]
        schur = np.zeros((n_blocks, n_par, n_par))
        rhs = np.zeros((n_blocks, n_par))
        for i in range(n_par):
            val = _dot(extra[i], r) - (pb[i] * rb + pc[i] * rc)
            rhs[:, i] = np.bincount(block, np.nan_to_num(val), n_blocks)
            for j in range(i, n_par):
                val = _dot(extra[i], extra[j]) - (pb[i] * gb[j] + pc[i] * gc[j])
                schur[:, i, j] = schur[:, j, i] = np.bincount(block, np.nan_to_num(val), n_blocks)
        diag = np.einsum("kii->ki", schur)
        diag *= 1.05  # a little Levenberg damping: a flat shift cost near focus stays tame
        ok = np.all(diag > 0, axis=1)
        step = np.zeros((n_blocks, n_par))
        if ok.any():
            step[ok] = np.linalg.solve(schur[ok], rhs[ok][:, :, None])[:, :, 0]
        gamma = gamma + step[:, 0]
        if align:
            delta = np.clip(delta + step[:, 1], -MAX_SHIFT_PX, MAX_SHIFT_PX)
            weight = np.where(ok, diag[:, 1], 0.0)
            if weight.sum() > 0:
                delta -= np.average(delta, weights=weight)
        # profile levels follow the block parameters' step
        dr_b = sum(step[:, i][block] * gb[i] for i in range(n_par))
        dr_c = sum(step[:, i][block] * gc[i] for i in range(n_par))
        rb2, rc2 = rb - dr_b, rc - dr_c
        b = b + (bb * rb2 - ab * rc2) / det
        c = c + (aa * rc2 - ab * rb2) / det
    xs = x - delta[block][:, None]
    one = 1.0 + gamma[block][:, None] * x
    z = (y / one - b[:, None]) / c[:, None]
    rms = np.sqrt(np.mean((z - esf(xs)) ** 2, axis=1))
    return xs, z, c, rms


def _dot(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise dot products."""
    return np.einsum("pk,pk->p", u, v)


def _levels(
    y: NDArray[np.float64], a: NDArray[np.float64], e: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per row, least squares ``y ≈ B·a + C·a·E``: level and contrast."""
    ca = a * e
    aa, ab, bb = _dot(a, a), _dot(a, ca), _dot(ca, ca)
    ya, yb = _dot(y, a), _dot(y, ca)
    det = aa * bb - ab * ab
    det = np.where(np.abs(det) > 1e-12 * aa * bb, det, np.nan)
    return (bb * ya - ab * yb) / det, (aa * yb - ab * ya) / det


def _bin(
    x: NDArray[np.float64], z: NDArray[np.float64], weight: NDArray[np.float64], n_profiles: int
) -> BinnedEsf:
    """Weighted bin means of ``z`` at positions ``x`` (every array flattened)."""
    edges = np.arange(-ESF_HALF_PX, ESF_HALF_PX + 0.5 * ESF_BIN_PX, ESF_BIN_PX)
    n_bins = edges.size - 1
    idx = np.floor((x - edges[0]) / ESF_BIN_PX).astype(np.int64)
    inside = (idx >= 0) & (idx < n_bins) & np.isfinite(z)
    idx, xs, zs, ws = idx[inside], x[inside], z[inside], weight[inside]
    count = np.bincount(idx, minlength=n_bins)
    sw = np.bincount(idx, ws, n_bins)
    sw2 = np.bincount(idx, ws * ws, n_bins)
    swx = np.bincount(idx, ws * xs, n_bins)
    swz = np.bincount(idx, ws * zs, n_bins)
    keep = count >= 3
    mean_x = swx[keep] / sw[keep]
    mean_z = swz[keep] / sw[keep]
    # weighted scatter about the bin mean, after removing the slope within the bin
    dev = zs - (swz / np.maximum(sw, 1e-300))[idx]
    dx = xs - (swx / np.maximum(sw, 1e-300))[idx]
    sdx = np.bincount(idx, ws * dx * dx, n_bins)
    sdz = np.bincount(idx, ws * dx * dev, n_bins)
    slope = np.where(sdx > 0, sdz / np.maximum(sdx, 1e-300), 0.0)
    resid = dev - slope[idx] * dx
    var = np.bincount(idx, ws * resid * resid, n_bins) / np.maximum(sw, 1e-300)
    # standard error of a weighted mean: sqrt(var · Σw² / (Σw)²), with n/(n-2) for the slope
    n_eff = sw * sw / np.maximum(sw2, 1e-300)
    se = np.sqrt(var * count / np.maximum(count - 2, 1) / np.maximum(n_eff, 1.0))
    x_sd = np.sqrt(sdx[keep] / sw[keep])
    return BinnedEsf(mean_x, mean_z, se[keep], count[keep].astype(np.int64), n_profiles, x_sd)


def frame_esf(prof: EdgeProfiles, *, start_width_px: float) -> BinnedEsf | None:
    """The binned, normalised edge-spread function of pooled profiles (None if too few).

    ``start_width_px`` is the blurred-step width (Gaussian sigma, pixels) the
    iteration starts from. Profiles whose residual RMS is far above the
    others' (a defect, a stray edge) are dropped.
    """
    if prof.count < MIN_PROFILES:
        return None
    esf: Callable[[NDArray[np.float64]], NDArray[np.float64]] = _gaussian_step(start_width_px)
    keep = np.ones(prof.count, dtype=bool)
    binned: BinnedEsf | None = None
    for round_ in range(2):
        sub = EdgeProfiles(prof.x[keep], prof.y[keep], prof.block[keep])
        xs, z, c, rms = _normalise(sub, esf, iterations=2 + round_, align=round_ > 0)
        good = np.isfinite(c) & (c > 0) & np.isfinite(rms)
        if good.sum() < MIN_PROFILES:
            return None
        med = float(np.median(rms[good]))
        good &= rms <= 4.0 * med + 1e-9
        weight = np.repeat(c * c, sub.x.shape[1]).reshape(sub.x.shape)
        binned = _bin(xs[good].ravel(), z[good].ravel(), weight[good].ravel(), int(good.sum()))
        if binned.x.size < 10:
            return None
        esf = _interpolator(binned)
        idx = np.flatnonzero(keep)
        keep[idx[~good]] = False
    return binned
