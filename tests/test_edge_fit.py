"""Batched edge-spread fits against synthetic profiles with known ground truth."""

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal
from scipy.special import ndtr

from calibration.edge_fit import fit_edges, fit_edges_symmetric, symmetric_about_edges


def _pixel_integrated_step(t: np.ndarray, t0: np.ndarray, w: np.ndarray, n_sub: int = 200):
    """Blurred step averaged over each pixel [t-1/2, t+1/2] by brute-force sub-sampling."""
    sub = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    tt = t[None, :, None] + sub[None, None, :]
    return ndtr((tt - t0[:, None, None]) / w[:, None, None]).mean(axis=2)


def _random_steps(seed: int, n: int, t0_range: tuple[float, float], w_range: tuple[float, float]):
    """``n`` noiseless 13-sample profiles (background 100, contrast 2500) of steps at random
    positions and widths: ``(t, t0, w, y)``."""
    rng = np.random.default_rng(seed)
    t = np.arange(13, dtype=float)
    t0 = rng.uniform(*t0_range, n)
    w = rng.uniform(*w_range, n)
    return t, t0, w, 100.0 + 2500.0 * _pixel_integrated_step(t, t0, w)


def test_positions_and_widths_recovered_without_noise() -> None:
    t, t0, w, y = _random_steps(0, 400, (4.5, 7.5), (0.3, 1.5))
    fits = fit_edges(y)
    assert fits.ok.all()
    assert_allclose(fits.position, t0, atol=2e-3)
    assert_allclose(fits.width, w, atol=5e-3)
    assert_allclose(fits.contrast, 2500.0, rtol=1e-3)


def test_falling_edges_and_noise_match_reported_uncertainty() -> None:
    rng = np.random.default_rng(1)
    n, k = 4000, 13
    t = np.arange(k, dtype=float)
    t0 = rng.uniform(5.0, 7.0, n)
    w = np.full(n, 0.6)
    clean = 3000.0 - 2800.0 * _pixel_integrated_step(t, t0, w, n_sub=50)
    y = clean + rng.normal(0.0, 25.0, clean.shape)
    fits = fit_edges(y)
    assert fits.ok.mean() > 0.99
    err = fits.position[fits.ok] - t0[fits.ok]
    assert abs(err.mean()) < 2e-3  # unbiased
    # the reported standard error describes the actual scatter
    assert_allclose(err.std(), np.median(fits.position_se[fits.ok]), rtol=0.15)
    assert (fits.contrast[fits.ok] < 0).all()


def test_flat_profiles_are_not_ok() -> None:
    rng = np.random.default_rng(2)
    y = 1000.0 + rng.normal(0.0, 5.0, (50, 13))
    fits = fit_edges(y)
    # a flat profile has no edge: positions fall outside or widths explode
    assert fits.ok.mean() < 0.5 or np.all(np.abs(fits.contrast) < 50)


def test_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="at least 5 samples"):
        fit_edges(np.zeros((3, 4)))
    with pytest.raises(ValueError, match="2-D"):
        fit_edges(np.zeros(13))


def test_samples_left_out_do_not_move_the_edge() -> None:
    """A profile whose last samples reach into a micro-image's rim (the light falls off
    there) is fitted on the samples it keeps: the edge where it is; fitted whole, the
    falling level moves it."""
    t, t0, _, y = _random_steps(2, 200, (5.5, 6.5), (0.4, 0.8))
    rim = np.clip(1.0 - 0.15 * (t - 9.0), None, 1.0)  # the last three samples fall off
    y = 100.0 + (y - 100.0) * rim[None, :]
    valid = np.broadcast_to(t < 10.0, y.shape)
    kept = fit_edges(y, valid=valid)
    whole = fit_edges(y)
    assert kept.ok.all()
    assert_allclose(kept.position, t0, atol=2e-3)
    assert_allclose(kept.contrast, 2500.0, rtol=1e-3)
    assert np.mean(np.abs(whole.position - t0)) > 0.01


def test_valid_must_match_the_profiles() -> None:
    with pytest.raises(ValueError, match="shape"):
        fit_edges(np.ones((3, 13)), valid=np.ones((3, 12), dtype=bool))


def _long_tailed_steps(t0: np.ndarray, *, tail: float, n_sub: int = 200) -> np.ndarray:
    """13-sample profiles (background 100, contrast 2500) of steps at ``t0`` blurred by a
    symmetric spread with long tails, as diffraction's: a Gaussian of σ 0.7 px carrying
    ``1 − tail`` of the light and a Cauchy of half-width 1.5 px (tails falling as 1/x²)
    carrying ``tail``; averaged over each pixel by sub-sampling."""
    t = np.arange(13, dtype=float)
    sub = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    x = t[None, :, None] + sub[None, None, :] - t0[:, None, None]
    spread = (1.0 - tail) * ndtr(x / 0.7) + tail * (0.5 + np.arctan(x / 1.5) / np.pi)
    return 100.0 + 2500.0 * spread.mean(axis=2)


def test_symmetric_windows_keep_the_samples_whose_mirror_about_the_edge_is_kept() -> None:
    valid = np.ones((3, 13), dtype=bool)
    valid[:, :2] = False  # the first two samples cut off (the rim)
    window = symmetric_about_edges(valid, np.array([6.0, 6.4, 5.3]))
    expected = np.ones((3, 13), dtype=bool)
    expected[:, :2] = False
    expected[0, 11:] = False  # mirrored about 6: 0, 1 ↔ 12, 11
    expected[1, 12] = False  # about 6.5 (the nearest half sample): 1 ↔ 12, 0 ↔ 13 (outside)
    expected[2, 10:] = False  # about 5.5: 10, 11 ↔ 1, 0 (cut off), 12 ↔ −1 (outside)
    assert_array_equal(window, expected)
    # an edge not located (a failed fit) has no mirror: nothing is kept
    assert not symmetric_about_edges(valid[:1], np.array([np.nan])).any()


def test_a_long_tailed_edge_cut_on_one_side_is_read_where_it_is_on_a_symmetric_window() -> None:
    """A window cut on one side reads the shorter side's level where a long-tailed blur has
    not settled yet, which moves the fitted edge towards the longer side; the symmetric
    window's departures from the Gaussian model pull both ways equally."""
    t0 = np.random.default_rng(3).uniform(5.5, 6.5, 300)
    y = _long_tailed_steps(t0, tail=0.3)
    valid = np.ones(y.shape, dtype=bool)
    valid[:, :2] = False
    cut = fit_edges(y, valid=valid)
    symmetric = fit_edges_symmetric(y, valid=valid, min_samples=7)
    assert cut.ok.all() and symmetric.ok.all()
    assert np.mean(cut.position - t0) > 0.008  # measured +0.012 px
    assert abs(np.mean(symmetric.position - t0)) < 0.002  # measured 0.0000 px
    whole = fit_edges_symmetric(y, valid=np.ones(y.shape, dtype=bool), min_samples=7)
    assert abs(np.mean(whole.position - t0)) < 0.002


def test_on_gaussian_edges_the_symmetric_window_changes_nothing_but_the_noise() -> None:
    """Gaussian steps (the model exact): the edges where they are on any window, and each
    fit's standard error still describes its scatter under noise."""
    t, t0, _, y = _random_steps(4, 300, (5.5, 6.5), (0.4, 1.2))
    valid = np.broadcast_to(t >= 2.0, y.shape)
    exact = fit_edges_symmetric(y, valid=valid, min_samples=7)
    assert exact.ok.all()
    assert_allclose(exact.position, t0, atol=2e-3)
    rng = np.random.default_rng(5)
    _, t0, _, y = _random_steps(6, 4000, (5.5, 6.5), (0.6, 0.6))
    valid = np.broadcast_to(t >= 2.0, y.shape)
    noisy = fit_edges_symmetric(y + rng.normal(0.0, 40.0, y.shape), valid=valid, min_samples=7)
    err = noisy.position[noisy.ok] - t0[noisy.ok]
    assert noisy.ok.mean() > 0.99
    assert abs(err.mean()) < 2e-3
    assert_allclose(err.std(), np.median(noisy.position_se[noisy.ok]), rtol=0.15)


def test_a_symmetric_window_too_short_to_fit_keeps_the_window_given() -> None:
    """Four samples cut off an edge near 5.5–6: the symmetric window would keep fewer than
    ``min_samples``, so the profile is fitted on the samples it has, as by ``fit_edges``."""
    t0 = np.random.default_rng(7).uniform(5.5, 6.0, 50)
    y = _long_tailed_steps(t0, tail=0.3)
    valid = np.ones(y.shape, dtype=bool)
    valid[:, :4] = False
    assert_allclose(
        fit_edges_symmetric(y, valid=valid, min_samples=7).position,
        fit_edges(y, valid=valid).position,
        atol=1e-4,
    )


def test_a_fit_started_from_given_parameters_converges_where_the_guess_does() -> None:
    """``initial`` starts each fit from those parameters; a row whose parameters are not
    finite starts from the profile's own guess."""
    t, t0, w, y = _random_steps(8, 40, (5.0, 7.0), (0.4, 1.2))
    first = fit_edges(y, max_iter=2)
    position = first.position.copy()
    position[:5] = np.nan
    fits = fit_edges(y, initial=dataclasses.replace(first, position=position))
    assert fits.ok.all()
    assert_allclose(fits.position, t0, atol=2e-3)
    assert_allclose(fits.width, w, atol=5e-3)
