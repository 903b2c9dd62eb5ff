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
(:func:`~calibration.edge_window.flat_distance`). Profiles flat-fielded by the white image
(:mod:`calibration.edge_profiles`) have no drift left and are read without it,
their levels at fixed points of tails whose shape the frame's profiles share
(:func:`calibration.edge_levels.levels_with_tail_shape`): a fitted drift takes the still-falling tails of a
diffraction-limited edge (1/x, 5-9 % short of the levels 4-6 px out) for
vignetting and bends the function by dividing them out, and flat tails make each
profile's levels depend on its sampling phase. The samples nearer the edge are then
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
The lattice's offset errs by one draw per frame, which moves the two halves of
each edge apart (their dark sides face opposite ways): each half-edge is
therefore centred on its own edge, the centroid of its pooled line spread,
before the four are pooled (:mod:`calibration.edge_centres`), and the jitter is
what varies within a half-edge. The lattice's scale is the weak part of it near
focus (one frame's ``Q`` to ~1e-3 there), so the samples are also binned by
their lever on that scale (:class:`LeverGroup`), and the sweep places them again
with a scale it knows far better (:mod:`calibration.lattice_scale`).

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

from .edge_bins import bin_means, group_means
from .edge_centres import centre_half_edges, lsf_centroid
from .edge_levels import levels_with_drift, levels_with_tail_shape
from .edge_window import ESF_HALF_PX, flat_distance
from .line_clusters import cluster_on_line
from .placement_error import PlacementError

ESF_BIN_PX = 0.1
"""Bin width of the binned edge-spread function (pixels)."""

MIN_PROFILES = 8
"""Fewest profiles for an edge-spread function of one corner in one frame."""

MIN_STEP_FRACTION = 0.02
"""Profiles whose step (light minus dark level, counts) is below this fraction of the corner's
typical step (the 90th percentile of the frame's) are dropped: they lie in unlit parts of the
frame (outside the main lens's image circle, a micro-image the corner's lattice predicts but
no light reaches) and are noise. Their weight (the step squared) is negligible, but a bin of
the function that only such samples reach would read the dark level with a tiny error."""


@dataclass
class EdgeProfiles:
    """Edge profiles of one corner in one frame, samples placed relative to their edge.

    ``x``: signed distance of each sample from the edge (pixels, dark side
    negative), shape ``(P, K)``; ``y``: the raw counts; ``block``: the edge
    block of each profile (profiles of one block share the drift terms);
    ``lever``: per profile, how far its samples move per unit error of the
    corner lattice's scale ``1+Q`` (pixels; :mod:`calibration.edge_profiles`),
    or None when unknown; ``half_edge``: per profile, which of the corner's
    half-edges it crosses (each is centred on its own edge before pooling,
    :mod:`calibration.edge_centres`), or None when unknown.
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    block: NDArray[np.int64]
    lever: NDArray[np.float64] | None = None
    half_edge: NDArray[np.int64] | None = None

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
        levers = [p.lever for p in parts]
        halves = [p.half_edge for p in parts]
        return EdgeProfiles(
            np.concatenate([p.x for p in parts]),
            np.concatenate([p.y for p in parts]),
            np.concatenate(blocks),
            None if any(v is None for v in levers) else np.concatenate(levers),  # type: ignore[arg-type]
            None if any(h is None for h in halves) else np.concatenate(halves),  # type: ignore[arg-type]
        )


LEVER_GROUPS = 6
"""Groups by lever (:class:`LeverGroup`) a corner's profiles are also binned in."""


@dataclass(frozen=True)
class LeverGroup:
    """The profiles of one range of levers, binned on their own.

    A frame's corner lattice ``s = (1+Q)·m + c`` places every profile; an error
    ``δ`` of its scale moves the samples of a profile by ``δ·lever`` (the lever
    is ``±`` the lens centre's coordinate across the edge, pixels, here taken
    about the profiles' mean). The pooled function mixes copies moved by
    different amounts, a blur no later shift can undo; kept apart by lever, each
    group can be moved back once the scale is known better
    (:meth:`BinnedEsf.replaced`). ``lever_px``: the group's mean lever,
    ``lever_sd_px``: their spread within the group.
    """

    lever_px: float
    lever_sd_px: float
    esf: BinnedEsf

    def to_dict(self) -> dict[str, Any]:
        """What :meth:`BinnedEsf.replaced` needs (not the standard errors: the merged
        function keeps the whole one's), rounded to far below the noise."""
        esf = self.esf
        return {
            "lever_px": round(self.lever_px, 3),
            "lever_sd_px": round(self.lever_sd_px, 3),
            "x_px": np.round(esf.x, 4).tolist(),
            "x_sd_px": np.round(esf.position_sd_px, 4).tolist(),
            "value": np.round(esf.value, 5).tolist(),
            "count": esf.count.tolist(),
            "weight": _round_significant(esf.sample_weight, 4).tolist(),
            "profiles": esf.profiles,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LeverGroup:
        x = np.asarray(data["x_px"], dtype=np.float64)
        esf = BinnedEsf(
            x,
            np.asarray(data["value"], dtype=np.float64),
            np.full(x.shape, np.nan),
            np.asarray(data["count"], dtype=np.int64),
            int(data["profiles"]),
            np.asarray(data["x_sd_px"], dtype=np.float64),
            weight=np.asarray(data["weight"], dtype=np.float64),
        )
        return cls(float(data["lever_px"]), float(data["lever_sd_px"]), esf)


@dataclass(frozen=True)
class BinnedEsf:
    """The normalised edge-spread function of one corner in one frame.

    Per bin of ``ESF_BIN_PX``: ``x`` the mean position of its samples
    (pixels from the edge), ``value`` their weighted mean (0 dark, 1 light),
    ``se`` its standard error, ``count`` the number of samples. Bins without
    samples are dropped. ``profiles``: how many profiles were pooled.
    ``jitter_px``: RMS error of the edge positions the samples were placed
    against (pixels): the function is the edge spread convolved with it.
    ``jitter_fixed_scale_px``: the same without the error of the lattice's scale
    (what is left once the scale is known), NaN when not recorded;
    ``lever_groups``: the same samples binned by lever (:class:`LeverGroup`),
    empty when not recorded; ``weight``: the sum of the samples' weights per bin
    (recorded for lever groups: their merge weighs the samples as the whole
    function does).
    """

    x: NDArray[np.float64]
    value: NDArray[np.float64]
    se: NDArray[np.float64]
    count: NDArray[np.int64]
    profiles: int
    x_sd: NDArray[np.float64] | None = None
    jitter_px: float = 0.0
    jitter_fixed_scale_px: float = float("nan")
    lever_groups: tuple[LeverGroup, ...] = ()
    weight: NDArray[np.float64] | None = None

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

    @property
    def sample_weight(self) -> NDArray[np.float64]:
        """The sum of the samples' weights per bin (``weight``; the counts when not recorded)."""
        return np.asarray(self.weight if self.weight is not None else self.count, np.float64)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "x_px": np.round(self.x, 5).tolist(),
            "x_sd_px": np.round(self.position_sd_px, 5).tolist(),
            "value": np.round(self.value, 6).tolist(),
            "se": np.round(self.se, 7).tolist(),
            "count": self.count.tolist(),
            "profiles": self.profiles,
            "jitter_px": round(float(self.jitter_px), 5),
        }
        if np.isfinite(self.jitter_fixed_scale_px):
            out["jitter_fixed_scale_px"] = round(float(self.jitter_fixed_scale_px), 5)
        if self.lever_groups:
            out["lever_groups"] = [g.to_dict() for g in self.lever_groups]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> BinnedEsf:
        sd = data.get("x_sd_px")
        fixed = data.get("jitter_fixed_scale_px")
        return cls(
            np.asarray(data["x_px"], dtype=np.float64),
            np.asarray(data["value"], dtype=np.float64),
            np.asarray(data["se"], dtype=np.float64),
            np.asarray(data["count"], dtype=np.int64),
            int(data["profiles"]),
            None if sd is None else np.asarray(sd, dtype=np.float64),
            float(data.get("jitter_px") or 0.0),
            float("nan") if fixed is None else float(fixed),
            tuple(LeverGroup.from_dict(g) for g in data.get("lever_groups") or ()),
        )

    def replaced(self, scale_error: float, scale_se: float) -> BinnedEsf:
        """The function with its samples placed by a better lattice scale.

        ``scale_error``: the frame lattice's scale ``1+Q`` minus the better one,
        ``scale_se``: the better one's standard error. Each lever group moves back
        by ``-scale_error·lever`` and the groups are merged; the jitter left is the
        placement without the scale's error, the spread of levers within each
        group times ``scale_error`` and each group's lever times ``scale_se``. The
        groups' bins are merged with their samples' weights (``weight``), so with no
        error this is the whole function again, each merged bin keeping the whole
        function's standard error at its position.
        Without lever groups (or without a finite error) the function itself.
        """
        fixed = self.jitter_fixed_scale_px
        if not self.lever_groups or not (np.isfinite(scale_error) and np.isfinite(fixed)):
            return self
        se2 = float(scale_se) ** 2 if np.isfinite(scale_se) else 0.0
        parts = [
            replace(
                g.esf.shifted(-scale_error * g.lever_px),
                jitter_px=float(
                    np.sqrt(fixed**2 + scale_error**2 * g.lever_sd_px**2 + se2 * g.lever_px**2)
                ),
            )
            for g in self.lever_groups
        ]
        sums = _BinSums.of(parts, [p.sample_weight for p in parts])
        keep = (sums.count >= 3) & (sums.sw > 0)
        mean = sums.mean_x(keep)
        return BinnedEsf(
            mean,
            sums.mean_value(keep),
            # the groups' bins hold few samples each, some of one sub-pixel phase: their
            # scatter says little, so the samples keep their weights in the whole function
            # and each bin the whole function's standard error where it now lies
            np.interp(mean, self.x, self.se),
            sums.count[keep],
            self.profiles,
            sums.position_sd(keep),
            _pooled_jitter(parts),
        )

    @staticmethod
    def merge(parts: Sequence[BinnedEsf]) -> BinnedEsf:
        """Inverse-variance weighted mean of functions binned on the same bins (their
        jitter variances averaged with the profile counts as weights)."""
        sums = _BinSums.of(parts, [1.0 / np.maximum(p.se, 1e-6) ** 2 for p in parts])
        keep = sums.sw > 0
        return BinnedEsf(
            sums.mean_x(keep),
            sums.mean_value(keep),
            1.0 / np.sqrt(sums.sw[keep]),
            sums.count[keep],
            sum(p.profiles for p in parts),
            sums.position_sd(keep),
            _pooled_jitter(parts),
        )

    def centre_px(self, *, half_window_px: float = 3.0) -> float:
        """Centroid of the line-spread function within ``±half_window_px`` (pixels).

        ``∫x·E'(x)dx = [x·E] - ∫E dx`` over the window (trapezoids on the bins): for a
        symmetric blur the edge itself, so it is where the function is centred. NaN
        when too few bins lie in the window.
        """
        return lsf_centroid(self.x, self.value, half_window_px=half_window_px)[0]

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


@dataclass(frozen=True)
class _BinSums:
    """Weighted sums over the functions' bins that fall in each standard bin: weights,
    positions, squared positions (with each bin's own spread) and values; sample counts."""

    sw: NDArray[np.float64]
    swx: NDArray[np.float64]
    swxx: NDArray[np.float64]
    swv: NDArray[np.float64]
    count: NDArray[np.int64]

    @classmethod
    def of(cls, parts: Sequence[BinnedEsf], weights: Sequence[NDArray[np.float64]]) -> _BinSums:
        n_bins = int(round(2 * ESF_HALF_PX / ESF_BIN_PX))
        sw, swx, swxx, swv = (np.zeros(n_bins) for _ in range(4))
        count = np.zeros(n_bins, dtype=np.int64)
        for p, w in zip(parts, weights, strict=True):
            b = np.clip(np.floor((p.x + ESF_HALF_PX) / ESF_BIN_PX).astype(np.int64), 0, n_bins - 1)
            np.add.at(sw, b, w)
            np.add.at(swx, b, w * p.x)
            np.add.at(swxx, b, w * (p.x**2 + p.position_sd_px**2))
            np.add.at(swv, b, w * p.value)
            np.add.at(count, b, p.count)
        return cls(sw, swx, swxx, swv, count)

    def mean_x(self, keep: NDArray[np.bool_]) -> NDArray[np.float64]:
        """Weighted mean sample position of each kept bin (px)."""
        return np.asarray(self.swx[keep] / self.sw[keep], dtype=np.float64)

    def mean_value(self, keep: NDArray[np.bool_]) -> NDArray[np.float64]:
        """Weighted mean value of each kept bin."""
        return np.asarray(self.swv[keep] / self.sw[keep], dtype=np.float64)

    def position_sd(self, keep: NDArray[np.bool_]) -> NDArray[np.float64]:
        """Spread of the sample positions in each kept bin (px)."""
        mean = self.mean_x(keep)
        return np.sqrt(np.maximum(self.swxx[keep] / self.sw[keep] - mean**2, 0.0))


def _round_significant(values: NDArray[np.float64], digits: int) -> NDArray[np.float64]:
    """``values`` rounded to ``digits`` significant digits each (zeros stay zero): sample
    weights span decades (a profile's weight is its contrast squared), and rounding them
    to fixed decimals set the weights of dim profiles' bins to 0."""
    v = np.asarray(values, dtype=np.float64)
    out = v.copy()
    nonzero = np.isfinite(v) & (v != 0)
    exponent = np.floor(np.log10(np.abs(v[nonzero])))
    scale = 10.0 ** (digits - 1 - exponent)
    out[nonzero] = np.round(v[nonzero] * scale) / scale
    return out


def _pooled_jitter(parts: Sequence[BinnedEsf]) -> float:
    """RMS jitter of pooled functions: their jitter variances weighted by profile counts."""
    n_prof = np.array([p.profiles for p in parts], dtype=np.float64)
    jitter2 = np.array([p.jitter_px**2 for p in parts], dtype=np.float64)
    return float(np.sqrt(np.sum(n_prof * jitter2) / max(float(np.sum(n_prof)), 1.0)))


def _bin(
    x: NDArray[np.float64], z: NDArray[np.float64], weight: NDArray[np.float64], n_profiles: int
) -> BinnedEsf:
    """Weighted bin means of ``z`` at positions ``x`` (every array flattened;
    :func:`~calibration.edge_bins.bin_means` in ``ESF_BIN_PX`` bins over ``±ESF_HALF_PX``)."""
    bins = bin_means(x, z, weight, bin_px=ESF_BIN_PX, half_px=ESF_HALF_PX)
    return BinnedEsf(
        bins.x, bins.value, bins.se, bins.count, n_profiles, bins.x_sd, weight=bins.weight
    )


def frame_esf(
    prof: EdgeProfiles,
    *,
    start_width_px: float,
    jitter_px: float = 0.0,
    jitter_fixed_scale_px: float = float("nan"),
    max_flat_px: float = np.inf,
    drift: bool = True,
    placement: PlacementError | None = None,
) -> BinnedEsf | None:
    """The binned, normalised edge-spread function of pooled profiles (None if too few).

    ``start_width_px``: the frame's blurred-step width (Gaussian sigma, px),
    which sets where the flat tails start (:func:`~calibration.edge_window.flat_distance`, at most
    ``max_flat_px``: ``edge_window.TAIL_SAMPLES`` short of the profiles' ends);
    ``jitter_px``: the RMS error of the edge positions the profiles are placed
    against, recorded with the function, and ``jitter_fixed_scale_px`` that
    error without the lattice scale's part; when the profiles carry levers the
    same samples are also binned by lever (:class:`LeverGroup`). ``drift``: the
    profiles are not flat-fielded: their levels are read with a drift per block and
    flat tails (:func:`~calibration.edge_levels.levels_with_drift`); false: without a
    drift, at fixed points of the tails' shared shape
    (:func:`~calibration.edge_levels.levels_with_tail_shape`). Profiles whose
    scatter about the pooled function is far above the others' (a defect, a
    stray edge) are dropped. When the profiles carry their half-edges, each half-edge
    is centred on its own edge first (:func:`~calibration.edge_centres.centre_half_edges`;
    one with too few profiles is dropped) and the levers are taken about each
    half-edge's mean. ``placement``: the profiles' placement errors
    (:mod:`calibration.placement_error`); when given, the jitter recorded is their
    spread as this function weighs its profiles (contrast squared, the dropped ones
    none), within each half-edge when they were centred and with the centres' own
    errors, instead of ``jitter_px`` and ``jitter_fixed_scale_px``.
    """
    if prof.count < MIN_PROFILES:
        return None
    x_flat = min(flat_distance(start_width_px), max_flat_px)
    if drift:
        z, c = levels_with_drift(prof.x, prof.y, prof.block, x_flat)
    else:
        z, c = levels_with_tail_shape(prof.x, prof.y, x_flat)
    good = _lit(c) & np.all(np.isfinite(z), axis=1)
    if good.sum() < MIN_PROFILES:
        return None
    weight = np.repeat(c * c, prof.x.shape[1]).reshape(prof.x.shape)
    x, lever, half_edge = prof.x, prof.lever, prof.half_edge
    centre_spread_px2 = 0.0
    if half_edge is not None:
        # each half-edge on its own edge (the lattice's offset errs by one draw per frame)
        centres = centre_half_edges(
            x, z, weight, half_edge, usable=good, half_window_px=x_flat, min_profiles=MIN_PROFILES
        )
        good &= centres.kept
        if good.sum() < MIN_PROFILES:
            return None
        x = x - centres.shift_px[:, None]
        centre_spread_px2 = centres.spread_px2
        if lever is not None:
            lever = lever - group_means(lever, np.where(good, c * c, 0.0), half_edge)
    binned = _bin(x[good].ravel(), z[good].ravel(), weight[good].ravel(), int(good.sum()))
    if binned.x.size < 10:
        return None
    rms = np.sqrt(np.mean((z - np.interp(x, binned.x, binned.value)) ** 2, axis=1))
    med = float(np.median(rms[good]))
    good &= rms <= 4.0 * med + 1e-9
    if good.sum() < MIN_PROFILES:
        return None
    binned = _bin(x[good].ravel(), z[good].ravel(), weight[good].ravel(), int(good.sum()))
    if binned.x.size < 10:
        return None
    groups: tuple[LeverGroup, ...] = ()
    if lever is not None:
        groups = _lever_groups(x[good], z[good], weight[good], lever[good])
    if placement is not None and placement.gradients.shape[0] == prof.count:
        # the spread of the placement errors as this function weighs its profiles, about
        # each half-edge's centre when they were centred, and the centres' own errors
        pooled = np.where(good, c * c, 0.0)
        centres_px = np.sqrt(centre_spread_px2)
        jitter_px = np.hypot(placement.jitter_px(pooled, groups=half_edge), centres_px)
        jitter_fixed_scale_px = np.hypot(
            placement.jitter_px(pooled, scale_known=True, groups=half_edge), centres_px
        )
    return replace(
        binned,
        jitter_px=float(jitter_px),
        jitter_fixed_scale_px=float(jitter_fixed_scale_px),
        lever_groups=groups,
    )


def _lit(step: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Profiles with a finite step of at least ``MIN_STEP_FRACTION`` of the typical one."""
    positive = np.isfinite(step) & (step > 0)
    if not positive.any():
        return positive
    typical = float(np.quantile(step[positive], 0.9))
    return positive & (step >= MIN_STEP_FRACTION * typical)


def _lever_groups(
    x: NDArray[np.float64],
    z: NDArray[np.float64],
    weight: NDArray[np.float64],
    lever: NDArray[np.float64],
) -> tuple[LeverGroup, ...]:
    """The profiles (rows) binned in at most ``LEVER_GROUPS`` groups of neighbouring levers,
    each of at least ``MIN_PROFILES`` profiles, levers about their weighted mean (weights
    ``weight[:, 0]``). A micro-image's half-edge shares one lever; the distinct levers are
    joined pairwise, neighbours with the least increase of the spread within groups first
    (Ward's criterion on a line), so a group never spans a gap between clusters."""
    weight = weight / float(np.mean(weight))  # sums of weights of order the sample counts
    w = weight[:, 0]
    rel = lever - float(np.sum(w * lever) / np.sum(w))
    label = cluster_on_line(rel, max_groups=LEVER_GROUPS, min_size=MIN_PROFILES)
    groups = []
    for k in np.unique(label):
        sel = label == k
        if sel.sum() < MIN_PROFILES:
            return ()
        wk = w[sel]
        mean = float(np.sum(wk * rel[sel]) / np.sum(wk))
        sd = float(np.sqrt(np.sum(wk * (rel[sel] - mean) ** 2) / np.sum(wk)))
        binned = _bin(x[sel].ravel(), z[sel].ravel(), weight[sel].ravel(), int(sel.sum()))
        if binned.x.size < 10:
            return ()
        groups.append(LeverGroup(mean, sd, binned))
    return tuple(groups)
