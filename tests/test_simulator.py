"""The simulator against geometry (OPTICS.md §1-3), measured on rendered images.

Positions are measured on the pixels with OpenCV (not with the simulator's own
formulas) and compared with the paper's thin-lens relations.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from numpy.testing import assert_allclose

from calibration.edge_fit import fit_edges
from calibration.optics import image_distance, paper_optics
from calibration.presets import get_preset, preset_names
from calibration.sim_sweep import fit_frame
from calibration.simulator import (
    Roi,
    SensorModel,
    SimCamera,
    corner_images_px,
    render_frame,
)


@pytest.fixture(scope="module")
def cam() -> SimCamera:
    """Paper optics, a 1000x1000 window around the axis (standard corner only)."""
    return SimCamera(
        paper_optics(),
        SensorModel(width=1000, height=1000),
        mla_rotation_deg=0.2,
        mla_offset_px=(1.3, -0.7),
    )


def _lens_centres_near(cam: SimCamera, x: float, y: float, radius: float) -> np.ndarray:
    ii, jj = cam.lens_grid.indices_in(cam.sensor.width, cam.sensor.height)
    mx, my = cam.lens_grid.centre(ii, jj)
    keep = np.hypot(mx - x, my - y) < radius
    return np.stack([ii[keep], jj[keep], mx[keep], my[keep]], axis=1)


def _paper_prediction(cam: SimCamera, u: float, mx: np.ndarray, my: np.ndarray):
    """s = m + (m - r) b/a with r = -X v/u (the main image of the board origin, inverted)."""
    o = cam.optics
    cx, cy = cam.sensor.pp
    a = o.L - image_distance(u, o.F)
    r = np.array([0.0, 0.0])  # standard corner at the origin, on the axis
    mxm, mym = (mx - cx) * o.delta, (my - cy) * o.delta
    sx = mxm + (mxm - r[0]) * o.b / a
    sy = mym + (mym - r[1]) * o.b / a
    return cx + sx / o.delta, cy + sy / o.delta


@pytest.mark.parametrize("u", [270.0, 300.0, 335.0])
def test_corner_images_follow_thin_lens_disparity(cam: SimCamera, u: float) -> None:
    img = render_frame(cam, object_distance_mm=u, noise=False).astype(np.float32)
    cx, cy = cam.sensor.pp
    lenses = _lens_centres_near(cam, cx, cy, 260.0)
    px, py = _paper_prediction(cam, u, lenses[:, 2], lenses[:, 3])
    # keep predictions well inside their micro-image disc
    k = (cam.optics.L + cam.optics.b) / cam.optics.L
    icx, icy = cx + k * (lenses[:, 2] - cx), cy + k * (lenses[:, 3] - cy)
    inside = np.hypot(px - icx, py - icy) < 30.0
    assert inside.sum() >= 9
    start = np.stack([px[inside] + 0.8, py[inside] - 0.6], axis=1).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-4)
    found = cv2.cornerSubPix(img, start.reshape(-1, 1, 2), (5, 5), (-1, -1), crit).reshape(-1, 2)
    err = found - np.stack([px[inside], py[inside]], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.1
    # the corner moves between neighbouring micro-images by (1 + b/a) lens pitches
    assert_allclose(np.abs(err).max(), 0.0, atol=0.2)


def test_micro_images_per_board_point_is_about_seven(cam: SimCamera) -> None:
    """Count the micro-images along x that show the standard corner as a dark/light saddle."""
    u = 300.0
    img = render_frame(cam, object_distance_mm=u, noise=False).astype(np.float32)
    g = cv2.GaussianBlur(img, (0, 0), 2.0)
    ixy = cv2.Sobel(g, cv2.CV_32F, 1, 1, ksize=3)
    cx, cy = cam.sensor.pp
    grid = cam.image_grid
    ii, jj = grid.indices_in(cam.sensor.width, cam.sensor.height, margin_px=60)
    row = jj == int(np.round(grid.fractional_index(np.array([cx]), np.array([cy]))[1][0]))
    strong = 0
    peak = np.abs(ixy).max()
    for i, j in zip(ii[row], jj[row], strict=True):
        x, y = grid.centre(i, j)
        x, y = int(round(float(x))), int(round(float(y)))
        r = 44  # inside the fully lit disc (radius 50 px)
        patch = ixy[y - r : y + r, x - r : x + r]
        yy, xx = np.mgrid[-r:r, -r:r]
        disc = np.hypot(xx, yy) < r
        if np.abs(patch[disc]).max() > 0.3 * peak:
            strong += 1
    expected = (15.0 / 3.0) * (cam.optics.L + 3.0) / (cam.optics.L - 15.0)  # about 7.3
    assert abs(strong - expected) <= 1.0
    assert strong > 1 / 0.2  # more than 1/Q = 5


def test_micro_image_pitch_from_white_image(cam: SimCamera) -> None:
    white = render_frame(cam, object_distance_mm=300.0, white=True, noise=False).astype(float)
    expected = cam.optics.lens_pitch_px * (cam.optics.L + cam.optics.b) / cam.optics.L
    # the spectrum of the row-average profile peaks at the micro-image frequency
    profile = white.mean(axis=0) - white.mean()
    n = 1 << 16
    spec = np.abs(np.fft.rfft(profile * np.hanning(profile.size), n))
    freqs = np.fft.rfftfreq(n)
    band = (freqs > 1 / (expected * 1.2)) & (freqs < 1 / (expected * 0.8))
    f_peak = freqs[band][np.argmax(spec[band])]
    # the MLA rotation (0.2 deg) shortens the x period by cos(0.2 deg) only
    assert_allclose(1.0 / f_peak, expected / np.cos(np.radians(0.2)), rtol=2e-3)
    assert abs(1.0 / f_peak - cam.optics.lens_pitch_px) > 3.0  # not the lens pitch


def _edge_width(cam: SimCamera, u: float) -> float:
    img = render_frame(cam, object_distance_mm=u, noise=False).astype(float)
    profiles = []
    for p in corner_images_px(cam, (0.0, 0.0), u, rim_margin_px=25):
        x0, y0 = int(round(p["x"])), int(round(p["y"]))
        for dy in range(4, 12):
            profiles.append(img[y0 - dy, x0 - 6 : x0 + 7])
    fits = fit_edges(np.array(profiles))
    return float(np.median(fits.width[fits.ok]))


def test_corner_blur_grows_on_both_sides_of_focus(cam: SimCamera) -> None:
    u0 = cam.optics.u0
    w_near, w_focus, w_far = (_edge_width(cam, u) for u in (u0 - 50.0, u0, u0 + 50.0))
    assert w_near > w_focus + 0.05
    assert w_far > w_focus + 0.03
    # at focus only the PSF is left
    assert_allclose(w_focus, cam.psf_sigma_px, atol=0.05)


def test_vignetting_darkens_the_border() -> None:
    big = SimCamera(paper_optics(), SensorModel(width=5120, height=5120))
    cx, cy = big.sensor.pp
    centre = render_frame(
        big,
        object_distance_mm=300.0,
        white=True,
        noise=False,
        roi=Roi(int(cx) - 150, int(cy) - 150, 300, 300),
    )
    corner = render_frame(
        big, object_distance_mm=300.0, white=True, noise=False, roi=Roi(0, 0, 300, 300)
    )
    assert np.percentile(corner, 95) < 0.98 * np.percentile(centre, 95)


def test_rendering_is_seeded_and_roi_consistent(cam: SimCamera) -> None:
    a = render_frame(cam, object_distance_mm=300.0, seed=7)
    b = render_frame(cam, object_distance_mm=300.0, seed=7)
    c = render_frame(cam, object_distance_mm=300.0, seed=8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    full = render_frame(cam, object_distance_mm=300.0, noise=False)
    part = render_frame(cam, object_distance_mm=300.0, noise=False, roi=Roi(200, 300, 400, 250))
    assert np.array_equal(full[300:550, 200:600], part)
    assert a.dtype == np.uint16 and a.max() <= 4095


def test_noise_statistics_follow_the_sensor_model(cam: SimCamera) -> None:
    flat = replace(cam, sensor=replace(cam.sensor, read_noise_e=10.0))
    clean = render_frame(flat, object_distance_mm=300.0, white=True, noise=False).astype(float)
    noisy = render_frame(flat, object_distance_mm=300.0, white=True, seed=3).astype(float)
    lit = clean > 0.9 * clean.max()
    gain = flat.sensor.max_count / flat.sensor.full_well_e  # DN per electron
    electrons = (clean[lit] - flat.sensor.black_level_dn) / gain
    expected_var = (electrons.mean() + 10.0**2) * gain**2 + 1 / 12
    assert_allclose((noisy[lit] - clean[lit]).var(), expected_var, rtol=0.1)


@pytest.mark.parametrize("name", preset_names())
def test_presets_show_both_corners_in_their_default_frame(name: str) -> None:
    preset = get_preset(name)
    c = preset.camera
    for rail in (preset.sweep.rail_positions_mm()[0], preset.sweep.rail_positions_mm()[-1]):
        u = preset.sweep.object_distance_mm(rail)
        for corner in (c.board.standard_corner_mm, c.board.reference_corner_mm):
            assert len(corner_images_px(c, corner, u, preset.sweep.board_offset_mm)) >= 9


def test_presets_differ_and_place_focus_between_steps() -> None:
    presets = [get_preset(n) for n in preset_names()]
    pitches = {round(p.camera.optics.D, 4) for p in presets}
    assert len(pitches) == 3
    between = 0
    for p in presets:
        rail = (p.camera.optics.u0 - p.sweep.zero_object_distance_mm) / p.sweep.direction
        if abs(rail - round(rail)) > 0.1:
            between += 1
    assert between >= 2


def test_fit_frame_keeps_both_corners_in_a_small_frame() -> None:
    preset = fit_frame(get_preset("paper"), 3000, 1000)
    c = preset.camera
    for rail in preset.sweep.rail_positions_mm()[::33]:
        u = preset.sweep.object_distance_mm(rail)
        for corner in (c.board.standard_corner_mm, c.board.reference_corner_mm):
            assert len(corner_images_px(c, corner, u)) >= 9
