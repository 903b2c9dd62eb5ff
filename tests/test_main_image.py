"""Main images and the magnification with a known Q (:mod:`calibration.main_image`).

Micro-image corner positions are made from OPTICS.md §1 (``s = m + (m - r)·Q``, ``m``
the lens centres of a rotated lattice) for a corner near the axis and one ~1000 px off
it whose micro-images all lie to one side of it (as the reference corner's do), then
perturbed: the main images must come back, ``1/M`` with them, and a ``Q`` error must
move them by the lever arm, as the uncertainty says.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import cast

import numpy as np
from numpy.testing import assert_allclose

from calibration.camera_model import CameraModelFit
from calibration.lens_grid import LensGrid
from calibration.main_image import lever_arm_inverse_magnification
from calibration.mla_grid import MlaGrid
from calibration.summary import FrameSummary, SweepGeometry
from calibration.two_corners import magnification_on_camera

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


class _Camera:
    """The two things :func:`magnification_on_camera` asks of a calibrated camera."""

    def __init__(self, q: np.ndarray, q0: float) -> None:
        self.q, self.values = q, {"Q0": q0}

    def q_at_rail(self, rail_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.q, np.zeros_like(self.q)


def test_main_images_follow_the_shading_pull_about_the_lens_centres() -> None:
    """Positions pulled toward their lens centres by the shading, ``s = m + (m - r)·Q·(1 +
    η_s·(Q - Q0))``: placed with that ``η_s`` the main images, and ``1/M``, come back
    exactly; placed without it, frames away from focus read ``1/M`` off by the lever arm
    (a tilt along the sweep, which is F's error)."""
    q0, eta_s = 0.30, 2e-3
    q = np.array([0.33, 0.31, 0.30, 0.29, 0.27])
    true_inv = np.array([7.1, 7.6, 8.0, 8.4, 9.2])
    frames = [
        SimpleNamespace(corners=_frame(float(qk * (1 + eta_s * (qk - q0))), float(ik)))
        for qk, ik in zip(q, true_inv, strict=True)
    ]
    grid = SimpleNamespace(lens_grid=GRID)
    geometry = SimpleNamespace(board=SimpleNamespace(square_mm=SQUARE_MM), pixel_pitch_mm=PIXEL_MM)

    def placed(eta: float) -> np.ndarray:
        inv, _ = magnification_on_camera(
            cast(CameraModelFit, _Camera(q, q0)),
            cast(list[FrameSummary], frames),
            np.arange(q.size, dtype=float),
            cast(MlaGrid, grid),
            cast(SweepGeometry, geometry),
            shading_eta=eta,
        )
        return inv

    assert_allclose(placed(eta_s), true_inv, rtol=1e-12)
    off = placed(0.0) / true_inv - 1.0
    assert abs(off[2]) < 1e-12  # at focus there is no pull
    assert np.all(np.abs(off[[0, 1, 3, 4]]) > 1e-6)
    assert np.sign(off[0]) == -np.sign(off[4])  # opposite sides of focus: a tilt


def test_positions_locked_to_the_pixel_grid_widen_the_uncertainty_to_their_scatter() -> None:
    """Each micro-image's corner rounded to the nearest half pixel (how an unresolved edge
    lands between point samples) while its fit claims 0.004 px: the main images' σ grows
    with the offsets' scatter, and ``1/M``'s errors stay within it."""
    rng = np.random.default_rng(11)
    q = np.full(300, 0.30)
    true_inv = np.full(300, 8.0)
    frames = []
    for _ in range(300):
        frame = _frame(0.30, 8.0)
        shift = rng.uniform(-0.5, 0.5, 2)  # the whole image against the pixel grid
        for rows in frame.values():
            for row in rows:
                row[2] = np.round((row[2] + shift[0]) * 2.0) / 2.0 - shift[0]
                row[3] = np.round((row[3] + shift[1]) * 2.0) / 2.0 - shift[1]
        frames.append(frame)
    inv, se = lever_arm_inverse_magnification(
        frames, GRID, q=q, q_se=np.zeros(300), square_mm=SQUARE_MM, pixel_pitch_mm=PIXEL_MM
    )
    exact, se_exact = lever_arm_inverse_magnification(
        [_frame(0.30, 8.0)],
        GRID,
        q=q[:1],
        q_se=np.zeros(1),
        square_mm=SQUARE_MM,
        pixel_pitch_mm=PIXEL_MM,
    )
    assert_allclose(exact, true_inv[:1], rtol=1e-12)
    z = (inv - true_inv) / se
    assert np.median(se) > 10 * se_exact[0]  # the scatter, not the fits' 0.004 px
    assert np.sqrt(np.mean(z**2)) < 1.5
    assert np.mean(np.abs(z) <= 3) > 0.97


def test_locked_positions_claiming_uneven_errors_do_not_hand_the_main_image_to_one() -> None:
    """The same locked positions, each claiming its own error between 0.0005 and 0.01 px
    (the sharpest edge, most locked, claims the least): the main images weigh the
    micro-images by their claims plus the scatter they share, so ``1/M`` is as good as
    with equal weights and its σ covers it (weights by the claims alone put it 24 % farther
    off on these frames; on a point-sampled Monte-Carlo sweep F and b 4σ off)."""
    rng = np.random.default_rng(12)
    n = 300
    q = np.full(n, 0.30)
    true_inv = np.full(n, 8.0)
    frames = []
    for _ in range(n):
        frame = _frame(0.30, 8.0)
        shift = rng.uniform(-0.5, 0.5, 2)
        for rows in frame.values():
            for row in rows:
                row[2] = np.round((row[2] + shift[0]) * 2.0) / 2.0 - shift[0]
                row[3] = np.round((row[3] + shift[1]) * 2.0) / 2.0 - shift[1]
                row[4] = row[5] = float(rng.uniform(0.0005, 0.01))
        frames.append(frame)
    kwargs = dict(q=q, q_se=np.zeros(n), square_mm=SQUARE_MM, pixel_pitch_mm=PIXEL_MM)
    inv, se = lever_arm_inverse_magnification(frames, GRID, **kwargs)
    z = (inv - true_inv) / se
    assert np.sqrt(np.mean(z**2)) < 1.3
    assert np.mean(np.abs(z) <= 3) > 0.97
    for frame in frames:
        for rows in frame.values():
            for row in rows:
                row[4] = row[5] = 0.004
    inv_equal, _ = lever_arm_inverse_magnification(frames, GRID, **kwargs)
    rms = float(np.sqrt(np.mean((inv - true_inv) ** 2)))
    assert rms < 1.1 * float(np.sqrt(np.mean((inv_equal - true_inv) ** 2)))
