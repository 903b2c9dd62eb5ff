"""An edge's slope measured on all of a frame's profiles across it (calibration.edge_slope).

Synthetic profiles, as :func:`calibration.edge_profiles.half_edge_profiles` cuts them:
blocks (one micro-image's half-edge) of rows along the edge, each row sampled at whole
pixels around the edge the lattice predicts, the true edge ``slope_error·t`` away (``t``
the row's distance along the edge from its micro-image's corner image). The correction
must come back within its standard error, the error must be honest over seeds, blocks
without an edge must not count, and on sharp pixel-locked edges the standard error must
say how little the profiles know.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from calibration.edge_slope import SlopeCorrection, refine_slope

DARK, LIGHT = 200.0, 3800.0


def _profiles(
    rng: np.random.Generator,
    *,
    slope_error: float,
    width_px: float,
    noise: float,
    blocks: int = 16,
    rows: int = 24,
    half_px: int = 6,
    point_sampled: bool = False,
) -> tuple[np.ndarray, ...]:
    """``(x, values, along, sign, block, half)`` of ``blocks`` blocks of ``rows`` rows."""
    offsets = np.arange(-half_px, half_px + 1, dtype=np.float64)
    xs, vs, alongs, signs, block_ids, halves = [], [], [], [], [], []
    for b in range(blocks):
        centre = rng.uniform(-110.0, 110.0)
        along = centre + np.arange(rows) - rows / 2.0
        sign = 1.0 if b % 2 == 0 else -1.0
        phase = rng.uniform(-0.5, 0.5)  # the predicted edge's sub-pixel position
        predicted = np.full(rows, phase)
        columns = np.rint(predicted)[:, None] + offsets[None, :]
        true_edge = predicted + slope_error * along
        dist = sign * (columns - true_edge[:, None])
        if point_sampled:
            # a sharp edge sampled at two points per pixel: locks to the pixel grid
            lit = 0.5 * ((dist - 0.25 > 0).astype(float) + (dist + 0.25 > 0).astype(float))
        else:
            lit = ndtr(dist / width_px)
        values = DARK + (LIGHT - DARK) * lit + rng.normal(0.0, noise, lit.shape)
        xs.append(sign * (columns - predicted[:, None]))
        vs.append(values)
        alongs.append(along)
        signs.append(np.full(rows, sign))
        block_ids.append(np.full(rows, b))
        halves.append((along > 0).astype(np.int64))
    return (
        np.concatenate(xs),
        np.concatenate(vs),
        np.concatenate(alongs),
        np.concatenate(signs),
        np.concatenate(block_ids).astype(np.int64),
        np.concatenate(halves),
    )


@pytest.mark.parametrize("slope_error", [0.0, 1.2e-3, -2.5e-3])
def test_a_slope_error_comes_back_from_blurred_profiles(slope_error: float) -> None:
    x, v, along, sign, block, half = _profiles(
        np.random.default_rng(1), slope_error=slope_error, width_px=0.7, noise=40.0
    )
    found = refine_slope(x, v, along, sign, block, half)
    assert np.isfinite(found.se) and found.se < 1e-4
    assert found.delta == pytest.approx(slope_error, abs=4 * found.se)


def test_its_standard_error_holds_over_seeds() -> None:
    """40 noisy frames: the errors over their standard errors have an RMS near 1."""
    z = []
    for seed in range(40):
        x, v, along, sign, block, half = _profiles(
            np.random.default_rng(100 + seed), slope_error=8e-4, width_px=0.8, noise=120.0
        )
        found = refine_slope(x, v, along, sign, block, half)
        z.append((found.delta - 8e-4) / found.se)
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.6 < rms < 1.5
    assert np.max(np.abs(z)) < 4.0


def test_blocks_without_an_edge_do_not_count() -> None:
    """Rows the frame does not show (an unrendered or unlit part: zeros), far along the
    edge where they would weigh most, leave the measured slope as it was."""
    rng = np.random.default_rng(7)
    x, v, along, sign, block, half = _profiles(rng, slope_error=1e-3, width_px=0.7, noise=40.0)
    clean = refine_slope(x, v, along, sign, block, half)
    dead = np.abs(along) > 90.0
    v_dead = v.copy()
    v_dead[dead] = rng.normal(0.3, 0.2, v_dead[dead].shape)
    kept = ~np.isin(block, np.unique(block[dead]))
    live_only = refine_slope(x[kept], v[kept], along[kept], sign[kept], block[kept], half[kept])
    with_dead = refine_slope(x, v_dead, along, sign, block, half)
    # (the live rows of partly dead blocks are in one set only: a little more data)
    assert with_dead.delta == pytest.approx(live_only.delta, abs=1.5 * live_only.se)
    assert clean.delta == pytest.approx(1e-3, abs=4 * clean.se)


def test_an_edge_mostly_outside_what_the_frame_shows_is_still_measured() -> None:
    """Most blocks unrendered and exactly dark (a renderer's window, a dark level without
    read noise): their contrast is exactly 0, so the median contrast of all blocks is 0;
    the edges the frame does show still give the slope (it once gave up, and the profiles
    kept the lattice's slope, 7e-3 off on a low-noise ray-traced frame)."""
    rng = np.random.default_rng(11)
    x, v, along, sign, block, half = _profiles(rng, slope_error=1.5e-3, width_px=0.7, noise=40.0)
    dead_blocks = np.arange(16) >= 6  # 10 of 16 blocks: well over half the profiles
    dead = dead_blocks[block]
    v_dead = v.copy()
    v_dead[dead] = 0.0
    live_only = refine_slope(
        x[~dead], v[~dead], along[~dead], sign[~dead], block[~dead], half[~dead]
    )
    with_dead = refine_slope(x, v_dead, along, sign, block, half)
    assert np.isfinite(with_dead.se)
    assert with_dead.delta == pytest.approx(live_only.delta, abs=1e-9)
    assert with_dead.delta == pytest.approx(1.5e-3, abs=4 * with_dead.se)


def test_pixel_locked_edges_say_how_little_they_know() -> None:
    """Sharp edges sampled at two points per pixel: each block's edge is locked to the
    pixel grid, its rows move together. The (block-clustered) standard errors are far
    larger than on blurred edges and the errors over seeds stay within a few of them
    (from 16 blocks they run ~1.5x small: the lattice's own slope, weighed against them,
    keeps most of its say)."""
    z, se = [], []
    for seed in range(12):
        x, v, along, sign, block, half = _profiles(
            np.random.default_rng(300 + seed),
            slope_error=5e-4,
            width_px=0.0,
            noise=20.0,
            point_sampled=True,
        )
        found = refine_slope(x, v, along, sign, block, half)
        if np.isfinite(found.se):
            z.append((found.delta - 5e-4) / found.se)
            se.append(found.se)
    assert len(z) >= 10
    assert float(np.sqrt(np.mean(np.square(z)))) < 2.0
    assert np.max(np.abs(z)) < 5.0
    assert np.median(se) > 1e-4


def test_the_lattice_and_the_profiles_are_weighed_by_their_variances() -> None:
    measured = SlopeCorrection(delta=1e-3, se=1e-4)
    assert measured.combined(float("inf")) == pytest.approx((1e-3, 1e-8))
    delta, var = measured.combined(1e-8)  # the lattice as good as the profiles: halfway
    assert delta == pytest.approx(5e-4) and var == pytest.approx(5e-9)
    delta, var = measured.combined(1e-10)  # a far better lattice keeps its slope
    assert abs(delta) < 1.1e-5
    unknown = SlopeCorrection(0.0, float("nan"))
    assert unknown.combined(4e-8) == (0.0, 4e-8)


def test_too_few_profiles_keep_the_lattices_slope() -> None:
    x, v, along, sign, block, half = _profiles(
        np.random.default_rng(3), slope_error=1e-3, width_px=0.7, noise=40.0, blocks=1, rows=10
    )
    found = refine_slope(x, v, along, sign, block, half)
    assert found.delta == 0.0 and np.isnan(found.se)
