"""The wave-optics renderer (bench.wavesim) against independent physics.

Expectations come from closed forms (the defocused pupil's on-axis intensity,
the sinc² and Airy patterns, the uniform geometric blur), from OPTICS.md's
formulas (where a lens images a main-image point) and from a brute-force ray
check written here, never from wavesim's own constants.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.special import fresnel, j1

from bench.wavesim import sweep as wsweep
from bench.wavesim.__main__ import main as wavesim_main
from bench.wavesim.kernel import frame_kernel
from bench.wavesim.psf import Pupil, fine_psf
from bench.wavesim.render import kernel_for, lenses_signal, white_signal
from bench.wavesim.settings import build_wave_spec

LAM = 0.55e-3  # mm
# 60 px lenses, focus plane at u = 150 mm; frames rendered lens by lens
CAMERA = {
    "width": 240,
    "height": 240,
    "main_focal_mm": 20.0,
    "mla_focal_mm": 1.2,
    "mla_pitch_mm": 0.15,
    "pixel_mm": 0.0025,
    "b_mm": 1.5,
    "u0_mm": 150.0,
    "theta_deg": 0.0,
    "mla_offset": (0.0, 0.0),
    "u_rail0_mm": 150.0,
    "frames": 1,
}


def _optics(cam, u):
    F, L, b = cam.main_focal_mm, cam.mla_distance_mm, cam.sensor_distance_mm
    v = u * F / (u - F)
    return v, L - v, b


def _lens_mm(cam, i, j):
    """Lens (i, j)'s centre projected along z, mm from the axis (OPTICS.md §2)."""
    t = math.radians(cam.theta_deg)
    p = cam.mla_pitch_mm / cam.pixel_mm
    ox, oy = cam.lens_origin_px
    cx, cy = cam.principal_point_px
    x = ox + p * (i * math.cos(t) - j * math.sin(t))
    y = oy + p * (i * math.sin(t) + j * math.cos(t))
    return (x - cx) * cam.pixel_mm, (y - cy) * cam.pixel_mm


def _edge_px(cam, u, i, j, lateral_mm, axis):
    """Sensor px where lens (i, j) images the board line at ``lateral_mm`` (x: 0, y: 1).

    OPTICS.md §1: main-image point r = -P·v/u is imaged to m + (m - r)·b/a.
    """
    v, a, b = _optics(cam, u)
    m = _lens_mm(cam, i, j)[axis]
    r = -lateral_mm * v / u
    s = m + (m - r) * b / a
    return s / cam.pixel_mm + cam.principal_point_px[axis]


def _cos4(cam, i, j, x_px, y_px):
    mx, my = _lens_mm(cam, i, j)
    cx, cy = cam.principal_point_px
    sx, sy = (x_px - cx) * cam.pixel_mm, (y_px - cy) * cam.pixel_mm
    t2 = ((sx - mx) ** 2 + (sy - my) ** 2) / cam.sensor_distance_mm**2
    return 1.0 / (1.0 + t2) ** 2


def _render(options, u, lenses):
    ws = build_wave_spec(**{**CAMERA, **options})
    li = np.array([p[0] for p in lenses], dtype=np.int64)
    lj = np.array([p[1] for p in lenses], dtype=np.int64)
    signal, _, _ = lenses_signal(ws, u, li, lj)
    return ws.sweep.camera, signal.astype(np.float64)


def _edge_position(cam, signal, i, j, predicted, row, half=12.0):
    """Area-method position of a light(left)-to-dark(right) step along ``row`` (px).

    The (pixel-integrated) profile is divided by cos⁴ and normalised with the
    known reflectances, then integrated over the window ``predicted ± half``
    (fractional end pixels), symmetric about the edge, so the blur's tails cancel.
    """
    x_lo, x_hi = predicted - half, predicted + half
    xs = np.arange(math.floor(x_lo + 0.5), math.floor(x_hi + 0.5) + 1)
    prof = signal[row, xs] / _cos4(cam, i, j, xs, row)
    dark = (prof - 0.95) / (0.05 - 0.95)
    w = np.clip(np.minimum(xs + 0.5, x_hi) - np.maximum(xs - 0.5, x_lo), 0.0, 1.0)
    return x_hi - float((dark * w).sum())


# ---- 1. defocused PSF on the axis ------------------------------------------------------
@pytest.mark.parametrize("w20", [0.25, 0.5, 0.75])
def test_defocused_disc_psf_peak_follows_sinc_squared_of_the_rim_wavefront(w20: float) -> None:
    """I(0)/I_focus = |∫₀¹ exp(2πi·(W₂₀/λ)·t) dt|² = [sin(πW₂₀/λ)/(πW₂₀/λ)]² (t = ρ²).

    The pupil phase π|ξ|²c/λ is 2π·W/λ with W = |ξ|²c/2, so W₂₀ = (D/2)²c/2.
    """
    D, b = 0.125, 1.95
    c = 2.0 * w20 * LAM / (D / 2) ** 2
    pupil = Pupil("circle", D)
    spacing, size = LAM * b / D / 8.0, 512
    focus = fine_psf(pupil, LAM, b, 0.0, spacing, size).values
    defocus = fine_psf(pupil, LAM, b, c, spacing, size).values
    ratio = defocus[size // 2, size // 2] / focus[size // 2, size // 2]
    x = math.pi * w20
    expected = (math.sin(x) / x) ** 2
    print(f"W20 = {w20} λ: peak ratio {ratio:.5f}, expected {expected:.5f}")
    assert ratio == pytest.approx(expected, rel=0.01)


@pytest.mark.parametrize("w20", [0.3, 0.6])
def test_frame_kernel_defocus_follows_the_board_distance(w20: float) -> None:
    """The renderer's kernel at u: peak / in-focus peak = the square pupil's Fresnel result.

    Square pupil: the on-axis amplitude factors, ∫_{-D/2}^{D/2} exp(iπcξ²/λ) dξ
    = √(2λ/c)·(C(X) + iS(X)) with X = (D/2)·√(2c/λ) (Fresnel integrals), so
    I(0)/I_focus = [(C² + S²)/X²]², with c = |1/a(u) - 1/a_f| from OPTICS.md.
    """
    ws = build_wave_spec(**{**CAMERA, "oversample": 4})
    cam = ws.sweep.camera
    D = cam.mla_pitch_mm
    c = 2.0 * w20 * LAM / (D / 2) ** 2  # W20 = (D/2)²·c/2 at the middle of the side
    a_f = 1.0 / (1.0 / cam.mla_focal_mm - 1.0 / cam.sensor_distance_mm)
    v = cam.mla_distance_mm - 1.0 / (1.0 / a_f + c)
    u = v * cam.main_focal_mm / (v - cam.main_focal_mm)
    focus, _ = kernel_for(ws, cam.u_focus_mm)
    defocus, _ = kernel_for(ws, u)
    m, n = defocus.half_cells, focus.half_cells
    # on the axis (not the maximum); undo the renormalisation after the truncation
    ratio = (defocus.values[m, m] * (1 - defocus.truncated_energy)) / (
        focus.values[n, n] * (1 - focus.truncated_energy)
    )
    x = D / 2 * math.sqrt(2 * c / LAM)
    s_x, c_x = fresnel(x)
    expected = ((c_x**2 + s_x**2) / x**2) ** 2
    print(f"W20 = {w20} λ at u = {u:.2f} mm: kernel peak ratio {ratio:.5f}, Fresnel {expected:.5f}")
    assert ratio == pytest.approx(expected, rel=0.005)


# ---- 2. in-focus diffraction patterns ----------------------------------------------------
def _first_zero(profile: np.ndarray, x: np.ndarray, near: float) -> float:
    """The first minimum near ``near``: parabola through the smallest sample and its neighbours."""
    window = np.flatnonzero(np.abs(x - near) < 0.3 * near)
    k = window[np.argmin(profile[window])]
    y0, y1, y2 = profile[k - 1 : k + 2]
    return float(x[k] + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) * (x[1] - x[0]))


def test_in_focus_square_line_spread_is_sinc_squared_with_zero_at_lambda_b_over_d() -> None:
    D, b, cell = 0.125, 1.95, 0.0025 / 8
    kernel = frame_kernel(Pupil("square", D), (LAM,), b, 0.0, cell, 8 * 30)
    marginal = kernel.values.sum(axis=0)
    x = (np.arange(marginal.size) - kernel.half_cells) * cell
    unit = LAM * b / D
    zero = _first_zero(marginal, x, unit)
    model = np.sinc(x / unit) ** 2
    model *= marginal.max() / model.max()
    worst = float(np.abs(marginal - model).max() / marginal.max())
    print(f"square: first zero {zero / unit:.4f} λb/D, profile error {worst:.2e} of the peak")
    assert zero == pytest.approx(unit, rel=0.01)
    assert worst < 0.01


def test_in_focus_disc_psf_is_airy_with_zero_at_1_22_lambda_b_over_d() -> None:
    D, b, cell = 0.125, 1.95, 0.0025 / 8
    kernel = frame_kernel(Pupil("circle", D), (LAM,), b, 0.0, cell, 8 * 20)
    row = kernel.values[kernel.half_cells]
    x = (np.arange(row.size) - kernel.half_cells) * cell
    unit = LAM * b / D
    zero = _first_zero(row, x, 1.22 * unit)
    arg = np.pi * np.where(x == 0, 1e-12, x) / unit
    model = (2 * j1(arg) / arg) ** 2
    model *= row.max() / model.max()
    worst = float(np.abs(row - model).max() / row.max())
    print(f"disc: first zero {zero / unit:.4f} λb/D (Airy 1.2197), profile error {worst:.2e}")
    assert zero == pytest.approx(1.2197 * unit, rel=0.01)
    assert worst < 0.01


# ---- 3. geometric limit -------------------------------------------------------------------
def _geometric_dark_fraction(x_px: np.ndarray, edge: float, blur: float, shape: str) -> np.ndarray:
    """Pixel-integrated dark fraction of a step at ``edge`` blurred by the pupil's image.

    The defocused pupil image is uniform (side or diameter ``blur`` px); its
    x-marginal is a box (square) or a semicircle law (disc); a fine quadrature
    over the blur and the pixel.
    """
    t = (np.arange(4000) + 0.5) / 4000 - 0.5  # in units of the blur
    weight = np.ones_like(t) if shape == "square" else np.sqrt(1.0 - (2.0 * t) ** 2)
    weight /= weight.sum()
    q = (np.arange(200) + 0.5) / 200 - 0.5  # across the pixel
    out = []
    for x in x_px:
        s = x + q[:, None] - t[None, :] * blur  # source point of each (pixel point, blur offset)
        out.append(float(((s > edge) * weight[None, :]).sum() / q.size))
    return np.array(out)


@pytest.mark.parametrize("shape", ["square", "circle"])
def test_tiny_wavelength_gives_the_geometric_blur_of_the_pupil(shape: str) -> None:
    u = 103.5  # a clear defocus: the geometric blur is about 6 px
    options = {
        "wavelengths_um": (0.005,),
        "aperture": shape,
        "board_offset": (0.013, -5.0),  # the X = 0 edge near the axis, Y = 5 mid-square
    }
    cam, signal = _render(options, u, [(0, 0)])
    v, a, b = _optics(cam, u)
    a_f = 1.0 / (1.0 / cam.mla_focal_mm - 1.0 / b)
    blur = cam.mla_pitch_mm * b * abs(1.0 / a_f - 1.0 / a) / cam.pixel_mm
    assert 5.0 < blur < 7.0
    edge = _edge_px(cam, u, 0, 0, 0.013, 0)
    row = round(cam.principal_point_px[1])
    xs = np.arange(round(edge) - 8, round(edge) + 9)
    rendered = signal[row, xs] / _cos4(cam, 0, 0, xs, row)
    dark = (rendered - 0.95) / (0.05 - 0.95)
    expected = _geometric_dark_fraction(xs, edge, blur, shape)
    worst = float(np.abs(dark - expected).max())
    print(f"{shape}: blur {blur:.3f} px, worst profile error {worst:.4f} of the step")
    assert worst < 0.01


# ---- 4. energy: a uniform board ----------------------------------------------------------
def _brute_transmission(cam, i, j, x_px, y_px, n=96):
    """cos⁴(chief ray)·(fraction of an n×n grid of pupil points whose ray passes the stops).

    Each ray from the sensor point s through pupil point ξ is bent by the thin
    microlens (slope change -(ξ - m)/f going forward) and followed back to the
    main lens at z = 0 (aperture A); a second stop at 0 < Z < L is met on the
    way, one at Z < 0 after the main lens bends the ray (slope change -x0/F).
    """
    L, b, f = cam.mla_distance_mm, cam.sensor_distance_mm, cam.mla_focal_mm
    Z, A_v = cam.vignetting_stop_mm, cam.vignetting_diameter_mm
    mx, my = _lens_mm(cam, i, j)
    g = ((np.arange(n) + 0.5) / n - 0.5) * cam.mla_pitch_mm
    px, py = np.meshgrid(mx + g, my + g)
    if cam.microlens_aperture == "circle":
        keep = (px - mx) ** 2 + (py - my) ** 2 <= (cam.mla_pitch_mm / 2) ** 2
        px, py = px[keep], py[keep]
    cx, cy = cam.principal_point_px
    out = []
    for x, y in zip(x_px, y_px, strict=True):
        sx, sy = (x - cx) * cam.pixel_mm, (y - cy) * cam.pixel_mm
        slope_x = (sx - px) / b + (px - mx) / f  # between the main lens and the MLA
        slope_y = (sy - py) / b + (py - my) / f
        x0, y0 = px - L * slope_x, py - L * slope_y
        ok = x0**2 + y0**2 <= (cam.main_aperture_mm / 2) ** 2
        if Z is not None and Z > 0:
            zx, zy = px - (L - Z) * slope_x, py - (L - Z) * slope_y
            ok &= zx**2 + zy**2 <= (A_v / 2) ** 2
        elif Z is not None:
            F = cam.main_focal_mm
            zx = x0 + Z * (slope_x + x0 / F)  # object side: slope + x0/F
            zy = y0 + Z * (slope_y + y0 / F)
            ok &= zx**2 + zy**2 <= (A_v / 2) ** 2
        passed = np.mean(ok)
        out.append(passed * _cos4(cam, i, j, x, y))
    return np.array(out)


@pytest.mark.parametrize(
    ("shape", "stop"),
    [("square", None), ("circle", None), ("square", (14.5, 1.6)), ("circle", (-5.0, 2.6))],
)
def test_uniform_board_renders_reflectance_times_cos4_times_vignetting(
    shape: str, stop: tuple[float, float] | None
) -> None:
    u = 170.0
    options = {"aperture": shape, "board_offset": (1000.0, 1000.0), "theta_deg": 0.3}
    if stop is not None:  # a second stop behind (Z > 0) or in front of (Z < 0) the main lens
        options.update(vignetting_stop_mm=stop[0], vignetting_diameter_mm=stop[1])
    cam, signal = _render(options, u, [(1, -1)])
    ws = build_wave_spec(**{**CAMERA, **options})
    white = white_signal(ws).astype(np.float64)
    ys, xs = np.nonzero(signal)
    # no light lost or wrapped by the convolution: exactly the white image's 0.95·cos⁴·V
    assert np.abs(signal[ys, xs] - white[ys, xs]).max() < 2e-6
    # 0.95·cos⁴·V from a brute-force ray check, on pixels across the micro-image and its rim
    rng = np.random.default_rng(3)
    pick = rng.choice(xs.size, 150, replace=False)
    px, py = xs[pick], ys[pick]
    sub = (np.arange(2) + 0.5) / 2 - 0.5  # 2×2 points per pixel (V is smooth on 10 px)
    truth = np.mean(
        [_brute_transmission(cam, 1, -1, px + ox, py + oy) for ox in sub for oy in sub], axis=0
    )
    err = np.abs(signal[py, px] - 0.95 * truth)
    print(
        f"{shape} {stop}: V<1 on {np.mean(truth < 0.99):.0%} of picks, worst error {err.max():.4f}"
    )
    assert (truth < 0.5).any() and (truth > 0.99).any()  # the rim is covered
    assert err.max() < 0.006
    if stop is not None:  # the second stop really cuts light here
        plain = {k: v for k, v in options.items() if not k.startswith("vignetting")}
        unstopped = white_signal(build_wave_spec(**{**CAMERA, **plain}))
        assert np.abs(unstopped[py, px] - signal[py, px]).max() > 0.05


# ---- 5. geometry: where lens m images a main-image point ---------------------------------
GEOMETRY = {"theta_deg": 0.3, "mla_offset": (1.7, -2.3)}


def _step_position(profile: np.ndarray, first: int, predicted: float, half: float) -> float:
    """Area-method position of a light-to-dark step in a flat-fielded profile (px).

    ``profile[k]`` is pixel ``first + k`` divided by the uniform board's render,
    so 1 = light, 0.05/0.95 = dark. It is integrated over ``predicted ± half``
    (fractional end pixels): symmetric about the edge, so the blur's tails cancel.
    """
    dark = (profile - 1.0) / (0.05 / 0.95 - 1.0)
    assert dark[0] < 0.1 and dark[-1] > 0.9  # light before the step, dark after: upright
    pos = first + np.arange(profile.size)
    lo, hi = predicted - half, predicted + half
    w = np.clip(np.minimum(pos + 0.5, hi) - np.maximum(pos - 0.5, lo), 0.0, 1.0)
    return hi - float((dark * w).sum())


@pytest.mark.parametrize("axis", [0, 1])
def test_edges_lie_where_lens_m_images_main_image_point_r(axis: int) -> None:
    """Board +X is sensor +x inside a micro-image, and lens m puts r at m + (m - r)·b/a."""
    u, half = 160.0, 10.0
    # the edge under test near the axis, the other board line 5 mm away
    offset = (0.02, -5.0) if axis == 0 else (-5.0, 0.02)
    lenses = [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    cam, signal = _render({**GEOMETRY, "board_offset": offset}, u, lenses)
    _, flat = _render({**GEOMETRY, "board_offset": (1000.0, 1000.0)}, u, lenses)
    if axis == 1:  # a horizontal edge (X > 0: r = -1 above Y = 0 light, r = 0 below dark)
        signal, flat = signal.T, flat.T
    errors = {}
    for i, j in lenses:
        centre = cam.micro_image_centre_px(np.array([i]), np.array([j]))
        along, across = float(centre[axis][0]), float(centre[1 - axis][0])
        predicted = _edge_px(cam, u, i, j, 0.02, axis)
        if abs(predicted - along) > 16:
            continue
        line = round(across)
        first = round(predicted - half)
        pix = np.arange(first, round(predicted + half) + 1)
        profile = signal[line, pix] / flat[line, pix]
        errors[(i, j)] = _step_position(profile, first, predicted, half) - predicted
    print(
        f"axis {axis}: worst {max(abs(e) for e in errors.values()):.1e} px over {len(errors)} lenses"
    )
    lens_index = {k[axis] for k in errors}
    assert lens_index == {-1, 0, 1}  # lenses on both sides of the axis: the b/a law
    assert max(abs(e) for e in errors.values()) <= 0.02


# ---- 6. edge position aliasing ------------------------------------------------------------
def test_sub_pixel_board_shifts_move_the_edge_by_exactly_that() -> None:
    u = 150.0
    v, a, b = _optics(build_wave_spec(**CAMERA).sweep.camera, u)
    px_per_mm = v * b / (u * a) / CAMERA["pixel_mm"]  # OPTICS.md: ds/dP = (v/u)(b/a)
    positions = []
    shifts = [0.0, 0.1, 0.23, 0.37, 0.5, 0.71]
    for shift in shifts:
        lateral = 0.011 + shift / px_per_mm
        cam, signal = _render({"board_offset": (lateral, -5.0)}, u, [(0, 0)])
        predicted = _edge_px(cam, u, 0, 0, lateral, 0)
        row = round(cam.principal_point_px[1])
        positions.append(_edge_position(cam, signal, 0, 0, predicted, row))
    moved = np.array(positions) - positions[0]
    print("edge moves", np.round(moved - np.array(shifts), 5))
    assert np.abs(moved - np.array(shifts)).max() <= 0.005


# ---- polychromatic ------------------------------------------------------------------------
def test_polychromatic_kernel_is_the_mean_of_the_single_wavelength_kernels() -> None:
    pupil, b, cell = Pupil("square", 0.125, 0.35), 1.95, 0.0025 / 4
    waves = (0.45e-3, 0.55e-3, 0.65e-3)
    mixed = frame_kernel(pupil, waves, b, 0.01, cell, 4 * 25).values
    single = [frame_kernel(pupil, (w,), b, 0.01, cell, 4 * 25).values for w in waves]
    assert mixed.sum() == pytest.approx(1.0)
    assert np.abs(mixed - np.mean(single, axis=0)).max() < 1e-12


# ---- 7. archive -----------------------------------------------------------------------------
TINY = ["--preset", "small", "--frames", "2", "--corners", "standard", "--fit-frame"]


def test_small_preset_writes_a_valid_archive(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    args = [str(out), *TINY, "--start-mm", "40", "--wavelengths-um", "0.5,0.6", "--oversample", "4"]
    assert wavesim_main(args) == 0
    manifest = json.loads((out / "sweep.json").read_text())
    assert manifest["format"] == "lfcal-sweep/1" and manifest["generator"] == "wavesim"
    assert set(manifest) >= {"camera", "optics", "board", "rail", "white", "frames"}
    assert [f["rail_mm"] for f in manifest["frames"]] == [40.0, 41.0]
    assert manifest["optics"]["mla_pitch_mm"] == 0.125
    log = json.loads((out / "render_log.json").read_text())
    assert log["renderer"] == "wavesim" and log["wavelengths_um"] == [0.5, 0.6]
    assert log["oversample"] == 4
    truth = json.loads((out / "truth.json").read_text())
    assert truth["generator"] == "wavesim" and truth["render"]["wavelengths_um"] == [0.5, 0.6]
    cam = manifest["camera"]
    for name in ["white.png"] + [f["file"] for f in manifest["frames"]]:
        raw = (out / name).read_bytes()
        assert raw[:8] == b"\x89PNG\r\n\x1a\n" and raw[12:16] == b"IHDR"
        width, height, depth, colour = struct.unpack(">IIBB", raw[16:26])
        assert (width, height, depth, colour) == (cam["width"], cam["height"], 16, 0)
        image = cv2.imread(str(out / name), cv2.IMREAD_UNCHANGED)
        assert image is not None and image.dtype == np.uint16
        assert 3000 < image.max() <= 4095  # 12 bit, right-aligned
    assert wavesim_main([str(out), *TINY]) == 1  # a previous render, no --force


def test_ray_tracer_options_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert wavesim_main(["/nonexistent/x", "--preset", "small", "--oversample", "0"]) == 2
    assert "oversample" in capsys.readouterr().err
    with pytest.raises(ValueError, match="not a wavesim option"):
        build_wave_spec(preset="small", rays=4)


def test_cached_sweep_renders_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(wsweep, "CACHE_ROOT", tmp_path)
    options = {"preset": "small", "frames": 1, "corners": "standard", "fit_frame": True}
    first = wsweep.cached_sweep("one", jobs=1, oversample=2, **options)
    stamp = (first / "frames" / "0000.png").stat().st_mtime_ns
    again = wsweep.cached_sweep("one", jobs=1, oversample=2, **options)
    assert again == first and (again / "frames" / "0000.png").stat().st_mtime_ns == stamp
