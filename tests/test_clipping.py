"""Clipped pixels: at full scale next to another one that is; a lone defect is not."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.clipping import (
    WHITE_CLIPPED_LIMIT,
    OverexposedWhiteError,
    check_white_exposure,
    clipped_at,
    clipped_fraction,
)


def test_a_clipped_patch_counts_a_lone_full_scale_pixel_does_not() -> None:
    image = np.full((20, 30), 1000, dtype=np.uint16)
    image[5:8, 10:14] = 4095  # a clipped patch of 12 pixels
    image[15, 3] = 4095  # a stuck pixel
    image[0, 29] = 4095  # a stuck pixel in the corner (neighbours off the image)
    rows, columns = np.mgrid[0:20, 0:30]
    clipped = clipped_at(image, rows, columns, 4095)
    assert clipped.sum() == 12 and clipped[5:8, 10:14].all()
    # any shape of index arrays: one profile of 5 samples across the patch's edge
    profile = clipped_at(image, np.full(5, 6), np.arange(8, 13), 4095)
    np.testing.assert_array_equal(profile, [False, False, True, True, True])


def test_the_clipped_fraction_counts_lit_pixels_in_clipped_patches() -> None:
    rng = np.random.default_rng(2)
    white = np.zeros((100, 200))
    white[:, :100] = rng.normal(3000.0, 20.0, (100, 100))  # lit, below full scale
    assert clipped_fraction(white, 4095) == 0.0
    white[:25, :100] = 4095  # a quarter of the lit pixels clipped
    white[90:, 100:] = 4  # dark pixels do not count
    assert clipped_fraction(white, 4095) == pytest.approx(0.25)
    # stuck pixels alone are not a clipped white
    stuck = np.full((100, 200), 3000.0)
    stuck[::10, ::10] = 4095
    assert clipped_fraction(stuck, 4095) == 0.0


def test_a_white_clipped_beyond_the_limit_is_refused_with_the_numbers() -> None:
    """A white image whose lit area is clipped beyond WHITE_CLIPPED_LIMIT is refused with the
    fraction, the full scale and what to do; at the limit it is accepted and its fraction
    returned."""
    assert WHITE_CLIPPED_LIMIT == pytest.approx(0.05)
    white = np.full((100, 200), 3000.0)
    white[:5, :] = 4095  # 5 % of the lit pixels: accepted
    assert check_white_exposure(white, 4095) == pytest.approx(0.05)
    white[5:8, :] = 4095  # 8 %: refused
    with pytest.raises(OverexposedWhiteError) as caught:
        check_white_exposure(white, 4095)
    message = str(caught.value)
    assert "8.0 % of its lit pixels" in message and "(4095 counts)" in message
    assert "lower exposure" in message
