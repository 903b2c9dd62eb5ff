"""MLA grid fit against the simulator's true lattices (``calibration.mla_grid``).

Bounds are twice the targets (lens-centre RMS 0.02 px, rotation 0.005°, image
pitch 1e-4 relative); ``bench/bench_mla.py`` reports the exact numbers at
full sensor size.
"""

from __future__ import annotations

import json
from functools import cache
from typing import Any

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from calibration.lens_grid import LensGrid
from calibration.mla_grid import (
    STATUS_DEAD,
    STATUS_OUTLIER,
    MlaGrid,
    fit_mla_grid,
    micro_image_labels,
)
from calibration.optics import focused_virtual_distance, image_centre_scale
from calibration.presets import Preset, get_preset
from calibration.shading import measure_shading
from calibration.sim_sweep import fit_frame
from calibration.simulator import SimCamera, render_frame

LENS_RMS_PX = 0.04
ROTATION_DEG = 0.01
PITCH_REL = 2e-4
IMAGE_RMS_PX = 0.08


def _mid_u(preset: Preset) -> float:
    rails = preset.sweep.rail_positions_mm()
    return preset.sweep.object_distance_mm(rails[len(rails) // 2])


@cache
def _scene(
    name: str, width: int, height: int, pp: tuple[float, float] | None = None
) -> tuple[SimCamera, np.ndarray]:
    preset = fit_frame(get_preset(name), width, height, principal_point_px=pp)
    white = render_frame(preset.camera, object_distance_mm=_mid_u(preset), white=True, seed=7)
    white.setflags(write=False)
    return preset.camera, white


def _fit(cam: SimCamera, white: np.ndarray, **kw: Any) -> MlaGrid:
    return fit_mla_grid(
        white, lens_pitch_px=cam.optics.lens_pitch_px, principal_point_px=cam.sensor.pp, **kw
    )


def _nearest_errors(fit: LensGrid, truth: LensGrid, w: int, h: int) -> np.ndarray:
    """(n, 2) fitted minus true position of every true node on the sensor."""
    ii, jj = truth.indices_in(w, h)
    tx, ty = truth.centre(ii, jj)
    fx, fy = fit.centre(*fit.nearest(tx, ty))
    return np.stack([fx - tx, fy - ty], axis=1)


def _assert_accurate(grid: MlaGrid, cam: SimCamera, lens_rms_px: float = LENS_RMS_PX) -> None:
    w, h = cam.sensor.width, cam.sensor.height
    err = _nearest_errors(grid.lens_grid, cam.lens_grid, w, h)
    rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert rms <= lens_rms_px, f"lens-centre RMS error {rms:.4f} px"
    # micro-image centres keep a small radial (scale) bias that cancels in the lens centres
    img_err = _nearest_errors(grid.image_grid, cam.image_grid, w, h)
    assert float(np.sqrt(np.mean(np.sum(img_err**2, axis=1)))) <= IMAGE_RMS_PX
    assert_allclose(grid.rotation_deg, cam.mla_rotation_deg, rtol=0, atol=ROTATION_DEG)
    assert_allclose(grid.image_pitch_px, cam.image_grid.pitch_px, rtol=PITCH_REL)
    assert_allclose(grid.lens_grid.pitch_px, cam.optics.lens_pitch_px, rtol=1e-12)
    assert_allclose(
        grid.scale, image_centre_scale(cam.optics.L, cam.optics.b), rtol=PITCH_REL, atol=0
    )
    # the same lens index in both lattices, and index (0, 0) nearest the principal point
    ti, tj = cam.image_grid.nearest(np.array([cam.sensor.pp[0]]), np.array([cam.sensor.pp[1]]))
    tx, ty = cam.image_grid.centre(ti, tj)
    assert_allclose(grid.image_grid.origin_px, [tx[0], ty[0]], atol=0.05)
    lx, ly = cam.lens_grid.centre(ti, tj)
    assert_allclose(grid.lens_grid.origin_px, [lx[0], ly[0]], atol=0.05)


@pytest.mark.parametrize("name", ["paper", "rotated", "noisy"])
@pytest.mark.parametrize("size", [(1200, 1200), (3000, 1000)])
def test_presets_match_the_true_lattices(name: str, size: tuple[int, int]) -> None:
    cam, white = _scene(name, *size)
    grid = _fit(cam, white)
    _assert_accurate(grid, cam)
    assert grid.residual_rms_px < 0.1
    assert grid.rejected["dead"] == 0
    assert grid.n_lenses_used >= 0.95 * (grid.n_lenses_used + grid.rejected["outlier"])
    assert grid.n_lenses_used >= 60
    # the bright disc is the main aperture's image: radius D/(2δ) with f-number matching
    assert_allclose(grid.disc_radius_px, 0.5 * cam.optics.lens_pitch_px, atol=1.0)
    # every micro-image whose disc is whole on the sensor was measured
    margin = 0.5 * cam.image_grid.pitch_px + 2
    ii, jj = cam.image_grid.indices_in(cam.sensor.width, cam.sensor.height, margin_px=margin)
    assert grid.lens_i.size >= ii.size


def test_dead_lenses_and_a_displaced_micro_image_are_rejected() -> None:
    cam, white = _scene("paper", 1200, 1200)
    img = white.copy()
    ig = cam.image_grid
    li, lj, inside = micro_image_labels(img.shape, ig, radius_px=0.5 * ig.pitch_px)
    ci, cj = (
        int(v[0]) for v in ig.nearest(np.array([cam.sensor.pp[0]]), np.array([cam.sensor.pp[1]]))
    )
    dead = {(ci + di, cj + dj) for di, dj in [(0, 0), (2, -1), (-3, 2), (4, 4), (-4, -3)]}
    for i, j in dead:
        img[(li == i) & (lj == j) & inside] = 0
    # shift the content of one micro-image by 4 px along x
    oi, oj = ci + 1, cj + 3
    x, y = (int(round(float(v))) for v in ig.centre(oi, oj))
    h = int(0.5 * ig.pitch_px)
    img[y - h : y + h + 1, x - h : x + h + 1] = np.roll(
        img[y - h : y + h + 1, x - h : x + h + 1], 4, axis=1
    )
    grid = _fit(cam, img)
    _assert_accurate(grid, cam)
    # indices of the fit agree with the truth's (both have (0, 0) nearest the pp)
    found_dead = set(
        zip(
            (grid.lens_i[grid.lens_status == STATUS_DEAD] + ci).tolist(),
            (grid.lens_j[grid.lens_status == STATUS_DEAD] + cj).tolist(),
            strict=True,
        )
    )
    assert found_dead == dead
    assert grid.rejected["dead"] == 5
    outliers = grid.lens_status == STATUS_OUTLIER
    assert_array_equal(grid.lens_i[outliers] + ci, [oi])
    assert_array_equal(grid.lens_j[outliers] + cj, [oj])
    assert_allclose(grid.residual_px[outliers], 4.0, atol=0.2)
    assert grid.n_rejected == sum(grid.rejected.values())


def test_off_centre_principal_point() -> None:
    cam, white = _scene("rotated", 1200, 1200, pp=(430.0, 790.5))
    assert cam.sensor.pp == (430.0, 790.5)
    _assert_accurate(_fit(cam, white), cam)


def test_black_level_and_dtype_do_not_matter() -> None:
    cam, white = _scene("paper", 1200, 1200)
    base = _fit(cam, white)
    lifted = _fit(cam, white.astype(np.float64) + 1500.0)
    assert_allclose(lifted.image_grid.origin_px, base.image_grid.origin_px, atol=1e-3)
    assert_allclose(lifted.image_pitch_px, base.image_pitch_px, rtol=1e-6)
    assert_allclose(lifted.background - base.background, 1500.0, atol=1.0)
    as8 = (white.astype(np.float64) * (255.0 / white.max())).round().astype(np.uint8)
    _assert_accurate(_fit(cam, as8), cam)


def test_high_noise() -> None:
    cam, white = _scene("noisy", 3000, 1000)
    rng = np.random.default_rng(11)
    level = float(np.percentile(white, 95))
    noisy = white + rng.normal(0.0, 0.08 * level, white.shape)
    grid = _fit(cam, noisy)
    _assert_accurate(grid, cam)
    assert grid.rejected["dead"] == 0


def test_pitch_guess_gives_the_same_fit() -> None:
    cam, white = _scene("rotated", 1200, 1200)
    a = _fit(cam, white)
    b = _fit(cam, white, pitch_guess_px=cam.image_grid.pitch_px * 1.01)
    assert_allclose(b.image_grid.origin_px, a.image_grid.origin_px, atol=1e-3)
    assert_allclose(b.image_pitch_px, a.image_pitch_px, rtol=1e-6)


def test_to_dict_is_json_ready() -> None:
    cam, white = _scene("paper", 1200, 1200)
    grid = _fit(cam, white)
    d = json.loads(json.dumps(grid.to_dict(include_lenses=True)))
    assert d["n_lenses_used"] == grid.n_lenses_used
    assert d["lens_grid"]["pitch_px"] == cam.optics.lens_pitch_px
    assert len(d["lenses"]["rows"]) == grid.lens_i.size
    assert "lenses" not in grid.to_dict()
    assert_allclose(d["residual_rms_px"], grid.residual_rms_px)


def test_micro_image_labels_follow_the_true_lattice() -> None:
    cam, white = _scene("paper", 1200, 1200)
    grid = _fit(cam, white)
    fi, fj, inside = grid.labels(white.shape)
    ti, tj, _ = micro_image_labels(white.shape, cam.image_grid)
    assert fi.shape == white.shape and fi.dtype == np.int32
    # only pixels within ~0.01 px of a cell boundary may differ
    assert np.mean((fi != ti) | (fj != tj)) < 1e-3
    # inside the measured disc the white is bright, outside the cell centre dark
    bright = np.percentile(white, 99)
    assert np.median(white[inside]) > 0.7 * bright
    core = grid.labels(white.shape, radius_px=0.3 * grid.image_pitch_px)[2]
    assert core.sum() < inside.sum()
    assert np.min(white[core]) > 0.5 * bright


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("black", "uniform"),
        ("tiny", "too small"),
        ("noise", "no microlens lattice"),
        ("checkerboard", "not a white"),
        ("rgb", "2-D"),
        ("nan", "NaN"),
    ],
)
def test_bad_input_raises_a_specific_error(case: str, message: str) -> None:
    cam, white = _scene("paper", 1200, 1200)
    if case == "black":
        img = np.zeros_like(white)
    elif case == "tiny":
        img = white[:300, :300]
    elif case == "noise":
        img = np.random.default_rng(1).normal(100.0, 5.0, white.shape)
    elif case == "checkerboard":
        preset = fit_frame(get_preset("paper"), 700, 700)
        img = render_frame(preset.camera, object_distance_mm=_mid_u(preset), seed=2)
    elif case == "rgb":
        img = np.stack([white] * 3, axis=-1)
    else:
        img = white.astype(np.float64)
        img[0, 0] = np.nan
    with pytest.raises(ValueError, match=message):
        _fit(cam, img)


def test_bad_prior_raises() -> None:
    cam, white = _scene("paper", 1200, 1200)
    with pytest.raises(ValueError, match="lens_pitch_px"):
        fit_mla_grid(white, lens_pitch_px=float("nan"), principal_point_px=cam.sensor.pp)
    # priors far from the truth: a harmonic in the searched band, or nothing there
    with pytest.raises(ValueError, match="harmonic of a lattice with a pitch of about 10[56]"):
        fit_mla_grid(white, lens_pitch_px=60.0, principal_point_px=cam.sensor.pp)
    with pytest.raises(ValueError, match="no microlens lattice"):
        fit_mla_grid(white, lens_pitch_px=200.0, principal_point_px=cam.sensor.pp)


@pytest.mark.parametrize("name", ["paper", "rotated"])
def test_the_shaded_rims_explain_the_lattice_scale_reading(name: str) -> None:
    """The lattice reads ``(L+b)/L`` as ``1 + β(1 + (β - Q0)·η)`` (module docstring), η from
    the white image's own shading; ``scale_se`` is the fit's statistical error."""
    cam, white = _scene(name, 3000, 1000)
    grid = _fit(cam, white)
    o = cam.optics
    beta = o.b / o.L
    q0 = o.b / focused_virtual_distance(o.f, o.b)
    shading = measure_shading(white, grid.image_grid, background=grid.background)
    eta = shading.bias_coefficient(o.lens_pitch_px**2 / 12.0)
    rim = beta * (beta - q0) * eta
    assert rim < -5e-6  # the pull is there: it is a few pitch-1e-5
    true_scale = image_centre_scale(o.L, o.b)
    assert 0 < grid.scale_se < 5e-6
    assert abs(grid.scale - (true_scale + rim)) < abs(rim) / 2
    assert grid.to_dict()["scale_se"] == grid.scale_se
