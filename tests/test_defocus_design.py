"""The whole-sweep defocus fit's design (:class:`calibration.defocus_design.DefocusDesign`)
against a direct evaluation of the model it tabulates.

The reference here is written from the design's documented definition, not from its code:
the integral ``IC`` of the geometric kernel's cumulative line spread in closed form (box,
uniform disk and their mixture), averaged over each observation's placement jitter
(5-node Gauss-Hermite), each static node's mass spread over the triangle of two centred
moving averages (``np.convolve``), read at the four ends ``x̄ ± w ∓ g`` of every bin's
interval by NumPy's linear interpolation, ``A = [IC(x̄+w-g) - IC(x̄-w-g) + IC(x̄+w+g) -
IC(x̄-w+g)]/(4w)``. The design stores the part beyond the ramp in float32, so the two
agree to about 1e-6.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from calibration.defocus_design import (
    STATIC_STEP_PX,
    DefocusDesign,
    diameter_factor,
)

PITCH_PX = 50.0
N_BINS = 90


def _box_ic(t: np.ndarray, d: float) -> np.ndarray:
    """``∫C`` of a box of width ``d``: 0 below it, ``(t + d/2)²/(2d)`` across, ``t`` above."""
    inside = np.clip(t + 0.5 * d, 0.0, d)
    return np.where(t > 0.5 * d, t, inside**2 / (2.0 * d))


def _disk_ic(t: np.ndarray, d: float) -> np.ndarray:
    """``∫C`` of a uniform disk of diameter ``d`` (its line spread is a half-ellipse)."""
    u = np.clip(2.0 * t / d, -1.0, 1.0)
    root = np.sqrt(1.0 - u * u)
    across = 0.5 * d * (0.5 * u + (u * np.arcsin(u) + root) / np.pi - root**3 / (3.0 * np.pi))
    return np.where(t >= 0.5 * d, t, np.where(t <= -0.5 * d, 0.0, across))


def _reference_design(
    design: DefocusDesign,
    q: np.ndarray,
    jitter: np.ndarray,
    xbar: np.ndarray,
    half: np.ndarray,
    theta: tuple[float, float, float],
) -> np.ndarray:
    q0, kappa, alpha = theta
    lattice = design.lattice
    spacing = lattice[1] - lattice[0]
    taps = 2 * int(round(0.5 * STATIC_STEP_PX / spacing)) + 1
    triangle = np.convolve(np.ones(taps), np.ones(taps)) / taps**2
    nodes, weights = np.polynomial.hermite_e.hermegauss(5)
    weights = weights / weights.sum()
    grid = np.arange(design.shape[2]) * STATIC_STEP_PX
    out = np.empty(design.shape)
    for k in range(q.size):
        d = max(diameter_factor(kappa, alpha) * PITCH_PX * abs(q[k] - q0), 1e-9)
        shifts = zip(nodes, weights, strict=True) if jitter[k] > 0.01 else [(0.0, 1.0)]
        ic = sum(
            w
            * (
                alpha * _box_ic(lattice + z * jitter[k], d)
                + (1 - alpha) * _disk_ic(lattice + z * jitter[k], d)
            )
            for z, w in shifts
        )
        padded = np.pad(ic, taps - 1, mode="edge")
        spread = np.convolve(padded, triangle, mode="valid")
        w = np.maximum(half[k], 2 * design.LATTICE_PX)[:, None]
        x = xbar[k][:, None]
        read = [
            np.interp(end, lattice, spread)
            for end in (x + w - grid, x - w - grid, x + w + grid, x - w + grid)
        ]
        out[k] = (read[0] - read[1] + read[2] - read[3]) / (4.0 * w)
    return out


def _observations(seed: int, n: int = 12) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    q = 0.25 + rng.uniform(-0.04, 0.04, n)
    jitter = np.where(rng.random(n) < 0.4, rng.uniform(0.02, 0.15, n), 0.0)
    xbar = np.linspace(-4.45, 4.45, N_BINS)[None, :] + rng.uniform(-0.02, 0.02, (n, N_BINS))
    half = rng.uniform(0.0, 0.05, (n, N_BINS))
    return q, jitter, xbar, half


@pytest.mark.parametrize("alpha", [0.0, 0.4, 1.0])
def test_the_design_is_the_tabulated_model_read_at_every_interval_end(alpha: float) -> None:
    q, jitter, xbar, half = _observations(seed=int(10 * alpha))
    design = DefocusDesign(q, jitter, xbar, half, PITCH_PX)
    theta = (0.25, 0.9, alpha)
    got = design.design(np.array([*theta, 0.0]), np.arange(q.size))
    want = _reference_design(design, q, jitter, xbar, half, theta)
    assert np.ptp(want) > 0.5  # bins from the dark to the bright side, defocused to ~3 px
    assert_allclose(got, want, rtol=0, atol=2e-6)


def test_blocks_on_threads_and_a_subset_give_the_same_design() -> None:
    q, jitter, xbar, half = _observations(seed=3, n=11)
    theta = np.array([0.26, 0.95, 0.3, 0.0])
    whole = DefocusDesign(q, jitter, xbar, half, PITCH_PX).design(theta, np.arange(q.size))
    with ThreadPoolExecutor(2) as pool:
        blocked = DefocusDesign(q, jitter, xbar, half, PITCH_PX, pool=pool, blocks=3)
        assert len(blocked.blocks) == 3
        assert_array_equal(blocked.design(theta, np.arange(q.size)), whole)
        keep = np.array([0, 2, 3, 7, 10])
        subset = blocked.subset(keep)
        assert_array_equal(subset.design(theta, np.arange(keep.size)), whole[keep])


def test_bins_beyond_the_lattice_are_refused() -> None:
    q, jitter, xbar, half = _observations(seed=4, n=3)
    xbar[1, -1] = 9.0  # its interval's end at +g reaches 15 px, the lattice ends at 11.5
    with pytest.raises(ValueError, match="beyond the design's lattice"):
        DefocusDesign(q, jitter, xbar, half, PITCH_PX)
