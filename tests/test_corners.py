"""ESIF corner detection on rendered frames against the simulator's ground truth."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from numpy.testing import assert_allclose

from calibration.corner_candidates import MicroImageMap
from calibration.corners import CornerOptions
from calibration.frame_analysis import FrameContext, analyze_frame
from calibration.presets import get_preset
from calibration.sim_sweep import fit_frame
from calibration.simulator import corner_images_px, render_frame


@pytest.fixture(scope="module")
def setup():
    preset = fit_frame(get_preset("paper"), 2900, 1000)
    cam = preset.camera
    o = cam.optics
    ctx = FrameContext(
        cam.image_grid,
        cam.lens_grid,
        cam.sensor.pp,
        o.delta,
        o.F,
        cam.board,
        0.8 * o.lens_pitch_px / 2,
    )
    mim = MicroImageMap(
        ctx.image_grid, (cam.sensor.height, cam.sensor.width), ctx.interior_radius_px
    )
    return cam, ctx, mim


def _truth(cam, u):
    out = {}
    for name, corner in (
        ("standard", cam.board.standard_corner_mm),
        ("reference", cam.board.reference_corner_mm),
    ):
        for p in corner_images_px(cam, corner, u):
            out[(name, p["i"], p["j"])] = (p["x"], p["y"])
    return out


@pytest.mark.parametrize("u", [262.0, 300.0, 341.0])
def test_corners_and_q_match_truth(setup, u: float) -> None:
    cam, ctx, mim = setup
    img = render_frame(cam, object_distance_mm=u, seed=int(u))
    res = analyze_frame(img, ctx, u, micro_image_map=mim)
    truth = _truth(cam, u)
    q_true = float(cam.optics.Q(u))
    for fit in (res.standard, res.reference):
        assert fit is not None
        assert fit.n_used >= 8
        errs = []
        for m, used in zip(fit.measurements, fit.used, strict=True):
            if used:
                tx, ty = truth[(fit.name, m.lens_i, m.lens_j)]
                errs.append((m.x - tx, m.y - ty))
        rms = float(np.sqrt(np.mean(np.square(errs))))
        assert rms < 0.1, f"{fit.name} corner RMS {rms:.3f} px"
        assert abs(fit.Q - q_true) / q_true < 5e-4
        assert fit.Q_se < 1e-4
    # the reference corner's gap makes its corner region larger
    assert res.Lr_px > res.Ls_px


def test_esif_not_worse_than_cornersubpix(setup) -> None:
    cam, ctx, mim = setup
    u = 300.0
    img = render_frame(cam, object_distance_mm=u, seed=11)
    res = analyze_frame(img, ctx, u, micro_image_map=mim)
    truth = _truth(cam, u)
    fit = res.standard
    assert fit is not None
    esif, cv = [], []
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    for m, used in zip(fit.measurements, fit.used, strict=True):
        if not used:
            continue
        tx, ty = truth[("standard", m.lens_i, m.lens_j)]
        start = np.array([[[round(tx), round(ty)]]], dtype=np.float32)
        refined = cv2.cornerSubPix(img.astype(np.float32), start, (5, 5), (-1, -1), crit)[0, 0]
        esif.append(np.hypot(m.x - tx, m.y - ty))
        cv.append(np.hypot(refined[0] - tx, refined[1] - ty))
    assert np.sqrt(np.mean(np.square(esif))) <= np.sqrt(np.mean(np.square(cv)))


def test_noisy_micro_images_with_missing_hough_lines_are_kept(setup) -> None:
    cam, ctx, mim = setup
    dim = replace(cam, sensor=replace(cam.sensor, white_level_e=400.0, read_noise_e=40.0))
    u = 300.0
    img = render_frame(dim, object_distance_mm=u, seed=5)
    res = analyze_frame(img, ctx, u, micro_image_map=mim)
    fit = res.standard
    assert fit is not None
    used = [m for m, k in zip(fit.measurements, fit.used, strict=True) if k]
    assert len(used) >= 8
    # the paper's "exactly 4 Hough lines" rule would have dropped these good micro-images
    assert any(m.hough_lines < 4 for m in used)
    assert abs(fit.Q - float(cam.optics.Q(u))) / float(cam.optics.Q(u)) < 2e-3


def test_rejected_micro_images_carry_a_reason(setup) -> None:
    cam, ctx, mim = setup
    u = 280.0
    res = analyze_frame(
        render_frame(cam, object_distance_mm=u, seed=2), ctx, u, micro_image_map=mim
    )
    assert res.rejected, "micro-images near the rim must be rejected with a reason"
    assert all(isinstance(k, str) and k for k in res.rejected)


def test_board_out_of_view_finds_no_corner(setup) -> None:
    cam, ctx, mim = setup
    u = 300.0
    img = render_frame(cam, object_distance_mm=u, board_offset_mm=(400.0, 400.0), seed=1)
    res = analyze_frame(img, ctx, u, micro_image_map=mim)
    assert res.standard is None and res.reference is None
    assert not np.isfinite(res.Q)


def test_options_are_keyword_tunable() -> None:
    opts = CornerOptions(interior_fraction=0.7, profile_half_px=5)
    assert opts.profile_half_px == 5


def test_edge_lines_are_weighted_least_squares_with_a_common_slope() -> None:
    """Each edge's two blocks share a slope and keep their own intercepts (the two halves of
    the reference corner's edge are the gap apart): the closed form equals the weighted
    least squares of that design, and its error of the mean intercept the one from the
    inverse normal matrix scaled by the reduced χ² (at least 1); points all at one position
    along the edge (slope undetermined) take the least-norm solution."""
    from calibration.corners import _edge_from_blocks

    rng = np.random.default_rng(5)
    along1, along2 = rng.uniform(0, 10, 12), rng.uniform(-12, -2, 9)
    se1, se2 = rng.uniform(0.003, 0.05, 12), rng.uniform(0.003, 0.05, 9)
    across1 = 4.0 + 0.02 * along1 + rng.normal(0, 1, 12) * se1 * 3
    across2 = 4.1 + 0.02 * along2 + rng.normal(0, 1, 9) * se2 * 3
    use1, use2 = np.ones(12, bool), np.ones(9, bool)
    use1[3] = False
    first, second = (along1, across1, se1, use1), (along2, across2, se2, use2)
    i1, i2, slope, mean_se, ref = _edge_from_blocks(first, second)
    a = np.r_[along1[use1], along2]
    c = np.r_[across1[use1], across2]
    w = 1.0 / np.maximum(np.r_[se1[use1], se2], 0.005) ** 2
    assert ref == pytest.approx(0.5 * (along1[use1].mean() + along2.mean()))
    design = np.c_[np.r_[np.ones(11), np.zeros(9)], np.r_[np.zeros(11), np.ones(9)], a - ref]
    normal = design.T @ (w[:, None] * design)
    coef = np.linalg.solve(normal, design.T @ (w * c))
    assert_allclose([i1, i2, slope], coef, rtol=1e-10)
    chi2 = float(np.sum(w * (c - design @ coef) ** 2)) / (a.size - 3)
    cov = np.linalg.inv(normal) * max(chi2, 1.0)
    assert mean_se == pytest.approx(0.5 * np.sqrt(cov[0, 0] + cov[1, 1] + 2 * cov[0, 1]))
    flat = _edge_from_blocks(
        (np.full(5, 2.0), across1[:5], se1[:5], np.ones(5, bool)),
        (np.full(4, 2.0), across2[:4], se2[:4], np.ones(4, bool)),
    )
    w1, w2 = 1.0 / np.maximum(se1[:5], 0.005) ** 2, 1.0 / np.maximum(se2[:4], 0.005) ** 2
    assert flat[2] == pytest.approx(0.0, abs=1e-12)
    assert_allclose(
        flat[:2], [np.sum(w1 * across1[:5]) / w1.sum(), np.sum(w2 * across2[:4]) / w2.sum()]
    )
