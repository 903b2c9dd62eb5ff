"""Batched edge-spread fits against synthetic profiles with known ground truth."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.special import ndtr

from calibration.edge_fit import fit_edges


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
