"""The defocus fit's jackknife over blocks of the sweep (:func:`jackknife_defocus`).

Edge-spread functions built by numerical convolution of the physics
(:mod:`tests.test_defocus`): on a sweep the blur model describes, the jackknife agrees
with the model's uncertainty and leaves it alone; on a sweep whose first frames were
taken with the focus elsewhere (the board slipped on its mount, then settled), the
model's own uncertainty misses the error by many sigma at a reduced chi-square near
one, and the jackknife must see it, say so and carry it.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
from scipy.stats import norm
from test_defocus import LENS_PITCH_PX, Q0, Q_SWEEP, _esf

from calibration.defocus import (
    JACKKNIFE_BLOCKS,
    JACKKNIFE_FALSE_ALARM,
    EdgeObservation,
    fit_defocus,
    jackknife_defocus,
    jackknife_warning,
)
from calibration.defocus_problem import DefocusProblem
from calibration.edge_spread import BinnedEsf

QS = Q_SWEEP[::2]  # 25 frames, focus near frame 9


def _sweep(seed: int, *, slipped_frames: int = 0, slip_q: float = 0.0) -> list[EdgeObservation]:
    """Noisy binned edge spreads (0.003 of the contrast per 0.1 px bin, 40 samples at random
    sub-pixel phases each); the first ``slipped_frames`` frames in focus at ``Q0 + slip_q``."""
    rng = np.random.default_rng(seed)
    centres = np.arange(-5.95, 6.0, 0.1)
    fine = np.arange(-6.1, 6.1, 0.005)
    noise = 0.003
    obs = []
    for k, q in enumerate(QS):
        q0 = Q0 + (slip_q if k < slipped_frames else 0.0)
        samples = (centres[:, None] + rng.uniform(-0.05, 0.05, (centres.size, 40))).ravel()
        curve = _esf(fine, LENS_PITCH_PX * abs(q - q0), sigma_px=0.4)
        value = np.interp(samples, fine, curve).reshape(centres.size, -1).mean(axis=1)
        value += rng.normal(0.0, noise, centres.size)
        esf = BinnedEsf(
            centres, value, np.full(centres.size, noise), np.full(centres.size, 40), 200
        )
        obs.append(EdgeObservation(k, "standard", float(q), esf))
    return obs


def test_the_jackknife_agrees_with_the_model_on_edges_it_describes() -> None:
    obs = _sweep(7)
    fit = fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX)
    jack = jackknife_defocus(obs, fit, lens_pitch_px=LENS_PITCH_PX)
    assert len(jack.jackknife_Q0) == len(jack.jackknife_z) == JACKKNIFE_BLOCKS
    critical = norm.isf(JACKKNIFE_FALSE_ALARM / (2 * JACKKNIFE_BLOCKS))
    assert np.max(np.abs(jack.jackknife_z)) <= critical
    assert jack.jackknife_consistent is True
    # the uncertainty stays the model's, Q0 is untouched, nothing to warn about
    assert jack.Q0_se == fit.Q0_se == jack.Q0_se_model
    assert jack.Q0 == fit.Q0
    assert jackknife_warning(jack, LENS_PITCH_PX) is None
    # the two estimates of the statistical uncertainty agree within their noise
    statistical = max(fit.Q0_se_curvature, fit.Q0_se_cluster)
    assert 0.3 <= jack.Q0_se_jackknife / statistical <= 3.0
    assert abs(fit.Q0 - Q0) <= 3 * jack.Q0_se


def test_the_jackknife_carries_a_focus_that_moved_during_the_sweep() -> None:
    """The first 4 of 25 frames in focus 0.003 lower in Q (about 13 mm of rail on the
    paper's optics): the model's fit lands between, 8 of its own sigma from where the
    other 21 frames put the focus, with a reduced chi-square near 1; leaving the first
    block out moves Q0 by tens of sigma of the difference."""
    obs = _sweep(3, slipped_frames=4, slip_q=-0.003)
    fit = fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX)
    assert fit.chi2_reduced < 1.2  # the misfit does not show in the chi-square
    assert abs(fit.Q0 - Q0) > 4 * fit.Q0_se  # and the model's uncertainty misses it
    jack = jackknife_defocus(obs, fit, lens_pitch_px=LENS_PITCH_PX)
    assert jack.jackknife_consistent is False
    assert abs(jack.jackknife_z[0]) > 10  # the first block: the slipped frames
    assert jack.Q0 == fit.Q0
    assert jack.Q0_se == jack.Q0_se_jackknife > 4 * fit.Q0_se
    assert abs(jack.Q0 - Q0) <= 2 * jack.Q0_se
    warning = jackknife_warning(jack, LENS_PITCH_PX)
    assert warning is not None and "left out" in warning and "jackknife" in warning


def test_a_sweep_too_short_for_blocks_is_left_alone() -> None:
    obs = _sweep(5)[5:10]  # 5 frames: fewer than 3 blocks of 2
    fit = fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX, min_blur_px=0.0)
    jack = jackknife_defocus(obs, fit, lens_pitch_px=LENS_PITCH_PX)
    assert jack is fit
    assert jack.jackknife_consistent is None and np.isnan(jack.Q0_se_jackknife)


def _jittered_problem(seed: int) -> tuple[list[EdgeObservation], DefocusProblem]:
    """A noisy sweep whose every third observation's edge is placed with a jitter the model
    averages over, and its problem in one block with noise scales from 1 to 2."""
    obs = [
        replace(o, esf=replace(o.esf, jitter_px=0.05)) if k % 3 == 0 else o
        for k, o in enumerate(_sweep(seed))
    ]
    problem = DefocusProblem(obs, LENS_PITCH_PX)
    problem.scale_noise(np.linspace(1.0, 2.0, len(obs)))
    return obs, problem


def test_blocks_of_observations_on_threads_give_the_residuals_of_one_block() -> None:
    """An evaluation cut into contiguous blocks of observations on a thread pool (the
    whole-sweep fit's) gives the residuals of the problem in one block: each block's rows of
    the design read its own lattice rows, for the geometric, blended and wave-optical
    kernels, with and without placement jitter; a jackknife's refit of it is one block."""
    obs, one = _jittered_problem(4)
    scales = one.noise_scale
    rows = np.arange(len(obs))
    with ThreadPoolExecutor(2) as pool:
        for blocks in (2, 3):
            cut = DefocusProblem(obs, LENS_PITCH_PX, pool=pool, blocks=blocks)
            cut.scale_noise(scales)
            assert len(cut.blocks) == blocks
            for theta in ([Q0, 0.9, 0.5, 0.0], [Q0 + 0.002, 0.6, 0.0, 0.3], [Q0, 1.0, 1.0, 2.5]):
                t = np.array(theta)
                assert_allclose(cut.residuals(t, rows), one.residuals(t, rows), rtol=0, atol=1e-9)
        assert len(cut.without(np.array([0])).blocks) == 1


def test_a_block_left_out_is_the_problem_built_without_it() -> None:
    """The jackknife's refits slice the full problem (:meth:`DefocusProblem.without`) instead
    of building it again: the same data, lattice rows and residuals as a problem built from
    the remaining observations, whatever noise scales the full one carries."""
    obs, full = _jittered_problem(3)
    scales = full.noise_scale.copy()
    dropped = np.array([0, 5, 6, 24])
    keep = np.setdiff1d(np.arange(len(obs)), dropped)
    sub = full.without(dropped)
    built = DefocusProblem([obs[k] for k in keep], LENS_PITCH_PX)
    assert [o.frame for o in sub.obs] == keep.tolist()
    assert_array_equal(sub.noise_scale, scales[keep])
    sub.scale_noise(np.ones(keep.size))
    rows = np.arange(keep.size)
    for theta in ([Q0, 0.9, 0.5, 0.0], [Q0 + 0.002, 0.6, 0.0, 0.3], [Q0 - 0.003, 1.0, 1.0, 2.5]):
        t = np.array(theta)
        assert_array_equal(sub.residuals(t, rows), built.residuals(t, rows))
    assert sub.data_scale == built.data_scale
    assert full.shape[0] == len(obs)  # the full problem is left as it was
