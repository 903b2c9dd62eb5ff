"""The Hough diagnostic around a corner's start point (``calibration.corner_candidates``)."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.corner_candidates import hough_refine


def _checker_patch(size: int, corner_x: float, corner_y: float) -> np.ndarray:
    """A sharp checkerboard corner at ``(corner_x, corner_y)`` (pixels), dark 10, light 200."""
    ys, xs = np.mgrid[0:size, 0:size].astype(float)
    dark = (xs < corner_x) == (ys < corner_y)
    return np.where(dark, 10.0, 200.0).astype(np.float32)


@pytest.mark.parametrize(("shift_x", "shift_y"), [(0.0, 0.0), (2.0, -1.0), (-2.0, 2.0)])
def test_the_four_half_edges_are_found_and_the_start_moves_to_their_crossing(
    shift_x: float, shift_y: float
) -> None:
    size = 31
    centre = (size - 1) / 2.0
    patch = _checker_patch(size, centre + shift_x + 0.5, centre + shift_y + 0.5)
    found, dx, dy = hough_refine(patch, threshold=8)
    assert found == 4
    # the edges lie between pixel centres: the lines found are within a pixel of them
    assert abs(dx - shift_x) <= 1.0 and abs(dy - shift_y) <= 1.0


def test_a_uniform_patch_has_no_lines() -> None:
    assert hough_refine(np.full((31, 31), 100.0, dtype=np.float32), threshold=8) == (0, 0.0, 0.0)


def test_a_single_edge_gives_two_half_edges_and_no_move_along_it() -> None:
    size = 31
    ys, xs = np.mgrid[0:size, 0:size]
    patch = np.where(xs < 16.5, 10.0, 200.0).astype(np.float32)  # one vertical edge
    found, dx, dy = hough_refine(patch, threshold=8)
    assert found == 2
    assert abs(dx - 1.5) <= 1.0 and dy == 0.0
