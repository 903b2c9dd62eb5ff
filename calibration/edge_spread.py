"""Edge-spread functions of one frame: the blur signal behind the focus plane.

Every well-resolved edge profile of a corner's micro-images (ESIF step 3) is a
sampled blurred step. Its samples are placed at their signed distance ``x``
from the edge (pixels; ``x < 0`` on the dark side) and normalised to the unit
step with levels read off its flat tails only:

    y = (1 + γ_k·x)·(B_p + C_p·H(x))   for |x| ≥ x_flat,

``B_p``, ``C_p``: dark level and contrast of profile ``p``; ``γ_k``: the
relative drift of both levels across the edge in block ``k`` (vignetting and
cos⁴ make the brightness change across a micro-image, and the change
multiplies dark and light alike); ``x_flat``: beyond the blur
(:func:`flat_distance`). The samples nearer the edge are then
``E(x) = (y/(1 + γ_k·x) - B_p)/C_p`` with no shape imposed: a template fitted
to the whole profile would pull each profile's levels toward the template
wherever the two differ near the edge, a bias that depends on the sampling
phase (it cost χ² ≈ 25 on point-sampled pixels).

Where the edge is (the origin of ``x``) comes from the frame's corner lattice,
not from each micro-image's own edge fit (:func:`calibration.frame_analysis`):
a sharp edge sampled by few points per pixel only locates to the sample
spacing in one micro-image, and the lattice ``s = (1+Q)·m + c`` averages that
over every micro-image of the corner. The lattice's own prediction error
is carried as ``jitter_px``: the function this module returns is the edge
spread convolved with that placement error, which the defocus model includes.

Pooling the profiles of every micro-image with their different sub-pixel
phases samples ``E`` far below the pixel: the result is binned in
``ESF_BIN_PX`` bins (mean position, weighted mean value and its standard
error per bin), a few hundred numbers per corner and frame, which is what the
whole-sweep defocus model (:mod:`calibration.defocus`) fits.

``E`` is the step convolved with everything that blurs the micro-image: the
pixel response (area or point sampling), the static blur (lens PSF,
diffraction, sensor) and the geometric defocus disk of OPTICS.md §1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

ESF_HALF_PX = 10.0
"""Half width of the binned edge-spread function (pixels): the longest profile
(:func:`profile_half_px`)."""

ESF_BIN_PX = 0.1
"""Bin width of the binned edge-spread function (pixels)."""

MIN_PROFILES = 8
"""Fewest profiles for an edge-spread function of one corner in one frame."""

FLAT_SIGMAS = 4.0
"""The tails start this many sigmas of the edge's blur (pixel included) from the edge, plus
``FLAT_MARGIN_PX``: a blur that is not Gaussian (a defocus box) reaches farther than three
of its sigmas."""

FLAT_MARGIN_PX = 0.25
"""Added to the tails' distance from the edge (px): half a sample of point-sampled pixels."""

FLAT_RANGE_PX = (2.0, 8.0)
"""Bounds of the tails' distance from the edge (px); the profile reaches 2 samples past it
(:func:`profile_half_px`)."""

TAIL_SAMPLES = 2
"""Samples of each tail beyond the flat distance (at least)."""


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
    def empty() -> EdgeProfiles:
        return EdgeProfiles(np.empty((0, 0)), np.empty((0, 0)), np.empty(0, dtype=np.int64))

    @staticmethod
    def concatenate(parts: Sequence[EdgeProfiles]) -> EdgeProfiles:
        """One set from many (block labels kept distinct)."""
        parts = [p for p in parts if p.count]
        if not parts:
            return EdgeProfiles.empty()
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
    ``jitter_px``: RMS error of the edge positions the samples were placed
    against (pixels): the function is the edge spread convolved with it.
    """

    x: NDArray[np.float64]
    value: NDArray[np.float64]
    se: NDArray[np.float64]
    count: NDArray[np.int64]
    profiles: int
    x_sd: NDArray[np.float64] | None = None
    jitter_px: float = 0.0

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
            "jitter_px": round(float(self.jitter_px), 5),
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
            float(data.get("jitter_px") or 0.0),
        )

    @staticmethod
    def merge(parts: Sequence[BinnedEsf]) -> BinnedEsf:
        """Inverse-variance weighted mean of functions binned on the same bins (their
        jitter variances averaged with the profile counts as weights)."""
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
        n_prof = np.array([p.profiles for p in parts], dtype=np.float64)
        jitter2 = np.array([p.jitter_px**2 for p in parts], dtype=np.float64)
        return BinnedEsf(
            mean,
            swv[keep] / sw[keep],
            1.0 / np.sqrt(sw[keep]),
            count[keep],
            sum(p.profiles for p in parts),
            np.sqrt(np.maximum(swxx[keep] / sw[keep] - mean**2, 0.0)),
            float(np.sqrt(np.sum(n_prof * jitter2) / max(float(np.sum(n_prof)), 1.0))),
        )

    def centre_px(self, *, half_window_px: float = 3.0) -> float:
        """Centroid of the line-spread function within ``±half_window_px`` (pixels).

        ``∫x·E'(x)dx = [x·E] - ∫E dx`` over the window (trapezoids on the bins): for a
        symmetric blur the edge itself, so it is where the function is centred. NaN
        when too few bins lie in the window.
        """
        inside = np.abs(self.x) <= half_window_px
        if inside.sum() < 10:
            return float("nan")
        x, e = self.x[inside], self.value[inside]
        area = float(np.sum(0.5 * (e[1:] + e[:-1]) * np.diff(x)))
        rise = float(e[-1] - e[0])
        if rise <= 0:
            return float("nan")
        return (float(x[-1] * e[-1] - x[0] * e[0]) - area) / rise

    def shifted(self, shift_px: float) -> BinnedEsf:
        """The same function with its positions moved by ``shift_px``."""
        return replace(self, x=self.x + shift_px)

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


def flat_distance(width_px: float) -> float:
    """Distance from the edge (px) beyond which a profile is taken as flat.

    ``width_px``: the blurred-step width (Gaussian sigma before pixel integration,
    :mod:`calibration.edge_fit`) of the frame's edges; ``FLAT_SIGMAS`` of the edge's
    whole sigma (the pixel's ``1/√12`` added) plus ``FLAT_MARGIN_PX``, within
    ``FLAT_RANGE_PX``.
    """
    lo, hi = FLAT_RANGE_PX
    if not np.isfinite(width_px):
        return hi
    sigma = float(np.sqrt(width_px**2 + 1.0 / 12.0))
    return float(np.clip(FLAT_SIGMAS * sigma + FLAT_MARGIN_PX, lo, hi))


def profile_half_px(width_px: float, *, minimum: int, maximum: int) -> int:
    """Half length (samples) of the profiles cut across a frame's edges: twice
    :func:`flat_distance` of the edges' width plus ``TAIL_SAMPLES`` (tails as long as the
    blurred part), at least ``minimum`` and at most ``maximum`` (what fits in the
    micro-images' plateau) and ``ESF_HALF_PX``.

    Blurred edges get longer profiles, so that their levels come from long tails: a
    diffraction-limited microlens (first zero of its pattern 2.75 px at f/12.5 in green
    light) still has a lobe 4-6 px from the edge, and levels read from ±6 px profiles put
    ``Q0`` 0.13 % low on a Monte-Carlo sweep with that diffraction, with the renderer's
    true ``Q`` (0.01 % with ±10 px profiles). Edges with σ ≤ 0.33 px keep the minimum.
    """
    wanted = int(np.ceil(2.0 * flat_distance(width_px))) + TAIL_SAMPLES
    return int(max(minimum, min(wanted, maximum, int(ESF_HALF_PX))))


def _tail_normalise(
    prof: EdgeProfiles, x_flat: float, *, iterations: int = 4
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(z, C)``: samples mapped to the unit step by levels read off the flat tails.

    Least squares of ``y = (1 + γ_k·x)·(B_p + C_p·H(x))`` over the samples with
    ``|x| ≥ x_flat``: for given drifts ``γ_k`` the levels of each profile are a
    2×2 linear problem, solved in closed form and projected out (variable
    projection), and each block's ``γ_k`` takes Gauss–Newton steps on what is
    left. ``C`` is NaN for a profile with fewer than 2 tail samples on either side.
    """
    x, y, block = prof.x, prof.y, prof.block
    n_blocks = int(block.max()) + 1
    light = x >= x_flat
    dark = x <= -x_flat
    tail = (light | dark).astype(np.float64)
    step = light.astype(np.float64)
    gamma = np.zeros(n_blocks)
    b = c = np.zeros(prof.count)
    for _ in range(iterations):
        one = 1.0 + gamma[block][:, None] * x
        col_b, col_c = one * tail, one * step  # (the light tail is inside the tails)
        aa, ab, bb = _dot(col_b, col_b), _dot(col_b, col_c), _dot(col_c, col_c)
        det = aa * bb - ab * ab
        det = np.where(np.abs(det) > 1e-12 * np.maximum(aa * bb, 1e-300), det, np.nan)
        yb, yc = _dot(y, col_b), _dot(y, col_c)
        b = (bb * yb - ab * yc) / det
        c = (aa * yc - ab * yb) / det
        resid = (y - b[:, None] * one - c[:, None] * one * step) * tail
        g = x * (b[:, None] + c[:, None] * step) * tail  # d model / d gamma
        gb, gc = _dot(g, col_b), _dot(g, col_c)
        pb = (bb * gb - ab * gc) / det
        pc = (aa * gc - ab * gb) / det
        g_perp = g - pb[:, None] * col_b - pc[:, None] * col_c
        num = np.bincount(block, np.nan_to_num(_dot(g_perp, resid)), n_blocks)
        den = np.bincount(block, np.nan_to_num(_dot(g_perp, g_perp)), n_blocks)
        gamma = gamma + np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
    one = 1.0 + gamma[block][:, None] * x
    z = (y / one - b[:, None]) / np.where(c == 0, np.nan, c)[:, None]
    enough = (dark.sum(axis=1) >= 2) & (light.sum(axis=1) >= 2)
    return z, np.where(enough, c, np.nan)


def _dot(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise dot products."""
    return np.einsum("pk,pk->p", u, v)


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


def frame_esf(
    prof: EdgeProfiles,
    *,
    start_width_px: float,
    jitter_px: float = 0.0,
    max_flat_px: float = np.inf,
) -> BinnedEsf | None:
    """The binned, normalised edge-spread function of pooled profiles (None if too few).

    ``start_width_px``: the frame's blurred-step width (Gaussian sigma, px),
    which sets where the flat tails start (:func:`flat_distance`, at most
    ``max_flat_px``: ``TAIL_SAMPLES`` short of the profiles' ends);
    ``jitter_px``: the RMS error of the edge positions the profiles are placed
    against, recorded with the function. Profiles whose scatter about the
    pooled function is far above the others' (a defect, a stray edge) are
    dropped.
    """
    if prof.count < MIN_PROFILES:
        return None
    z, c = _tail_normalise(prof, min(flat_distance(start_width_px), max_flat_px))
    good = np.isfinite(c) & (c > 0) & np.all(np.isfinite(z), axis=1)
    if good.sum() < MIN_PROFILES:
        return None
    weight = np.repeat(c * c, prof.x.shape[1]).reshape(prof.x.shape)
    binned = _bin(prof.x[good].ravel(), z[good].ravel(), weight[good].ravel(), int(good.sum()))
    if binned.x.size < 10:
        return None
    rms = np.sqrt(np.mean((z - np.interp(prof.x, binned.x, binned.value)) ** 2, axis=1))
    med = float(np.median(rms[good]))
    good &= rms <= 4.0 * med + 1e-9
    if good.sum() < MIN_PROFILES:
        return None
    binned = _bin(prof.x[good].ravel(), z[good].ravel(), weight[good].ravel(), int(good.sum()))
    if binned.x.size < 10:
        return None
    return replace(binned, jitter_px=float(jitter_px))
