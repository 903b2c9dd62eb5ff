"""The levels of flat-fielded edge profiles read at fixed points of a shared tail shape."""

import numpy as np
from numpy.testing import assert_allclose

from calibration.edge_levels import levels_with_tail_shape


def _tail_shape(x: np.ndarray, x_flat: float, coef: tuple[float, ...]) -> np.ndarray:
    """OPTICS-free model of ``levels_with_tail_shape``: 1 plus a parabola in ``x - r`` on the
    light tail, a parabola in ``x + r`` on the dark one (0 plus it), ``r = x_flat + 1``."""
    r = x_flat + 1.0
    light, dark = x >= x_flat, x <= -x_flat
    t = np.where(light, 1.0 + coef[0] * (x - r) + coef[2] * (x - r) ** 2, 0.0)
    return t + np.where(dark, coef[1] * (x + r) + coef[3] * (x + r) ** 2, 0.0)


def test_levels_and_the_tails_shape_are_recovered_exactly() -> None:
    """Profiles at random sampling phases, each with its own levels, whose tails fall off
    with a shape the frame shares: every contrast and every mapped sample comes back to
    1e-9 (the shape's four coefficients are fitted, the levels projected out)."""
    rng = np.random.default_rng(0)
    x_flat = 3.0
    x = np.arange(-9, 10)[None, :] + rng.uniform(-0.5, 0.5, (300, 1))
    coef = (-0.012, 0.006, -0.0015, 0.0009)
    background = rng.uniform(20.0, 80.0, 300)
    contrast = rng.uniform(300.0, 900.0, 300)
    shape = _tail_shape(x, x_flat, coef)
    y = background[:, None] + contrast[:, None] * shape
    z, c = levels_with_tail_shape(x, y, x_flat)
    assert_allclose(c, contrast, rtol=1e-9)
    tails = np.abs(x) >= x_flat
    assert_allclose(z[tails], shape[tails], atol=1e-9)


def test_profiles_without_two_samples_in_each_tail_have_no_contrast() -> None:
    """A profile whose dark tail has one sample does not give its contrast (NaN), and the
    others' still come back exact."""
    rng = np.random.default_rng(1)
    x_flat = 3.0
    x = np.arange(-9, 10)[None, :] + rng.uniform(-0.5, 0.5, (50, 1))
    x[0] = np.linspace(-3.5, 9.0, 19)  # one dark-tail sample (at -3.5)
    coef = (-0.01, 0.004, -0.001, 0.0005)
    contrast = rng.uniform(300.0, 900.0, 50)
    y = 40.0 + contrast[:, None] * _tail_shape(x, x_flat, coef)
    z, c = levels_with_tail_shape(x, y, x_flat)
    assert np.isnan(c[0])
    assert_allclose(c[1:], contrast[1:], rtol=1e-9)
