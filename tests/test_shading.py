"""The angular shading of micro-images, measured on a constructed white image.

Micro-images are discs on a lattice; inside each, the intensity falls off as
``exp(-(c/2)·|s - m|²)`` about the lens-centre projection ``m``, which for
off-axis micro-images is not the micro-image centre (so each disc also has a
tilt). The measured curvature must be ``c`` whatever the tilt, and the
disparity bias it implies, ``η = Var(aperture)·c``, follows.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import convolve1d

from calibration.lens_grid import LensGrid
from calibration.shading import measure_shading
from calibration.white_rings import measure_plateau

PITCH_PX = 60.0
SCALE = 1.05  # micro-image centres lie (L+b)/L farther from the principal point


def _lens_grid(h: int = 600, w: int = 900) -> LensGrid:
    pp = ((w - 1) / 2, (h - 1) / 2)
    return LensGrid((pp[0] + 3.2, pp[1] - 1.7), PITCH_PX, np.radians(0.3))


def _white(curvature: float, seed: int = 0, noise: float = 0.005) -> tuple[np.ndarray, LensGrid]:
    h, w = 600, 900
    pp = ((w - 1) / 2, (h - 1) / 2)
    lens = _lens_grid(h, w)
    image = lens.scaled_about(pp, SCALE)
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    i, j = image.nearest(xs, ys)
    cx, cy = image.centre(i, j)
    mx, my = lens.centre(i, j)
    r = np.hypot(xs - cx, ys - cy)
    disc = np.clip((0.5 * image.pitch_px - r) / 2.0, 0.0, 1.0)  # soft rim
    shade = np.exp(-0.5 * curvature * ((xs - mx) ** 2 + (ys - my) ** 2))
    rng = np.random.default_rng(seed)
    white = 3000.0 * disc * shade * (1 + rng.normal(0, noise, disc.shape)) + 40.0
    return white, image


@pytest.mark.parametrize("curvature", [0.0, 3e-6, 2e-5])
def test_the_curvature_of_the_shading_is_measured(curvature: float) -> None:
    white, image = _white(curvature)
    found = measure_shading(white, image, background=40.0)
    assert found.micro_images > 50
    assert found.curvature_px2 == pytest.approx(
        curvature, abs=max(3 * found.curvature_se_px2, 2e-7)
    )
    assert found.curvature_se_px2 < 5e-7
    assert not found.tilt_measured  # no lens grid given
    tilted = measure_shading(white, image, background=40.0, lens_grid=_lens_grid())
    # the micro-images' tilt across the sensor measures the same curvature
    assert tilted.tilt_curvature_px2 == pytest.approx(
        curvature, abs=3 * tilted.tilt_curvature_se_px2
    )
    assert tilted.tilt_curvature_se_px2 < 5e-7
    assert tilted.tilt_consistent and tilted.interior_consistent
    c, se = tilted.angular_curvature()  # both, weighted
    assert min(found.curvature_se_px2, tilted.tilt_curvature_se_px2) > se
    assert c == pytest.approx(curvature, abs=3 * se)


def test_the_bias_coefficient_is_the_aperture_variance_times_the_curvature() -> None:
    white, image = _white(3e-6, seed=1)
    found = measure_shading(white, image, background=40.0)
    variance = PITCH_PX**2 / 12.0
    assert found.bias_coefficient(variance) == pytest.approx(
        variance * 3e-6, abs=3 * variance * found.curvature_se_px2
    )
    assert found.to_dict()["micro_images"] == found.micro_images


def test_a_dark_frame_gives_no_measurement() -> None:
    _, image = _white(0.0)
    found = measure_shading(np.zeros((600, 900)), image)
    assert found.micro_images == 0 or not np.isfinite(found.curvature_px2)


def _falling_beyond(white: np.ndarray, image: LensGrid, plateau: float) -> np.ndarray:
    """``white`` (dark level 40) falling linearly from ``plateau`` (fraction of half the
    pitch) to zero at the micro-images' rims."""
    h, w = white.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    i, j = image.nearest(xs, ys)
    cx, cy = image.centre(i, j)
    r = np.hypot(xs - cx, ys - cy) / (0.5 * image.pitch_px)
    return (white - 40.0) * np.clip(1.0 - (r - plateau) / (1.0 - plateau), 0.0, 1.0) + 40.0


@pytest.mark.parametrize("plateau", [0.55, 0.7])
def test_the_fully_lit_plateau_ends_where_the_white_image_falls_off(plateau: float) -> None:
    """Beyond the plateau the microlens aperture is clipped by the main aperture and the
    white image falls (here linearly to the rim); the shading inside must not be taken for it."""
    white, image = _white(3e-6, seed=2)
    half = 0.5 * image.pitch_px
    lit = _falling_beyond(white, image, plateau)
    found = measure_plateau(lit, image, background=40.0)
    # the first 0.5 px bin that has fallen by 0.1 % starts within a bin of the true edge
    assert plateau - 0.5 / half - 0.01 <= found <= plateau + 0.01
    assert measure_shading(lit, image, background=40.0).plateau_fraction == found


@pytest.mark.parametrize("plateau", [0.55, 0.7])
def test_the_flat_field_follows_the_white_s_fall_beyond_the_plateau(plateau: float) -> None:
    """On the plateau the flat field is the curvature's paraboloid; beyond it, where the white
    falls (here linearly to the rim), the rings' measured fall, continuing from the
    paraboloid: within 1 % of the white's own ``log W`` wherever it keeps 40 % of its light."""
    curvature = 3e-6
    white, image = _white(curvature, seed=6, noise=0.002)
    half = 0.5 * image.pitch_px
    lit = _falling_beyond(white, image, plateau)
    found = measure_shading(lit, image, background=40.0)
    flat = found.flat_field(40.0)
    assert flat is not None and flat.radial_px
    radius = np.linspace(0.0, 0.95 * half, 200)
    fall = np.clip(1.0 - (radius / half - plateau) / (1.0 - plateau), 0.0, 1.0)
    measured = radius <= found.radial_px[-1]
    assert np.all(measured[fall >= 0.4])  # the rings reach wherever 40 % of the light is left
    zero = (np.zeros_like(radius), np.zeros_like(radius))
    bowl = flat.log_shading((radius, np.zeros_like(radius)), zero)
    on = radius <= found.plateau_fraction * half
    np.testing.assert_allclose(bowl[on], -0.5 * found.curvature_px2 * radius[on] ** 2, atol=1e-6)
    truth = np.log(np.maximum(fall, 1e-9)) - 0.5 * curvature * radius**2
    check = fall >= 0.4
    np.testing.assert_allclose(bowl[check], truth[check], atol=0.01)
    # the paraboloid alone misses the fall by far more
    assert np.max(np.abs(-0.5 * found.curvature_px2 * radius[check] ** 2 - truth[check])) > 0.5


def _diffraction_blurred(
    image: np.ndarray, first_zero_px: float, *, half_px: int = 40
) -> np.ndarray:
    """``image`` through a diffraction-limited square microlens aperture: convolved on the
    sensor with the separable ``sinc²(x/s)·sinc²(y/s)`` (first zeros at ``±s`` =
    ``first_zero_px``, cut at ``half_px``, normalised; the borders extended)."""
    x = np.arange(-half_px, half_px + 1, dtype=float)
    line = np.sinc(x / first_zero_px) ** 2
    line /= line.sum()
    once = convolve1d(np.asarray(image, dtype=np.float64), line, axis=0, mode="nearest")
    return convolve1d(once, line, axis=1, mode="nearest")


def test_a_rim_blurred_into_the_interior_is_not_taken_for_angular_shading() -> None:
    """Diffraction spreads each micro-image's rim into its interior (1/x² tails), which bends
    log W more towards the rim: the curvature then depends on the radius it is fitted over,
    and the angular part is only known to lie between 0 and the measured curvature."""
    curvature = 3e-6
    white, image = _white(curvature, seed=3, noise=0.002)
    clean = measure_shading(white, image, background=40.0)
    assert clean.radially_consistent
    assert clean.angular_curvature() == (clean.curvature_px2, clean.curvature_se_px2)
    blurred = _diffraction_blurred(white - 40.0, 2.5) + 40.0
    found = measure_shading(blurred, image, background=40.0)
    assert found.curvature_px2 > 3 * curvature  # the rim's tails, not the rays' angles
    assert not found.radially_consistent
    c, se = found.angular_curvature()
    assert abs(c - curvature) <= se  # the true angular curvature is covered
    assert found.to_dict()["radially_consistent"] is False


def test_the_tilt_of_the_micro_images_separates_angular_shading_from_a_blurred_rim() -> None:
    """A rim blurred into the interior bends log W symmetrically about each micro-image's
    centre; the angular shading is centred on the lens centre, so it also tilts the
    off-axis micro-images, by ``-c·(c_i - m_i)``: that tilt is the angular curvature."""
    curvature = 3e-6
    white, image = _white(curvature, seed=4, noise=0.002)
    blurred = _diffraction_blurred(white - 40.0, 2.5) + 40.0
    found = measure_shading(blurred, image, background=40.0, lens_grid=_lens_grid())
    assert found.curvature_px2 > 3 * curvature
    assert found.tilt_measured and not found.tilt_consistent and not found.interior_consistent
    c, se = found.angular_curvature()
    assert (c, se) == (found.tilt_curvature_px2, found.tilt_curvature_se_px2)
    assert c == pytest.approx(curvature, abs=max(3 * se, 1e-7))
    assert se < 0.1 * curvature  # far tighter than the c/2 ± c/2 of the curvature alone
    assert found.to_dict()["tilt_consistent"] is False


def test_without_off_axis_micro_images_there_is_no_tilt() -> None:
    """Micro-images whose centres are their lenses' (no offset: an image-space telecentric
    camera, or a window on the axis) do not determine the tilt."""
    white, image = _white(3e-6, seed=5)
    found = measure_shading(white, image, background=40.0, lens_grid=image)
    assert not found.tilt_measured
    assert found.angular_curvature() == (found.curvature_px2, found.curvature_se_px2)
