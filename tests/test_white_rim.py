"""The rims of a white image's micro-images against the optics that formed them.

The whites are rendered by the Monte-Carlo ray tracer (bench.mcsim, rays through the
real apertures, no model of a rim), and the rims' blur is compared with OPTICS.md §1: the
main aperture, at ``Q = b/L``, blurred by the microlens aperture scaled to
``(D/δ)·|Q0 - b/L|``.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.mcsim.render import WHITE, frame_rng, white_signal
from bench.mcsim.spec import build_spec
from calibration.mla_grid import fit_mla_grid
from calibration.white_rim import measure_rim

# mcsim's 50 px camera (focus at u = 220.3 mm) and an 80 px one, through small windows
CAMERAS = {
    "50px": {"main_focal_mm": 25.0, "mla_focal_mm": 1.5, "mla_pitch_mm": 0.125, "b_mm": 1.95,
             "u0_mm": 220.3},
    "80px": {"main_focal_mm": 50.0, "mla_focal_mm": 2.0, "mla_pitch_mm": 0.2, "b_mm": 2.4,
             "u0_mm": 400.0},
}  # fmt: skip
KAPPA = {"square": 1.0, "circle": float(np.sqrt(12.0 / 16.0))}
"""The RMS scale of each aperture against a square of the full pitch (calibration.defocus)."""


def _white(camera: str, aperture: str, size: int = 320, **extra: float):
    spec = build_spec(
        width=size,
        height=size,
        pixel_mm=0.0025,
        theta_deg=0.3,
        aperture=aperture,
        white_rays=32,
        subpixel=2,
        **CAMERAS[camera],
        **extra,
    )
    signal, _ = white_signal(spec, frame_rng(1, WHITE))
    image = 3000.0 * signal + 50.0
    pitch = spec.camera.mla_pitch_mm / spec.camera.pixel_mm
    grid = fit_mla_grid(image, lens_pitch_px=pitch, principal_point_px=((size - 1) / 2,) * 2)
    cam = spec.camera
    q0 = cam.sensor_distance_mm / CAMERAS[camera]["mla_focal_mm"] - 1.0
    beta = cam.sensor_distance_mm / cam.mla_distance_mm
    return image, grid, pitch, q0, beta


@pytest.mark.parametrize("aperture", ["square", "circle"])
@pytest.mark.parametrize("camera", ["50px", "80px"])
def test_the_rims_show_the_microlens_aperture(camera: str, aperture: str) -> None:
    """12-13 px of rim defocus: the rims' variance gives the aperture's RMS scale within 5 %
    (the 2×2 point samples per pixel, variance 1/16 px², are the static blur)."""
    image, grid, pitch, q0, beta = _white(camera, aperture, size=320 if camera == "50px" else 480)
    rim = measure_rim(image, grid.image_grid, background=grid.background)
    assert rim is not None
    kappa = rim.aperture_scale(q0=q0, q_rim=beta, lens_pitch_px=pitch, static_rms_px=0.25)
    assert kappa == pytest.approx(KAPPA[aperture], rel=0.05)
    # the rim's mean radius is the main aperture's image: A/2·(b/L)/δ, A = L·D/b
    assert rim.radius_px == pytest.approx(pitch / 2, rel=0.02)
    # with the static blur left in, the scale is larger; a wrong Q0 scales it
    assert rim.aperture_scale(q0=q0, q_rim=beta, lens_pitch_px=pitch, static_rms_px=0.0) > kappa
    half_q0 = rim.aperture_scale(
        q0=beta + 2.0 * (q0 - beta), q_rim=beta, lens_pitch_px=pitch, static_rms_px=0.25
    )
    assert half_q0 == pytest.approx(kappa / 2.0, rel=1e-9)


def test_rims_cut_by_their_cells_are_not_measured() -> None:
    """A main aperture 1.2 times the matched one: the discs overlap their neighbours' cells
    and the rims are cut, so no width is claimed (the lattice fit refuses such a white; its
    lattice is the matched white's: the discs' centres do not depend on their size)."""
    _, grid, *_ = _white("50px", "square")
    matched = 34.7 * 0.125 / 1.95  # L·D/b of the 50 px camera
    spec = build_spec(
        width=320,
        height=320,
        pixel_mm=0.0025,
        theta_deg=0.3,
        white_rays=32,
        main_aperture_mm=1.2 * matched,
        **CAMERAS["50px"],
    )
    image = 3000.0 * white_signal(spec, frame_rng(1, WHITE))[0] + 50.0
    assert measure_rim(image, grid.image_grid, background=grid.background) is None


def test_no_micro_image_clear_of_the_vignetting_is_not_measured() -> None:
    image, grid, *_ = _white("50px", "square")
    assert (
        measure_rim(
            image,
            grid.image_grid,
            background=grid.background,
            unvignetted=(grid.principal_point_px, 10.0),
        )
        is None
    )
