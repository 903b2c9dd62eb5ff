"""The Monte-Carlo renderer (bench.mcsim) against OPTICS.md's formulas, with no project code.

Each check recomputes the expectation from OPTICS.md (thin-lens relations, the
micro-image lattice, where a lens images a main-image point, the defocus blur,
the archive layout) and compares the rendered pixels with it.
"""

from __future__ import annotations

import functools
import json
import math
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.mcsim import sweep as mcsweep
from bench.mcsim.__main__ import main as mcsim_main
from bench.mcsim.archive import manifest as manifest_of
from bench.mcsim.archive import truth as truth_of
from bench.mcsim.presets import PRESETS
from bench.mcsim.render import WHITE, frame_rng, frame_signal, white_signal
from bench.mcsim.sensor import SensorSettings, expose
from bench.mcsim.spec import build_spec
from bench.mcsim.trace import Tracer, TraceSettings
from bench.mcsim.windows import corner_windows

# a small camera: 30 px lenses (~31.2 px micro-images), focus plane at u = 150 mm
SMALL = {
    "width": 320,
    "height": 320,
    "main_focal_mm": 20.0,
    "mla_focal_mm": 0.9,
    "mla_pitch_mm": 0.075,
    "pixel_mm": 0.0025,
    "b_mm": 1.1,
    "u0_mm": 150.0,
    "theta_deg": 0.3,
    "mla_offset": (1.7, -2.3),
    "board_offset": (0.3, -0.2),
    "u_rail0_mm": 140.0,
    "frames": 21,
    "rays": 16,
    "read_noise_e": 0.0,
}
# a camera with 60 px lenses for edge profiles well inside one micro-image
WIDE_LENS = {**SMALL, "mla_pitch_mm": 0.15, "mla_focal_mm": 1.2, "b_mm": 1.5, "theta_deg": 0.0}
# a tiny sweep for archive-level tests: 2 mm squares keep both corners close to the axis
TINY_SWEEP = [
    "--F", "20", "--f", "0.9", "--D", "0.075", "--pixel", "0.0025", "--b", "1.1",
    "--u0", "150", "--u-rail0", "148", "--frames", "3", "--rays", "4", "--white-rays", "2",
    "--square-mm", "2", "--gap-mm", "0.05", "--fit-frame", "--theta-deg", "0.4",
]  # fmt: skip


def _chief_focus(spec_camera, corner_mm, u, i, j):
    """Where lens (i, j) images a board point at lateral position ``corner_mm`` (pixels).

    OPTICS.md §1: lens m images the main-image point r to m + (m - r)·b/a.
    """
    cam = spec_camera
    F, L, b = cam.main_focal_mm, cam.mla_distance_mm, cam.sensor_distance_mm
    v = u * F / (u - F)
    a = L - v
    rx, ry = (-corner_mm[0] * v / u, -corner_mm[1] * v / u)  # the main lens inverts
    t = math.radians(cam.theta_deg)
    pitch = cam.mla_pitch_mm / cam.pixel_mm
    ox, oy = cam.lens_origin_px
    cx, cy = cam.principal_point_px
    mx = (ox + pitch * (i * math.cos(t) - j * math.sin(t)) - cx) * cam.pixel_mm
    my = (oy + pitch * (i * math.sin(t) + j * math.cos(t)) - cy) * cam.pixel_mm
    sx, sy = mx + (mx - rx) * b / a, my + (my - ry) * b / a
    return sx / cam.pixel_mm + cx, sy / cam.pixel_mm + cy


def _step_position(profile: np.ndarray, first_x: float) -> float:
    """Where a light-to-dark step lies, from the area under the normalised profile."""
    light, dark = profile[:3].mean(), profile[-3:].mean()
    return first_x - 0.5 + float(((profile - dark) / (light - dark)).sum())


def _edge_width(profile: np.ndarray, subpixel: int) -> float:
    """Blur width (px) of a light-to-dark edge: √(12·variance of the line spread).

    A uniform blur of width B has variance B²/12; point sampling n×n per pixel
    and the finite difference add (n²-1)/(12n²) + 1/12, removed here.
    """
    light, dark = profile[:3].mean(), profile[-3:].mean()
    lsf = -np.diff((profile - dark) / (light - dark))
    x = np.arange(lsf.size)
    mean = (lsf * x).sum() / lsf.sum()
    var = (lsf * (x - mean) ** 2).sum() / lsf.sum()
    n2 = subpixel * subpixel
    return math.sqrt(max(12.0 * var - ((n2 - 1) / n2 + 1.0), 0.0))


def test_white_image_centroids_lie_on_the_micro_image_lattice() -> None:
    spec = build_spec(**SMALL)
    cam = spec.camera
    signal, _ = white_signal(spec, np.random.default_rng(0))
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    # nearest lattice point of pitch (D/δ)(L+b)/L around O projected by (L+b)/L
    L, b = cam.mla_distance_mm, cam.sensor_distance_mm
    pitch = cam.mla_pitch_mm / cam.pixel_mm * (L + b) / L
    cx, cy = cam.principal_point_px
    ox = cx + (cam.lens_origin_px[0] - cx) * (L + b) / L
    oy = cy + (cam.lens_origin_px[1] - cy) * (L + b) / L
    t = math.radians(cam.theta_deg)
    dx, dy = xs - ox, ys - oy
    li = np.rint((dx * math.cos(t) + dy * math.sin(t)) / pitch)
    lj = np.rint((-dx * math.sin(t) + dy * math.cos(t)) / pitch)
    rows = []
    for i in range(-3, 4):
        for j in range(-3, 4):
            mask = (li == i) & (lj == j)
            w = signal[mask]
            rows.append((i, j, (xs[mask] * w).sum() / w.sum(), (ys[mask] * w).sum() / w.sum()))
    table = np.array(rows)
    design = np.c_[np.ones(len(table)), table[:, 0], table[:, 1]]
    fx = np.linalg.lstsq(design, table[:, 2], rcond=None)[0]
    fy = np.linalg.lstsq(design, table[:, 3], rcond=None)[0]
    assert math.hypot(fx[1], fy[1]) == pytest.approx(pitch, abs=0.02)
    assert math.hypot(fx[2], fy[2]) == pytest.approx(pitch, abs=0.02)
    assert math.degrees(math.atan2(fy[1], fx[1])) == pytest.approx(cam.theta_deg, abs=0.05)
    assert (fx[0], fy[0]) == pytest.approx((ox, oy), abs=0.1)
    # the lens pitch D/δ would be 1.2 px off: the lattice is the projected one
    assert abs(math.hypot(fx[1], fy[1]) - cam.mla_pitch_mm / cam.pixel_mm) > 1.0


def test_white_signal_is_the_cos4_weighted_aperture_mean() -> None:
    # a sensor point on the axis of lens (i, j): every ray passes the main aperture,
    # so the signal is 0.95 · mean over the lens square of cos⁴θ = 1/(1 + |s-m|²/b²)²
    spec = build_spec(**{**SMALL, "theta_deg": 0.0})
    cam = spec.camera
    tracer = Tracer(cam, None, 150.0, TraceSettings(rays=4096, subpixel=1))
    for i, j in ((0, 0), (3, -2)):
        lx, ly = cam.lens_centre_px(np.array(i), np.array(j))
        # the pixel nearest the point where lens (i, j)'s axis meets the sensor
        px, py = float(np.rint(lx)), float(np.rint(ly))
        got = float(tracer.trace(np.array([px]), np.array([py]), np.random.default_rng(5))[0])
        g = (np.arange(400) + 0.5) / 400 * cam.mla_pitch_mm - cam.mla_pitch_mm / 2
        mx, my = np.meshgrid(g, g)
        sx, sy = (px - lx) * cam.pixel_mm, (py - ly) * cam.pixel_mm
        tan2 = ((sx - mx) ** 2 + (sy - my) ** 2) / cam.sensor_distance_mm**2
        expected = 0.95 * float(np.mean(1.0 / (1.0 + tan2) ** 2))
        assert got == pytest.approx(expected, abs=1e-4)  # MC σ ≈ 1e-5
        assert abs(got - 0.95) > 1e-3  # without cos⁴ it would be 0.95


def test_without_cos4_every_passing_ray_counts_alike() -> None:
    # --no-cos4: the signal is 0.95 times the fraction of rays that pass, so a pixel whose
    # rays all pass (on its lens's axis) reads 0.95 wherever it is; with cos⁴ it reads less
    spec = build_spec(**{**SMALL, "theta_deg": 0.0, "cos4": False})
    assert spec.trace.cos4 is False and build_spec(**SMALL).trace.cos4 is True
    cam = spec.camera
    flat = Tracer(cam, None, 150.0, TraceSettings(rays=4096, subpixel=1, cos4=False))
    shaded = Tracer(cam, None, 150.0, TraceSettings(rays=4096, subpixel=1))
    for i, j in ((0, 0), (3, -2)):
        lx, ly = cam.lens_centre_px(np.array(i), np.array(j))
        px, py = np.array([float(np.rint(lx))]), np.array([float(np.rint(ly))])
        assert float(flat.trace(px, py, np.random.default_rng(5))[0]) == pytest.approx(
            0.95, abs=1e-6
        )
        assert float(shaded.trace(px, py, np.random.default_rng(5))[0]) < 0.95 - 1e-3
    # the truth file says how it was rendered
    assert truth_of(spec)["render"]["cos4_weighting"] is False
    assert truth_of(build_spec(**SMALL))["render"]["cos4_weighting"] is True


def test_focused_corner_appears_where_the_microlens_imaging_law_puts_it() -> None:
    spec = build_spec(**WIDE_LENS)
    cam = spec.camera
    u = cam.u_focus_mm
    assert u == pytest.approx(150.0)
    tracer = Tracer(cam, spec.board, u, TraceSettings(rays=32, subpixel=8))
    rng = np.random.default_rng(1)
    candidates = []
    for i in range(-3, 4):
        for j in range(-3, 4):
            px, py = _chief_focus(cam, spec.board.offset_mm, u, i, j)
            mx, my = cam.micro_image_centre_px(np.array(i), np.array(j))
            candidates.append((math.hypot(px - mx, py - my), px, py))
    checked = 0
    for _, px, py in sorted(candidates)[:3]:
        # a row 5 px below the corner (board Y > 0): X < 0 light, X >= 0 dark (upright)
        xs = np.arange(int(px) - 8, int(px) + 9)
        row = tracer.trace(xs, np.full(xs.shape, round(py) + 5), rng)
        assert row[:3].mean() > 0.9 and row[-3:].mean() < 0.1
        assert _step_position(row, xs[0]) == pytest.approx(px, abs=0.1)
        # a column 5 px left of the corner (board X < 0): Y < 0 dark, Y >= 0 light
        ys = np.arange(int(py) - 8, int(py) + 9)
        col = tracer.trace(np.full(ys.shape, round(px) - 5), ys, rng)[::-1]
        assert col[:3].mean() > 0.9 and col[-3:].mean() < 0.1
        assert ys[-1] - (_step_position(col, 0.0)) == pytest.approx(py, abs=0.1)
        checked += 1
    assert checked == 3


def test_reference_corner_shows_the_gap_between_its_shrunk_dark_squares() -> None:
    # OPTICS.md §3: at the reference corner (2s, 0) the dark squares are shrunk by Cr/2,
    # so a row below the corner steps to dark Cr/2 right of the corner, a column left
    # of it steps to dark Cr/2 above it; inside a micro-image 1 mm of board is
    # (v/u)(b/a)/δ pixels
    spec = build_spec(**{**WIDE_LENS, "square_mm": 2.0, "gap_mm": 0.3})
    cam = spec.camera
    u = cam.u_focus_mm
    ox, oy = spec.board.offset_mm
    v = u * cam.main_focal_mm / (u - cam.main_focal_mm)
    px_per_mm = (v / u) * (cam.sensor_distance_mm / (cam.mla_distance_mm - v)) / cam.pixel_mm
    half_gap_px = 0.15 * px_per_mm
    tracer = Tracer(cam, spec.board, u, TraceSettings(rays=32, subpixel=8))
    rng = np.random.default_rng(12)
    for corner, gap in (((ox, oy), 0.0), ((4.0 + ox, oy), half_gap_px)):
        _, _, px, py = _corner_nearest_centre(cam, corner, u)
        xs = np.arange(int(px) - 8, int(px) + 9)
        row = tracer.trace(xs, np.full(xs.shape, round(py) + 5), rng)
        assert row[:3].mean() > 0.9 and row[-3:].mean() < 0.1
        assert _step_position(row, xs[0]) == pytest.approx(px + gap, abs=0.1)
        ys = np.arange(int(py) - 8, int(py) + 9)
        col = tracer.trace(np.full(ys.shape, round(px) - 5), ys, rng)[::-1]
        assert col[:3].mean() > 0.9 and col[-3:].mean() < 0.1
        assert ys[-1] - _step_position(col, 0.0) == pytest.approx(py - gap, abs=0.1)
    assert half_gap_px > 1.0


def test_defocused_edge_width_is_the_geometric_blur() -> None:
    spec = build_spec(**WIDE_LENS)
    cam = spec.camera
    rng = np.random.default_rng(2)
    a_f = 1.0 / (1.0 / cam.mla_focal_mm - 1.0 / cam.sensor_distance_mm)
    widths = {}
    for u in (150.0, 130.0, 120.0, 110.0, 100.0, 200.0, 250.0):
        a = cam.mla_distance_mm - u * cam.main_focal_mm / (u - cam.main_focal_mm)
        blur = cam.mla_pitch_mm * cam.sensor_distance_mm * abs(1 / a_f - 1 / a) / cam.pixel_mm
        tracer = Tracer(cam, spec.board, u, TraceSettings(rays=64, subpixel=4))
        best = min(
            (
                math.hypot(p[0] - c[0], p[1] - c[1]),
                p,
            )
            for i in range(-3, 4)
            for j in range(-3, 4)
            for p in [_chief_focus(cam, spec.board.offset_mm, u, i, j)]
            for c in [cam.micro_image_centre_px(np.array(i), np.array(j))]
        )
        px, py = best[1]
        half = int(blur / 2) + 6
        xs = np.arange(int(px) - half, int(px) + half + 1)
        row = tracer.trace(xs, np.full(xs.shape, round(py) + int(blur / 2) + 3), rng)
        widths[u] = (blur, _edge_width(row, 4))
    for blur, width in widths.values():
        if blur >= 1.5:
            assert width == pytest.approx(blur, abs=0.35)
    in_order = sorted(widths.values())
    # a circular microlens blurs into a disc of diameter B: 1-D variance B²/16
    circle = build_spec(**{**WIDE_LENS, "aperture": "circle"}).camera
    u = 100.0
    blur, _ = widths[u]
    px, py = _corner_nearest_centre(circle, spec.board.offset_mm, u)[2:]
    xs = np.arange(int(px) - int(blur / 2) - 6, int(px) + int(blur / 2) + 7)
    row = round(py) + int(blur / 2) + 3
    disc = Tracer(circle, spec.board, u, TraceSettings(rays=64, subpixel=4))
    width = _edge_width(disc.trace(xs, np.full(xs.shape, row), rng), 4)
    assert width == pytest.approx(blur * math.sqrt(12 / 16), abs=0.35)
    assert [w for _, w in in_order] == sorted(w for _, w in in_order)  # grows with the blur
    assert widths[100.0][1] > widths[150.0][1] + 5.0


def _corner_nearest_centre(cam, corner_mm, u):
    """(i, j, x, y) of the lens whose image of the corner lies nearest its micro-image centre."""
    # search the lenses around the one the chief ray through the corner reaches
    scale = -(cam.mla_distance_mm + cam.sensor_distance_mm) / u / cam.pixel_mm
    cx, cy = cam.principal_point_px
    li, lj = cam.lattice_coords(cx + corner_mm[0] * scale, cy + corner_mm[1] * scale)
    best = None
    for i in range(round(float(li)) - 3, round(float(li)) + 4):
        for j in range(round(float(lj)) - 3, round(float(lj)) + 4):
            px, py = _chief_focus(cam, corner_mm, u, i, j)
            mx, my = cam.micro_image_centre_px(np.array(i), np.array(j))
            d = math.hypot(px - mx, py - my)
            if best is None or d < best[0]:
                best = (d, i, j, px, py)
    assert best is not None
    return best[1:]


@functools.cache
def _sinc2_table() -> tuple[np.ndarray, np.ndarray]:
    grid = np.linspace(-4000.0, 4000.0, 1_600_001)
    cdf = np.cumsum(np.sinc(grid / math.pi) ** 2)
    return grid, cdf / cdf[-1]


def _sinc2_cdf(q: np.ndarray) -> np.ndarray:
    """CDF of the density sin²q/(πq²) (the 1-D Fraunhofer pattern of a slit)."""
    return np.interp(q, *_sinc2_table())


def test_microlens_diffraction_blurs_a_focused_edge_by_the_square_aperture_pattern() -> None:
    # a square aperture of side D at distance b diffracts into sinc²(x·D/(λb)) per axis
    spec = build_spec(**WIDE_LENS)
    cam = spec.camera
    u = cam.u_focus_mm
    _, _, ex, ey = _corner_nearest_centre(cam, spec.board.offset_mm, u)
    xs = np.arange(int(ex) - 10, int(ex) + 11)
    row = round(ey) + 8
    wavelength_mm = 0.55e-3
    tracer = Tracer(
        cam, spec.board, u, TraceSettings(rays=2048, subpixel=4, airy_wavelength_um=0.55)
    )
    got = tracer.trace(xs, np.full(xs.shape, row), np.random.default_rng(8))
    per_mm = math.pi * cam.mla_pitch_mm / (wavelength_mm * cam.sensor_distance_mm)
    offsets = (np.arange(4) + 0.5) / 4 - 0.5
    dark = np.zeros(xs.shape)
    for ox in offsets:
        for oy in offsets:
            # dark where X >= 0 and Y >= 0, or X < 0 and Y < 0 (upright inside the micro-image)
            px = 1.0 - _sinc2_cdf((ex - (xs + ox)) * cam.pixel_mm * per_mm)
            py = 1.0 - _sinc2_cdf((ey - (row + oy)) * cam.pixel_mm * per_mm)
            dark += (px * py + (1 - px) * (1 - py)) / 16
    expected = 0.95 - 0.9 * dark

    def normalised(p: np.ndarray) -> np.ndarray:
        return (p - p[-2:].mean()) / (p[:2].mean() - p[-2:].mean())

    assert np.abs(normalised(got) - normalised(expected)).max() < 0.02
    sharp = Tracer(cam, spec.board, u, TraceSettings(rays=256, subpixel=4))
    plain = sharp.trace(xs, np.full(xs.shape, row), np.random.default_rng(8))
    assert np.abs(normalised(plain) - normalised(expected)).max() > 0.08


def test_spherical_aberration_shifts_edges_seen_through_off_axis_sub_apertures() -> None:
    # F(ρ) = F - S(ρ/R)²: a ray through the main lens at x0 lands on the board
    # ΔX = -u·x0·(1/F(ρ) - 1/F) away from its paraxial point; a pixel sees the
    # main aperture through its microlens as a square footprint, so an edge in
    # the micro-image moves by -M·median(ΔX) over that footprint, M = (v/u)(b/a)
    spec = build_spec(**WIDE_LENS)
    cam = spec.camera
    u, S = cam.u_focus_mm, 1.0
    L, b, f, D, F = (
        cam.mla_distance_mm,
        cam.sensor_distance_mm,
        cam.mla_focal_mm,
        cam.mla_pitch_mm,
        cam.main_focal_mm,
    )
    R = cam.main_aperture_mm / 2
    v = u * F / (u - F)
    magnification = (v / u) * (b / (L - v))
    side = abs(1 + L / b - L / f) * D  # footprint of the lens aperture on the main lens
    shifts = []
    for i in range(-3, 4):
        px, py = _chief_focus(cam, spec.board.offset_mm, u, i, 0)
        mx, my = cam.micro_image_centre_px(np.array(i), np.array(0))
        if not 10 <= abs(px - mx) <= 20:
            continue
        row = round(py) + 5
        x0c = -(L / b) * (px - mx) * cam.pixel_mm  # the footprint's centre
        y0c = -(L / b) * (row - my) * cam.pixel_mm
        g = (np.arange(400) + 0.5) / 400 * side - side / 2
        gx, gy = np.meshgrid(x0c + g, y0c + g)
        r2 = gx**2 + gy**2
        assert r2.max() < R * R  # the whole footprint passes
        dX = -u * gx * (1 / (F - S * r2 / R**2) - 1 / F)
        expected = -magnification * float(np.median(dX)) / cam.pixel_mm
        xs = np.arange(int(px) - 8, int(px) + 9)
        ys = np.full(xs.shape, row)
        edges = [
            _step_position(
                Tracer(
                    cam, spec.board, u, TraceSettings(rays=512, subpixel=8, spherical_mm=s)
                ).trace(xs, ys, np.random.default_rng(9)),
                xs[0],
            )
            for s in (0.0, S)
        ]
        shifts.append((expected, edges[1] - edges[0]))
    assert len(shifts) >= 2
    assert {e > 0 for e, _ in shifts} == {True, False}  # opposite sides of the axis
    for expected, got in shifts:
        assert abs(expected) > 1.0
        assert got == pytest.approx(expected, rel=0.25)


def test_dark_pixels_skipped_by_the_footprint_test_really_get_no_light() -> None:
    spec = build_spec(**{**SMALL, "theta_deg": 12.0})
    cam = spec.camera
    tracer = Tracer(cam, None, 150.0, TraceSettings(rays=64, subpixel=2))
    ys, xs = np.mgrid[100:200, 100:200]
    consts = tracer._point_constants(
        xs.ravel().astype(float), ys.ravel().astype(float), np.random.default_rng(0)
    )
    lit = consts[0]
    assert 0.01 < 1.0 - lit.mean() < 0.5  # some pixels are skipped, most are traced
    # trace the skipped pixels by brute force, straight from the thin-lens law, on a
    # grid that includes the pixel's and the lens square's edges and corners: nothing passes
    dark_x, dark_y = xs.ravel()[~lit], ys.ravel()[~lit]
    L, b, f, D = cam.mla_distance_mm, cam.sensor_distance_mm, cam.mla_focal_mm, cam.mla_pitch_mm
    i, j = cam.lens_of_pixels(dark_x, dark_y)
    lx, ly = cam.px_to_mm(*cam.lens_centre_px(i, j))
    lx, ly = lx[:, None, None], ly[:, None, None]
    sx, sy = cam.px_to_mm(dark_x, dark_y)
    pix = np.array([-0.5, 0.0, 0.5]) * cam.pixel_mm
    sx = (sx[:, None] + np.repeat(pix, 3)[None, :])[:, :, None]
    sy = (sy[:, None] + np.tile(pix, 3)[None, :])[:, :, None]
    grid = np.linspace(-0.5, 0.5, 25) * D
    along1, along2 = np.repeat(grid, 25)[None, None, :], np.tile(grid, 25)[None, None, :]
    t = math.radians(cam.theta_deg)  # square lenses turned with the grid
    mx = lx + along1 * math.cos(t) - along2 * math.sin(t)
    my = ly + along1 * math.sin(t) + along2 * math.cos(t)
    tx = (sx - mx) / b + (mx - lx) / f  # thin-lens deflection -h/f
    ty = (sy - my) / b + (my - ly) / f
    x0, y0 = mx - L * tx, my - L * ty
    assert (x0**2 + y0**2).min() > (cam.main_aperture_mm / 2) ** 2


def test_square_microlens_apertures_turn_with_the_grid() -> None:
    spec = build_spec(**{**SMALL, "theta_deg": 25.0})
    cam = spec.camera
    tracer = Tracer(cam, None, 150.0, TraceSettings())
    ex, ey = tracer._aperture_samples(np.random.default_rng(13), (2000, 50))
    t = math.radians(25.0)
    along1 = ex * math.cos(t) + ey * math.sin(t)  # back onto the grid's axes e1, e2
    along2 = -ex * math.sin(t) + ey * math.cos(t)
    D = cam.mla_pitch_mm
    for along in (along1, along2):
        assert along.min() > -1e-6 and along.max() < D + 1e-6
        assert np.histogram(along, bins=10, range=(0, D))[0].min() > 0.9 * along.size / 10
    # and the centre of the sampled square is the lens centre: mean offset = the
    # corner-to-centre vector turned by θ
    centre = (D / 2 * (math.cos(t) - math.sin(t)), D / 2 * (math.sin(t) + math.cos(t)))
    assert (float(ex.mean()), float(ey.mean())) == pytest.approx(centre, abs=2e-4)


def test_frames_render_whole_micro_images_around_the_corners_only() -> None:
    spec = build_spec(**{**SMALL, "square_mm": 2.0, "gap_mm": 0.05, "rays": 4, "fit_frame": True})
    cam = spec.camera
    signal, stats = frame_signal(spec, 10, frame_rng(spec.seed, 10))
    white, _ = white_signal(spec, frame_rng(spec.seed, WHITE))
    assert stats.windows_inside_frame
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    i, j = cam.lens_of_pixels(xs.ravel(), ys.ravel())
    keys = i * 100000 + j
    lit = white.ravel() > 0.6  # inside the micro-image discs: every ray passes
    rendered = signal.ravel() > 0.0
    fractions = []
    for key in np.unique(keys[lit]):
        in_lens = (keys == key) & lit
        fractions.append(rendered[in_lens].mean())
    fractions_arr = np.array(fractions)
    # every micro-image is either rendered whole or left dark, never cut
    assert np.all((fractions_arr == 1.0) | (fractions_arr == 0.0))
    rendered_count = int((fractions_arr == 1.0).sum())
    windows = corner_windows(cam, spec.board, spec.rail.u_mm(10), spec.corners, spec.margin)
    assert rendered_count == sum(w.lens_i.size for w in windows) == stats.micro_images
    # each window is centred where the chief ray of its corner meets the sensor
    u = spec.rail.u_mm(10)
    scale = -(cam.mla_distance_mm + cam.sensor_distance_mm) / u / cam.pixel_mm
    for w, corner_x in zip(windows, (0.0, 2.0 * spec.board.square_mm), strict=True):
        expected = (
            cam.principal_point_px[0] + (corner_x + spec.board.offset_mm[0]) * scale,
            cam.principal_point_px[1] + spec.board.offset_mm[1] * scale,
        )
        assert w.centre_px == pytest.approx(expected)
        mx, my = cam.micro_image_centre_px(w.lens_i, w.lens_j)
        assert abs(mx.mean() - expected[0]) < cam.micro_image_pitch_px
        assert abs(my.mean() - expected[1]) < cam.micro_image_pitch_px


def test_presets_hold_both_corner_windows_over_their_whole_sweep() -> None:
    names = set()
    for name in PRESETS:
        spec = build_spec(preset=name)
        cam = spec.camera
        names.add((cam.main_focal_mm, cam.mla_pitch_mm))
        for u in spec.u_values_mm:
            for w in corner_windows(cam, spec.board, u, ("standard", "reference"), spec.margin):
                assert w.inside_frame(cam), (name, u, w.corner)
    assert len(names) == len(PRESETS)  # different cameras
    between = build_spec(preset="between")
    focus_rail = (between.camera.u_focus_mm - between.rail.u_rail0_mm) / between.rail.direction
    assert focus_rail % 1.0 == pytest.approx(0.5)


def test_sensor_noise_follows_shot_and_read_noise() -> None:
    sensor = SensorSettings(bit_depth=12, photons=2000.0, read_noise_e=10.0, black_level=64)
    signal = np.full((400, 400), 0.5, dtype=np.float32)
    counts = expose(signal, sensor, np.random.default_rng(6)).astype(np.float64)
    gain = (4095 - 64) / 2000.0
    assert counts.mean() == pytest.approx(64 + 1000 * gain, rel=2e-3)
    assert counts.var() == pytest.approx((1000 + 100) * gain**2 + 1 / 12, rel=0.03)
    bright = expose(np.full((10, 10), 2.0, np.float32), sensor, np.random.default_rng(7))
    assert bright.max() == 4095  # clipped to the bit depth
    # exposure scales the light before the noise: twice the electrons, the same gain
    quarter = np.full((400, 400), 0.25, dtype=np.float32)
    doubled = expose(quarter, sensor, np.random.default_rng(8), exposure=2.0).astype(np.float64)
    assert doubled.mean() == pytest.approx(64 + 1000 * gain, rel=2e-3)
    assert doubled.var() == pytest.approx((1000 + 100) * gain**2 + 1 / 12, rel=0.03)


def test_exposure_brightens_the_frames_not_the_white_image(tmp_path: Path) -> None:
    plain = _render(tmp_path, "plain", "--seed", "4")
    bright = _render(tmp_path, "bright", "--seed", "4", "--exposure", "1.5")
    assert json.loads((bright / "truth.json").read_text())["render"]["noise"][
        "frame_exposure"
    ] == pytest.approx(1.5)
    white = [cv2.imread(str(d / "white.png"), cv2.IMREAD_UNCHANGED) for d in (plain, bright)]
    np.testing.assert_array_equal(white[0], white[1])
    frames = [
        cv2.imread(str(d / "frames" / "0001.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        for d in (plain, bright)
    ]
    lit = frames[0] > 0.5 * frames[0].max()
    assert np.count_nonzero(frames[0] >= 4095) == 0
    assert np.count_nonzero(frames[1][lit] >= 4095) > 0.3 * np.count_nonzero(lit)


def _render(tmp_path: Path, name: str, *extra: str) -> Path:
    out = tmp_path / name
    assert mcsim_main([str(out), *TINY_SWEEP, *extra]) == 0
    return out


def test_archive_layout_and_16_bit_pngs(tmp_path: Path) -> None:
    out = _render(tmp_path, "sweep", "--seed", "3")
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["format"] == "lfcal-sweep/1" and manifest["generator"] == "mcsim"
    assert set(manifest) >= {"camera", "optics", "board", "rail", "white", "frames"}
    cam = manifest["camera"]
    assert cam["bit_depth"] == 12 and cam["pixel_pitch_mm"] == 0.0025
    assert [f["rail_mm"] for f in manifest["frames"]] == [0.0, 1.0, 2.0]
    truth = json.loads((out / "truth.json").read_text())
    assert set(truth) == {
        "generator", "F_mm", "f_mm", "D_mm", "pixel_pitch_mm", "b_mm", "L_mm", "a_f_mm",
        "Q_focus", "patch_size_px_focus", "u0_mm", "focus_rail_mm", "u_rail0_mm", "direction",
        "width", "height", "principal_point_px", "main_aperture_diameter_mm",
        "vignetting_stop_mm", "vignetting_diameter_mm", "lens_grid",
        "micro_image_grid", "board", "render", "manifest_priors", "frames",
    }  # fmt: skip
    a_f = 1 / (1 / 0.9 - 1 / 1.1)
    assert truth["a_f_mm"] == pytest.approx(a_f)
    assert truth["u0_mm"] == pytest.approx(150.0)
    assert truth["focus_rail_mm"] == pytest.approx(2.0)
    f1 = truth["frames"][1]
    assert f1["u_mm"] == 149.0 and f1["v_mm"] == pytest.approx(149 * 20 / 129)
    assert f1["a_mm"] == pytest.approx(truth["L_mm"] - f1["v_mm"])
    assert f1["defocus_blur_px"] == pytest.approx(
        0.075 * 1.1 * abs(1 / a_f - 1 / f1["a_mm"]) / 0.0025
    )
    for name in ["white.png"] + [f["file"] for f in manifest["frames"]]:
        raw = (out / name).read_bytes()
        assert raw[:8] == b"\x89PNG\r\n\x1a\n" and raw[12:16] == b"IHDR"
        width, height, depth, colour = struct.unpack(">IIBB", raw[16:26])
        assert (width, height, depth, colour) == (cam["width"], cam["height"], 16, 0)
        image = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert (
            image is not None and image.dtype == np.uint16 and 3000 < image.max() <= 4095
        )  # right-aligned 12 bit


def test_renders_are_reproducible_from_the_seed(tmp_path: Path) -> None:
    first = _render(tmp_path, "a", "--seed", "11", "--frames", "2")
    again = _render(tmp_path, "b", "--seed", "11", "--frames", "2", "--jobs", "2")
    other = _render(tmp_path, "c", "--seed", "12", "--frames", "2")
    for name in ("white.png", "frames/0000.png", "frames/0001.png"):
        assert (first / name).read_bytes() == (again / name).read_bytes()
        assert (first / name).read_bytes() != (other / name).read_bytes()


def test_manifest_priors_can_differ_from_the_rendered_camera(tmp_path: Path) -> None:
    out = _render(
        tmp_path,
        "priors",
        "--manifest-main-focal-mm", "20.4", "--manifest-mla-focal-mm", "0.88",
        "--manifest-rail-zero-mm", "147.2", "--manifest-tolerances", "0.5,0.03,1.5",
    )  # fmt: skip
    manifest = json.loads((out / "sweep.json").read_text())
    truth = json.loads((out / "truth.json").read_text())
    assert manifest["optics"]["main_focal_mm"] == 20.4 and truth["F_mm"] == 20.0
    assert manifest["optics"]["mla_focal_mm"] == 0.88 and truth["f_mm"] == 0.9
    assert manifest["rail"]["zero_object_distance_mm"] == 147.2 and truth["u_rail0_mm"] == 148
    assert manifest["optics"]["main_focal_tolerance_mm"] == 0.5
    assert manifest["optics"]["mla_focal_tolerance_mm"] == 0.03
    assert manifest["rail"]["zero_object_distance_tolerance_mm"] == 1.5
    assert truth["manifest_priors"]["rail_zero_object_distance_mm"] == 147.2
    plain = manifest_of(build_spec(**{**SMALL, "u_rail0_mm": 148.0}))
    assert plain["optics"]["main_focal_mm"] == 20.0
    assert plain["rail"]["zero_object_distance_mm"] == 148.0
    assert plain["optics"]["mla_focal_mm"] == 0.9
    assert "main_focal_tolerance_mm" not in plain["optics"]


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["--b", "0.9"], "must exceed f"),  # b <= f
        (["--u-rail0", "15"], "<= F"),  # u <= F
        (["--u-rail0", "21", "--frames", "2"], "a = "),  # main image behind the MLA
    ],
)
def test_impossible_optics_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], reason: str
) -> None:
    assert reason in refused(tmp_path, capsys, args)


def refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str]) -> str:
    """The one-line error of a TINY_SWEEP render with ``args`` that must exit 2 and write
    nothing."""
    out = tmp_path / "never"
    assert mcsim_main([str(out), *TINY_SWEEP, *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert not out.exists()
    return err


def test_cached_sweep_renders_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mcsweep, "CACHE_ROOT", tmp_path)
    options = {
        "main_focal_mm": 20.0, "mla_focal_mm": 0.9, "mla_pitch_mm": 0.075, "b_mm": 1.1,
        "pixel_mm": 0.0025, "u0_mm": 150.0, "u_rail0_mm": 149.0, "frames": 2, "rays": 2,
        "white_rays": 1, "square_mm": 2.0, "gap_mm": 0.05, "fit_frame": True,
        "corners": "standard",
    }  # fmt: skip
    path = mcsweep.cached_sweep("tiny", jobs=1, **options)
    assert path == tmp_path / "tiny" and (path / ".complete").exists()
    stamp = (path / "frames" / "0001.png").stat().st_mtime_ns
    assert mcsweep.cached_sweep("tiny", jobs=1, **options) == path
    assert (path / "frames" / "0001.png").stat().st_mtime_ns == stamp
    mcsweep.cached_sweep("tiny", jobs=1, **{**options, "seed": 5})  # other options: render again
    assert (path / "frames" / "0001.png").stat().st_mtime_ns != stamp
    assert json.loads((path / "truth.json").read_text())["render"]["seed"] == 5
