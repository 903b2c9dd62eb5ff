"""Edge-spread functions pooled from edge profiles: levels, drifts and phases removed.

Profiles are synthesised from a known edge-spread function at random sub-pixel
phases, with per-profile dark level and contrast, a multiplicative drift
across the edge per block (vignetting), and noise; pooling must give back the
known function, with standard errors that describe its scatter.
"""

from __future__ import annotations

import numpy as np
import pytest
from edge_shapes import sinc2_cdf
from scipy.special import ndtr

from calibration.edge_spread import ESF_BIN_PX, BinnedEsf, EdgeProfiles, frame_esf
from calibration.edge_window import corner_clearance_px


def _truth(x: np.ndarray) -> np.ndarray:
    """A box-blurred (1.2 px) Gaussian (0.5 px) step integrated over the pixel: not a Gaussian."""
    k = (np.arange(40) + 0.5) / 40 * 2.2 - 1.1  # box 1.2 px ⊗ pixel 1 px, as a 2.2 px support
    w = np.clip(1.1 - np.abs(k), 0, 1.0)  # their convolution: a trapezoid
    w = w / w.sum()
    return ndtr((x[:, None] - k[None, :]) / 0.5) @ w


def _profiles(seed: int, *, noise: float = 0.004, drift: float = 0.01) -> EdgeProfiles:
    rng = np.random.default_rng(seed)
    n_blocks, per_block, k = 40, 12, 13
    xs, ys, blocks = [], [], []
    for blk in range(n_blocks):
        gamma = rng.uniform(-drift, drift)  # relative level change per pixel across the edge
        for _ in range(per_block):
            phase = rng.uniform(-0.5, 0.5)
            x = np.arange(k) - 6 + phase
            dark, contrast = rng.uniform(80, 120), rng.uniform(600, 900)
            y = (1 + gamma * x) * (dark + contrast * _truth(x))
            y = y + rng.normal(0, noise * contrast, k)
            xs.append(x)
            ys.append(y)
            blocks.append(blk)
    return EdgeProfiles(np.array(xs), np.array(ys), np.array(blocks))


def test_pooled_profiles_give_back_the_edge_spread_function() -> None:
    esf = frame_esf(_profiles(1), start_width_px=0.6)
    assert esf is not None
    inside = np.abs(esf.x) < 5.0
    np.testing.assert_allclose(esf.value[inside], _truth(esf.x[inside]), atol=0.006)
    # the residuals scatter like the stated standard errors
    z = (esf.value[inside] - _truth(esf.x[inside])) / esf.se[inside]
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6


def test_without_the_drift_terms_the_function_would_be_tilted() -> None:
    """The drift model matters: a strong vignetting drift is removed, not folded into the shape."""
    esf = frame_esf(_profiles(2, drift=0.03), start_width_px=0.6)
    assert esf is not None
    far = np.abs(esf.x) > 3.5
    np.testing.assert_allclose(esf.value[far], _truth(esf.x[far]), atol=0.01)


def test_too_few_profiles_give_no_function() -> None:
    prof = _profiles(3)
    few = EdgeProfiles(prof.x[:5], prof.y[:5], prof.block[:5])
    assert frame_esf(few, start_width_px=0.6) is None


def test_binned_functions_merge_by_inverse_variance_and_round_trip_through_json() -> None:
    a = frame_esf(_profiles(4), start_width_px=0.6)
    b = frame_esf(_profiles(5), start_width_px=0.6)
    assert a is not None and b is not None
    merged = BinnedEsf.merge([a, b])
    assert merged.profiles == a.profiles + b.profiles
    assert np.median(merged.se) < np.median(a.se)
    again = BinnedEsf.from_dict(merged.to_dict())
    np.testing.assert_allclose(again.value, merged.value, atol=1e-6)
    assert np.all(np.diff(merged.x) > 0) and np.all(np.diff(merged.x) < 2.5 * ESF_BIN_PX)


@pytest.mark.parametrize("width", [0.3, 1.0])
def test_the_display_width_grows_with_the_blur(width: float) -> None:
    x = np.arange(-5.95, 6.0, 0.1)
    narrow = BinnedEsf(x, ndtr(x / 0.3), np.ones_like(x), np.ones(x.size, dtype=np.int64), 1)
    wide = BinnedEsf(x, ndtr(x / width), np.ones_like(x), np.ones(x.size, dtype=np.int64), 1)
    assert wide.spread_px() == pytest.approx(width, rel=0.05)
    assert narrow.spread_px() <= wide.spread_px()


def test_long_tails_of_flat_fielded_profiles_are_not_taken_for_a_drift() -> None:
    """A diffraction-limited edge's tails still fall 5-9 % short of the levels 4-6 px from
    the edge. With a drift per block fitted to the tails (the levels' model before the
    profiles were flat-fielded by the white image), those slopes were taken for vignetting
    and divided out: the bright side came out bent by 3 % of the contrast (as measured on
    a Monte-Carlo sweep with that diffraction against its exact functions) and ``Q0``
    0.3 % low on exact functions (``tests/test_defocus.py``). Flat-fielded profiles read
    their levels at fixed points of tails whose shape the frame's profiles share: the
    pooled function is the true one up to the level and gain (which the defocus model
    fits per frame) to 1e-3 (read as flat, each profile's levels depended on its
    sampling phase: a ripple of 2.4e-3)."""
    rng = np.random.default_rng(6)
    x = np.arange(-6, 7)[None, :] + rng.uniform(-0.5, 0.5, (400, 1))
    y = 30.0 + 500.0 * sinc2_cdf(x / 3.43)
    prof = EdgeProfiles(x, y, np.repeat(np.arange(20), 20))

    def affine_misfit(esf: BinnedEsf | None) -> float:
        assert esf is not None
        truth = sinc2_cdf(esf.x / 3.43)
        design = np.c_[np.ones_like(truth), truth]
        coef = np.linalg.lstsq(design, esf.value, rcond=None)[0]
        return float(np.max(np.abs(esf.value - design @ coef)))

    assert affine_misfit(frame_esf(prof, start_width_px=1.2, max_flat_px=4.0, drift=False)) < 0.001
    assert affine_misfit(frame_esf(prof, start_width_px=1.2, max_flat_px=4.0)) > 0.015


def test_profiles_in_unlit_parts_of_the_frame_are_dropped() -> None:
    """A corner's lattice can predict half-edges in micro-images no light reaches (outside
    the main lens's image circle, or a renderer's window): their profiles are read noise,
    with a step of a count or two against the lit ones' hundreds. Their weight is negligible,
    but when they outnumber the lit ones the scatter test (against the median profile's)
    keeps them, and where they alone reach a bin (edges along the pixel rows share a few
    sub-pixel phases) the bin read noise with a tiny error: a Fourier-optics sweep put its
    focus plane 13 mm off (4.8σ) that way."""
    rng = np.random.default_rng(5)
    k = 13
    xs, ys, blocks = [], [], []
    for blk in range(40):
        phase = (0.1, 0.3, 0.5, 0.7, 0.9)[blk % 5]  # lit profiles at five phases
        for _ in range(10):
            x = np.arange(k) - 6 + phase
            dark, contrast = rng.uniform(80, 120), rng.uniform(600, 900)
            xs.append(x)
            ys.append(dark + contrast * _truth(x) + rng.normal(0, 0.004 * contrast, k))
            blocks.append(blk)
    # unlit: a black level of 0 and read noise, counts 0 or 1 (a step of about a count,
    # positive in half of them); more of them than lit ones, as in a frame seen
    for blk in range(40, 240):
        for _ in range(10):
            xs.append(np.arange(k) - 6 + 0.63)
            ys.append((rng.uniform(size=k) < 0.15).astype(float))
            blocks.append(blk)
    esf = frame_esf(
        EdgeProfiles(np.array(xs), np.array(ys), np.array(blocks)), start_width_px=0.6, drift=False
    )
    assert esf is not None
    inside = np.abs(esf.x) < 5.0
    np.testing.assert_allclose(esf.value[inside], _truth(esf.x[inside]), atol=0.006)
    # no bin is made of the unlit profiles' samples (phase 0.63)
    assert not np.any(np.isclose((esf.x + 6) % 1.0, 0.63, atol=0.01))


def _corner_profile(x: np.ndarray, along_px: float, radius_px: float) -> np.ndarray:
    """Across the vertical edge of a checkerboard corner (bright where x·y > 0) at
    ``along_px`` from the corner, blurred by a uniform disk of radius ``radius_px``."""
    g = (np.arange(160) + 0.5) / 160 * 2.0 - 1.0
    px, py = np.meshgrid(g * radius_px, g * radius_px)
    inside = px**2 + py**2 <= radius_px**2
    px, py = px[inside], py[inside]
    u, v = x[:, None] - px[None, :], along_px - py[None, :]
    return np.mean(u * v > 0, axis=1)


@pytest.mark.parametrize("radius_px", [2.0, 4.0])
def test_profiles_clear_of_the_corner_see_one_edge_only(radius_px: float) -> None:
    """A defocus disk is not separable: within its radius of the corner a profile across
    one edge also sees the other, and is not the edge's step response. At the clearance
    (the edges' flat distance for the disk's width, radius/2) it is, up to its levels; a
    fixed 3 px was not, for a disk of 8 px."""
    x = np.linspace(-8.0, 8.0, 161)
    step = _corner_profile(x, 40.0, radius_px)  # far along the edge: one edge only

    def misfit(along_px: float) -> float:
        profile = _corner_profile(x, along_px, radius_px)
        design = np.stack([np.ones_like(step), step], axis=1)
        coef, *_ = np.linalg.lstsq(design, profile, rcond=None)
        return float(np.max(np.abs(design @ coef - profile)) / abs(coef[1]))

    clearance = corner_clearance_px(radius_px / 2.0, minimum_px=3.0)
    assert clearance > radius_px
    assert misfit(clearance) < 1e-9
    if radius_px > 3.0:
        assert misfit(3.0) > 0.01
