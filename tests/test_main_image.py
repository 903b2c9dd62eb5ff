"""Main images and the magnification with a known Q (:mod:`calibration.main_image`).

Micro-image corner positions are made from OPTICS.md §1 (``s = m + (m - r)·Q``, ``m``
the lens centres of a rotated lattice) for a corner near the axis and one ~1000 px off
it whose micro-images all lie to one side of it (as the reference corner's do), then
perturbed: the main images must come back, ``1/M`` with them, and a ``Q`` error must
move them by the lever arm, as the uncertainty says.
"""

from __future__ import annotations

import numpy as np
from numpy.testing import assert_allclose

from calibration.lens_grid import LensGrid
from calibration.main_image import lever_arm_inverse_magnification

GRID = LensGrid(origin_px=(1898.8, 268.7), pitch_px=50.0, rotation_rad=np.radians(0.35))
SQUARE_MM, PIXEL_MM = 10.0, 0.0025


def _rows(r: np.ndarray, q: float, lenses: list[tuple[int, int]], rng=None, se=0.004):
    """``[i, j, x, y, x_se, y_se, size]`` for the micro-images ``lenses`` of main image ``r``."""
    rows = []
    for i, j in lenses:
        m = np.array(GRID.centre(i, j), dtype=float)
        s = m + (m - r) * q
        if rng is not None:
            s = s + rng.normal(0.0, se, 2)
        rows.append([i, j, s[0], s[1], se, se, 3.0])
    return rows


def _frame(q: float, inv_m: float, rng=None):
    """Standard corner 8 px from the origin lens, reference corner 2s away on the board."""
    r_std = np.array([1905.0, 262.0])
    dist_px = 2 * SQUARE_MM / (inv_m * PIXEL_MM)
    r_ref = r_std - np.array([dist_px, 0.0])
    near = [(0, 0), (1, 0), (0, -1), (-1, 0), (0, 1)]
    # the reference corner's micro-images: one side of it, ~60 px (as on the chief ray)
    i0 = int(round((r_ref[0] - GRID.origin_px[0]) / 50.0)) - 1
    off_axis = [(i0, 0), (i0 - 1, 0), (i0, -1), (i0 - 1, -1)]
    return {"standard": _rows(r_std, q, near, rng), "reference": _rows(r_ref, q, off_axis, rng)}


def test_exact_positions_give_the_magnification_exactly() -> None:
    q = np.array([0.30, 0.27, 0.33])
    true_inv = np.array([8.0, 9.5, 7.1])
    frames = [_frame(float(qk), float(ik)) for qk, ik in zip(q, true_inv, strict=True)]
    inv, se = lever_arm_inverse_magnification(
        frames, GRID, q=q, q_se=np.zeros(3), square_mm=SQUARE_MM, pixel_pitch_mm=PIXEL_MM
    )
    assert_allclose(inv, true_inv, rtol=1e-12)
    assert np.all(se > 0)


def test_a_q_error_moves_the_magnification_by_the_lever_arm_as_its_uncertainty_says() -> None:
    q_true, inv_true = 0.30, 8.0
    frame = _frame(q_true, inv_true)
    dq = 3e-4
    inv, se = lever_arm_inverse_magnification(
        [frame],
        GRID,
        q=np.array([q_true + dq]),
        q_se=np.array([dq]),
        square_mm=SQUARE_MM,
        pixel_pitch_mm=PIXEL_MM,
    )
    _, se0 = lever_arm_inverse_magnification(
        [frame],
        GRID,
        q=np.array([q_true]),
        q_se=np.array([0.0]),
        square_mm=SQUARE_MM,
        pixel_pitch_mm=PIXEL_MM,
    )
    shift = abs(inv[0] - inv_true)
    # the off-axis corner's lever arm makes a 1e-3 relative Q error a visible 1/M error ...
    assert shift / inv_true > 1e-5
    # ... which the propagated uncertainty carries (on top of the position noise)
    assert abs(se[0] - np.hypot(se0[0], shift)) <= 0.05 * shift


def test_noisy_positions_scatter_as_the_uncertainty_says() -> None:
    rng = np.random.default_rng(5)
    q, inv_true = np.full(200, 0.28), np.full(200, 9.0)
    frames = [_frame(0.28, 9.0, rng) for _ in range(200)]
    inv, se = lever_arm_inverse_magnification(
        frames, GRID, q=q, q_se=np.zeros(200), square_mm=SQUARE_MM, pixel_pitch_mm=PIXEL_MM
    )
    z = (inv - inv_true) / se
    assert abs(np.mean(z)) < 0.25
    assert 0.8 < np.std(z) < 1.2


def test_a_missing_corner_gives_nan() -> None:
    frame = _frame(0.3, 8.0)
    inv, se = lever_arm_inverse_magnification(
        [{"standard": frame["standard"], "reference": []}, {"standard": frame["standard"]}],
        GRID,
        q=np.array([0.3, 0.3]),
        q_se=np.zeros(2),
        square_mm=SQUARE_MM,
        pixel_pitch_mm=PIXEL_MM,
    )
    assert np.all(np.isnan(inv)) and np.all(np.isnan(se))
