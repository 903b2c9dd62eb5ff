"""Patch rendering and the seam score, against the simulator's ground truth.

Ground truth: the simulator's true micro-image lattice (``cam.image_grid``), its
corner-image positions (``corner_images_px``) and the optics. The seam-free
patch size is *not* the ESIF ``p = Q·D/δ`` but ``p - (μ - D/δ)`` (patches are
centred on micro-image centres, ``μ`` apart; see ``calibration/rendering.py``):
``test_seamless_patch_size_is_the_per_lens_shift`` checks that on the
simulator's own geometry, the seam tests then check the rendered pixels.

The seam frames use a 1 mm double checkerboard: the standard 10 mm board shows
only two edges (one each way) in a 1500×1000 window, parallel to the seams, so
its renders have no content that a wrong patch size could break.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration.board import Board
from calibration.lens_grid import LensGrid
from calibration.presets import Preset, get_preset
from calibration.rendering import (
    best_patch_size,
    patch_maps,
    render_box,
    render_patches,
    seam_scan,
    seam_score,
    seamless_patch_px,
)
from calibration.sim_sweep import fit_frame
from calibration.simulator import SimCamera, corner_images_px, render_frame

DESIGN_P_PX = 20.0  # designed a = 15 mm, b = 3 mm: Q = 0.2, p = Q·D/δ = 20 px
OUT_N = 20


def _seamless(cam: SimCamera, u: float) -> float:
    o = cam.optics
    return seamless_patch_px(
        float(o.patch_px(u)), lens_pitch_px=o.lens_pitch_px, image_pitch_px=o.image_pitch_px
    )


@pytest.fixture(scope="module")
def paper() -> Preset:
    return fit_frame(get_preset("paper"), 1500, 1000)


@pytest.fixture(scope="module")
def fine_cam(paper: Preset) -> SimCamera:
    """Paper optics, 1500×1000 around the axis, a 1 mm board (rich content), 2×2 rays per lens."""
    return replace(paper.camera, board=Board(square_mm=1.0), aperture_samples=2)


@pytest.fixture(scope="module")
def fine_frames(fine_cam: SimCamera) -> dict[float, np.ndarray]:
    return {
        u: render_frame(fine_cam, object_distance_mm=u, seed=[7, int(u)]) for u in (300.0, 260.0)
    }


@pytest.mark.parametrize("u", [230.91, 260.0, 300.0, 340.0])
def test_seamless_patch_size_is_the_per_lens_shift(paper: Preset, u: float) -> None:
    """Per lens, a board point moves by the seam-free patch size relative to the image centres."""
    cam = paper.camera
    pts = [q for q in corner_images_px(cam, (0.0, 0.0), u) if q["j"] == 0]
    pts.sort(key=lambda q: q["i"])
    assert len(pts) >= 5
    ii = np.array([q["i"] for q in pts])
    cx, _ = cam.image_grid.centre(ii, np.zeros_like(ii))
    rel = np.array([q["x"] for q in pts]) - cx
    shift = np.diff(rel) / np.diff(ii)
    np.testing.assert_allclose(shift, _seamless(cam, u), atol=0.01)
    # and it is clearly not the ESIF patch size
    assert abs(_seamless(cam, u) - float(cam.optics.patch_px(u))) > 5.0


@pytest.mark.parametrize("u", [300.0, 260.0])
def test_seam_score_is_lowest_at_the_seamless_patch_size(
    fine_cam: SimCamera, fine_frames: dict[float, np.ndarray], u: float
) -> None:
    raw, grid = fine_frames[u], fine_cam.image_grid
    p_true = _seamless(fine_cam, u)
    p_esif = float(fine_cam.optics.patch_px(u))
    wrong = [0.9 * p_true, 1.1 * p_true, p_esif, DESIGN_P_PX]
    scores = seam_scan(raw, image_grid=grid, patch_sizes_px=[p_true, *wrong], out_patch_px=OUT_N)
    assert scores[0] < 1.6  # about 1: seams look like the inside of the tiles
    assert np.all(scores[1:] > 1.5 * scores[0]), scores
    # the plain score of the plain render ranks them the same way
    plain = [
        seam_score(
            render_patches(raw, image_grid=grid, patch_size_px=p, out_patch_px=OUT_N),
            tile_px=OUT_N,
        )
        for p in (p_true, p_esif)
    ]
    assert plain[1] > 2.0 * plain[0]


@pytest.mark.parametrize("u", [300.0, 260.0])
def test_seam_scan_minimum_is_within_half_a_pixel(
    fine_cam: SimCamera, fine_frames: dict[float, np.ndarray], u: float
) -> None:
    sizes = np.arange(11.0, 24.0, 0.1)
    scores = seam_scan(
        fine_frames[u], image_grid=fine_cam.image_grid, patch_sizes_px=sizes, out_patch_px=OUT_N
    )
    best = best_patch_size(sizes, scores)
    assert abs(best - _seamless(fine_cam, u)) < 0.5, (best, _seamless(fine_cam, u))


def test_render_is_inverted_with_respect_to_the_board(paper: Preset) -> None:
    """The standard corner, moved off the axis, lands where the inverted orientation puts it."""
    cam = fit_frame(paper, 1000, 800).camera
    u, offset = 300.0, (2.5, 1.5)  # corner at world (+2.5, +1.5) mm
    raw = render_frame(cam, object_distance_mm=u, board_offset_mm=offset, seed=3)
    grid, p = cam.image_grid, _seamless(cam, u)
    img = render_patches(raw, image_grid=grid, patch_size_px=p, out_patch_px=OUT_N)
    i0, _, j0, _ = render_box(raw.shape, image_grid=grid, patch_size_px=p)
    # predicted position: the lens whose patch holds the corner, flipped in-patch offset
    pred = []
    for q in corner_images_px(cam, (0.0, 0.0), u, offset):
        cx, cy = grid.centre(q["i"], q["j"])
        t = np.array([q["x"] - cx, q["y"] - cy])
        t1, t2 = float(t @ grid.e1), float(t @ grid.e2)
        if abs(t1) < p / 2 and abs(t2) < p / 2:
            col = (q["i"] - i0) * OUT_N + OUT_N / 2 - 0.5 - t1 * OUT_N / p
            row = (q["j"] - j0) * OUT_N + OUT_N / 2 - 0.5 - t2 * OUT_N / p
            pred.append((col, row))
    assert len(pred) == 1
    col, row = pred[0]
    gx = np.abs(np.diff(img, axis=1)).mean(axis=0)  # the vertical edge (board X = 0)
    gy = np.abs(np.diff(img, axis=0)).mean(axis=1)  # the horizontal edge (board Y = 0)
    edge_col, edge_row = np.argmax(gx) + 0.5, np.argmax(gy) + 0.5
    assert abs(edge_col - col) < 1.5 and abs(edge_row - row) < 1.5
    # an upright render would put it at the mirrored place, far away
    h, w = img.shape
    assert abs((w - 1 - col) - col) > 20 and abs((h - 1 - row) - row) > 10
    # board +X, +Y is rendered towards -x, -y: the corner (world +X, +Y) sits up-left of the centre
    assert edge_col < w / 2 and edge_row < h / 2
    # dark square (0, 0) (X, Y > 0) is rendered up-left of the corner, light (-1, 0) up-right
    r, c, k = int(edge_row), int(edge_col), 6
    dark, light = img[r - k : r - 2, c - k : c - 2].mean(), img[r - k : r - 2, c + 3 : c + k].mean()
    assert light > 5 * dark


def _synthetic_raw(grid: LensGrid, w: int, h: int) -> np.ndarray:
    """Value = t1 + 3 t2 + 200 i + 5000 j: (t1, t2) px from the nearest node along e1, e2."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    fi, fj = grid.fractional_index(x, y)
    i, j = np.rint(fi), np.rint(fj)
    t1, t2 = (fi - i) * grid.pitch_px, (fj - j) * grid.pitch_px
    return (t1 + 3 * t2 + 200 * i + 5000 * j).astype(np.float32)


@pytest.mark.parametrize("n", [None, 12])
def test_patches_are_sampled_along_the_lattice_flipped_and_tiled_in_order(n: int | None) -> None:
    grid = LensGrid((203.7, 181.2), 40.3, np.radians(0.6))
    raw = _synthetic_raw(grid, 420, 380)
    p = 17.3
    img = render_patches(raw, image_grid=grid, patch_size_px=p, out_patch_px=n)
    nn = n or 17
    i0, i1, j0, j1 = render_box(raw.shape, image_grid=grid, patch_size_px=p)
    assert img.dtype == np.float32
    assert img.shape == ((j1 - j0 + 1) * nn, (i1 - i0 + 1) * nn)
    t = -((np.arange(nn) + 0.5) / nn - 0.5) * p  # flipped offsets along each axis
    cols_i = np.repeat(np.arange(i0, i1 + 1), nn)
    rows_j = np.repeat(np.arange(j0, j1 + 1), nn)
    expected = (
        np.tile(t, i1 - i0 + 1)[None, :]
        + 3 * np.tile(t, j1 - j0 + 1)[:, None]
        + 200 * cols_i[None, :]
        + 5000 * rows_j[:, None]
    )
    np.testing.assert_allclose(img, expected, atol=0.1)
    # every lens whose patch fits is there, the box is not empty
    assert (i1 - i0 + 1) >= 8 and (j1 - j0 + 1) >= 7


def test_region_limits_the_lenses_and_raw_is_untouched() -> None:
    grid = LensGrid((203.7, 181.2), 40.3, np.radians(0.6))
    raw = _synthetic_raw(grid, 420, 380)
    before = raw.copy()
    region = (150, 100, 160, 170)
    i0, i1, j0, j1 = render_box(raw.shape, image_grid=grid, patch_size_px=15.0, region=region)
    ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1))
    cx, cy = grid.centre(ii, jj)
    reach = 7.5 * np.sqrt(2)
    assert np.all((cx - reach >= 150) & (cx + reach <= 309) & (cy - reach >= 100))
    assert np.all(cy + reach <= 269)
    img = render_patches(raw, image_grid=grid, patch_size_px=15.0, region=region)
    assert img.shape == ((j1 - j0 + 1) * 15, (i1 - i0 + 1) * 15)
    np.testing.assert_array_equal(raw, before)
    mx, my = patch_maps(grid, (i0, i1, j0, j1), 15.0, 15)
    assert mx.min() >= 150 and mx.max() <= 309 and my.min() >= 100 and my.max() <= 269


def test_bad_inputs_raise() -> None:
    grid = LensGrid((50.0, 50.0), 40.0, 0.0)
    raw = np.zeros((100, 100), np.uint16)
    with pytest.raises(ValueError):
        render_patches(raw, image_grid=grid, patch_size_px=0.0)
    with pytest.raises(ValueError):
        render_patches(raw, image_grid=grid, patch_size_px=10.0, region=(500, 500, 10, 10))
    with pytest.raises(ValueError):
        render_patches(raw[None], image_grid=grid, patch_size_px=10.0)
    with pytest.raises(ValueError):
        render_patches(raw, image_grid=grid, patch_size_px=90.0)  # no patch fits


def test_seam_score_on_synthetic_tilings() -> None:
    """A smooth image cut into tiles scores about 1; the same tiles shuffled score far higher."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:160, 0:160].astype(np.float64)
    smooth = 100 * np.sin(x / 7.0) * np.cos(y / 9.0) + rng.normal(0, 0.5, x.shape)
    assert seam_score(smooth, tile_px=16) == pytest.approx(1.0, abs=0.25)
    tiles = smooth.reshape(10, 16, 10, 16).transpose(0, 2, 1, 3).reshape(100, 16, 16)
    shuffled = tiles[rng.permutation(100)].reshape(10, 10, 16, 16).transpose(0, 2, 1, 3)
    assert seam_score(shuffled.reshape(160, 160), tile_px=16) > 5.0
    assert np.isnan(seam_score(smooth[:20, :20], tile_px=16))  # fewer than two tiles
    with_nan = smooth.copy()
    with_nan[5, 5] = np.nan
    assert np.isfinite(seam_score(with_nan, tile_px=16))


def test_best_patch_size_refines_between_samples() -> None:
    sizes = np.arange(10.0, 20.0, 1.0)
    scores = 1.0 + (sizes - 14.3) ** 2
    assert best_patch_size(sizes, scores) == pytest.approx(14.3, abs=1e-9)
    scores[3] = np.nan
    assert best_patch_size(sizes, scores) == pytest.approx(14.3, abs=1e-9)
    assert np.isnan(best_patch_size(sizes, np.full(sizes.size, np.nan)))
