"""Edge profiles cut by a corner's lattice from every micro-image that shows its half-edges.

A synthetic frame of micro-images, each showing the standard corner where the
disparity model puts it (``s = (1+Q)·m + c``), blurred by a known Gaussian:
the profiles, placed against the predicted edges and pooled, must give back
that edge spread; they must come from micro-images beyond those that contain
the corner; and the placement jitter must count only how the placement errors
spread over the profiles, not their common shift.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from calibration.edge_profiles import (
    CornerLattice,
    ProfileWindow,
    _placement_jitter,
    half_edge_profiles,
)
from calibration.edge_spread import frame_esf
from calibration.lens_grid import LensGrid

PITCH, Q, SIGMA, RADIUS = 40.0, 0.25, 0.7, 14.0
DARK, LIGHT = 100.0, 900.0


def _frame(
    *, width: int = 720, height: int = 480, corner: tuple[float, float] = (-3.3, 2.6)
) -> tuple[np.ndarray, LensGrid, LensGrid, tuple[float, float, float]]:
    """Micro-images on a lens lattice; each shows the corner at ``s = (1+Q)·m + c``."""
    lens = LensGrid((361.2, 239.7), PITCH, np.radians(0.3))
    image = LensGrid(lens.origin_px, PITCH * 1.02, lens.rotation_rad)  # centres ≈ (L+b)/L apart
    # the main image of the corner, r, sits at `corner` (in lens pitches) from lens (0, 0)
    rx, ry = lens.centre(*corner)
    coef = (1.0 + Q, -Q * float(rx), -Q * float(ry))
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    i, j = image.nearest(xx, yy)
    cx, cy = image.centre(i, j)
    mx, my = lens.centre(i, j)
    sx, sy = coef[0] * mx + coef[1], coef[0] * my + coef[2]
    u, v = ndtr((xx - sx) / SIGMA), ndtr((yy - sy) / SIGMA)
    light = u * (1 - v) + (1 - u) * v  # the standard corner: dark where x, y have one sign
    frame = DARK + (LIGHT - DARK) * light
    frame[np.hypot(xx - cx, yy - cy) > 0.5 * image.pitch_px - 1] = 10.0  # dark gaps
    rng = np.random.default_rng(3)
    return frame + rng.normal(0.0, 2.0, frame.shape), lens, image, coef


def _window() -> ProfileWindow:
    return ProfileWindow(plateau_px=RADIUS, clearance_px=3.0, reach_px=400.0, half_px=6)


def test_profiles_of_every_micro_image_give_back_the_edge_spread() -> None:
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    profiles, jitter = half_edge_profiles(frame, lattice, lens, image, _window())
    assert jitter == 0.0
    esf = frame_esf(profiles, start_width_px=SIGMA)
    assert esf is not None
    inside = np.abs(esf.x) < 4.0
    np.testing.assert_allclose(esf.value[inside], ndtr(esf.x[inside] / SIGMA), atol=0.004)
    # the blocks come from many more micro-images than the few that show the corner itself
    assert int(profiles.block.max()) + 1 > 40


def test_no_profile_reaches_the_corner_or_leaves_the_plateau() -> None:
    frame, lens, image, coef = _frame()
    window = _window()
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    profiles, _ = half_edge_profiles(frame, lattice, lens, image, window)
    # a profile through the corner's other edge, or through a dark gap, would not be a
    # clean step: every profile is flat at both ends
    z = (profiles.y - DARK) / (LIGHT - DARK)
    first, last = z[:, :2], z[:, -2:]
    assert np.all(np.minimum(np.abs(first), np.abs(first - 1.0)) < 0.05)
    assert np.all(np.minimum(np.abs(last), np.abs(last - 1.0)) < 0.05)
    assert np.all(np.abs(first.mean(axis=1) - last.mean(axis=1)) > 0.9)


def test_an_error_of_the_lattice_offset_blurs_the_pooled_function() -> None:
    """The halves of an edge on either side of the corner have opposite polarity, so an
    error of ``c`` moves their profiles' signed distances in opposite directions: it
    spreads them by its whole size."""
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.diag([0.0, 0.04, 0.04]))
    _, jitter = half_edge_profiles(frame, lattice, lens, image, _window())
    assert jitter == pytest.approx(0.2, rel=0.1)


def test_an_error_of_1_plus_q_blurs_by_the_lenses_spread() -> None:
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.diag([1e-6, 0.0, 0.0]))
    _, jitter = half_edge_profiles(frame, lattice, lens, image, _window())
    # lens centres spread over the frame by about ±300 px: a 1e-3 error of 1+Q, ~0.2 px
    assert 0.1 < jitter < 0.3


def test_a_shift_common_to_every_profile_is_not_counted_as_jitter() -> None:
    """The defocus model fits each function's position; only the spread about it blurs."""
    sigma = np.diag([0.0, 0.0, 0.0, 0.01, 0.0])
    same = np.tile([0.0, 0.0, 0.0, 1.0, 0.0], (50, 1))
    assert _placement_jitter(same, sigma) == pytest.approx(0.0, abs=1e-12)
    mixed = same * np.repeat([1.0, -1.0], 25)[:, None]
    assert _placement_jitter(mixed, sigma) == pytest.approx(0.1)
