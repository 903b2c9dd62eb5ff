"""Mechanical vignetting of the main lens: where it starts, the lattice and shading
measured without the cut discs, and the pixels that still see the whole aperture.

The white images come from the Monte-Carlo ray tracer (``bench/mcsim``) with a second
circular stop behind the main lens, which cuts the micro-images far from the axis on
their side towards it (its image, projected through each lens centre, lies farther out
than the micro-image), or in front of it, which cuts them on the other side; the same
seed without the stop is the reference.
"""

from __future__ import annotations

import math
import warnings
from functools import cache
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from bench.mcsim.presets import PRESETS
from bench.mcsim.render import WHITE, frame_rng, white_signal
from bench.mcsim.spec import build_spec
from calibration.aperture_mask import ApertureMask, full_aperture_mask
from calibration.mla_grid import STATUS_VIGNETTED, fit_mla_grid
from calibration.shading import measure_shading
from calibration.vignetting import AREA_TOLERANCE, area_deficit, vignetting_onset

STOPS = {"rear": (12.0, 2.8), "front": (-15.0, 3.0)}
"""Axial position and diameter (mm) of a stop that cuts the small camera's micro-images
from ~800 px (rear) or ~550 px (front) off the axis."""

CAMERA = {**PRESETS["small"], "width": 1440, "height": 256, "pp": (1400.5, 127.5), "frames": 1}
FULL_LIGHT = 4000.0
PIXEL_NOISE = 0.007
"""Relative noise of each white pixel (about the Monte-Carlo white images' own)."""


def _stop(kind: str) -> dict[str, float]:
    if kind == "none":
        return {}
    z, diameter = STOPS[kind]
    return {"vignetting_stop_mm": z, "vignetting_diameter_mm": diameter}


@cache
def _white(kind: str) -> tuple[NDArray[np.float64], Any]:
    spec = build_spec(**CAMERA, rays=4, white_rays=64, subpixel=2, seed=3, **_stop(kind))
    signal, _ = white_signal(spec, frame_rng(spec.seed, WHITE))
    noise = np.random.default_rng(11).normal(0.0, PIXEL_NOISE, signal.shape)
    white = FULL_LIGHT * signal.astype(np.float64) * (1.0 + noise)
    return white, spec.camera


@cache
def _grid(kind: str) -> Any:
    white, cam = _white(kind)
    return fit_mla_grid(
        white,
        lens_pitch_px=cam.mla_pitch_mm / cam.pixel_mm,
        principal_point_px=CAMERA["pp"],
    )


def _true_scale(cam: Any) -> float:
    return (cam.mla_distance_mm + cam.sensor_distance_mm) / cam.mla_distance_mm


def test_no_deficit_means_no_vignetting() -> None:
    rng = np.random.default_rng(0)
    radius = rng.uniform(0.0, 2500.0, 3000)
    for seed in range(20):
        area = 2000.0 * (1.0 + np.random.default_rng(seed).normal(0.0, 0.0017, radius.size))
        assert vignetting_onset(radius, area, 53.0) == math.inf


def test_the_onset_is_where_the_rings_lose_area() -> None:
    rng = np.random.default_rng(1)
    radius = rng.uniform(0.0, 2500.0, 3000)
    # a cut that grows linearly beyond 1400 px: 1 % of the disc 100 px further out
    cut = np.clip((radius - 1400.0) / 100.0, 0.0, None) * 0.01
    area = 2000.0 * (1.0 - cut) * (1.0 + rng.normal(0.0, 0.0017, radius.size))
    onset = vignetting_onset(radius, area, 53.0)
    # the first ring whose median has lost the tolerance, less a pitch
    assert 1400.0 - 3 * 53.0 <= onset <= 1400.0 + 100 * AREA_TOLERANCE / 0.01
    deficit = area_deficit(radius, area)
    assert abs(float(np.median(deficit[radius < 1000]))) < 3e-4


@pytest.mark.parametrize("kind", ["rear", "front"])
def test_the_lattice_leaves_the_cut_discs_out(kind: str) -> None:
    plain, vignetted = _grid("none"), _grid(kind)
    cam = _white(kind)[1]
    assert plain.vignetting_onset_px == math.inf
    assert plain.rejected["vignetted"] == 0
    onset = vignetted.vignetting_onset_px
    assert 400.0 < onset < 1100.0, onset
    assert vignetted.rejected["vignetted"] > 25
    # the cut discs' centroids lie off the lattice, pushed from the cut side (a rear stop
    # cuts the side towards the axis, a front stop the side away from it): fitted with
    # them, the pitch (so (L+b)/L and b) was 4e-3 too large on the benchmark's camera
    out = vignetted.lens_status == STATUS_VIGNETTED
    dx = vignetted.measured_x[out] - CAMERA["pp"][0]
    dy = vignetted.measured_y[out] - CAMERA["pp"][1]
    r = np.hypot(dx, dy)
    outward_px = (dx * vignetted.residual_x[out] + dy * vignetted.residual_y[out]) / r
    sign = 1.0 if kind == "rear" else -1.0
    assert sign * np.median(outward_px[r > onset + 300]) > 0.3
    # without them the scale is the unvignetted white's within the statistics of the
    # fewer micro-images it keeps (inside the onset the cut white's centroids are the
    # unvignetted one's to the last digit), and the truth's within the rim-shading pull
    se = float(np.hypot(vignetted.scale_se, plain.scale_se))
    assert abs(vignetted.scale - plain.scale) < max(3.0 * se, 1e-5), (vignetted.scale, se)
    pull = 3e-5  # the shaded rims' pull (calibration.mla_grid), modelled downstream
    assert abs(vignetted.scale - _true_scale(cam)) < 3.0 * vignetted.scale_se + pull
    assert vignetted.to_dict()["vignetting_onset_px"] == pytest.approx(onset)
    assert plain.to_dict()["vignetting_onset_px"] is None


def test_the_shading_is_measured_inside_the_onset() -> None:
    plain, vignetted = _grid("none"), _grid("rear")
    white_plain, white_cut = _white("none")[0], _white("rear")[0]
    ref = measure_shading(white_plain, plain.image_grid, lens_grid=plain.lens_grid)
    cut_all = measure_shading(white_cut, vignetted.image_grid, lens_grid=vignetted.lens_grid)
    inside = measure_shading(
        white_cut,
        vignetted.image_grid,
        lens_grid=vignetted.lens_grid,
        unvignetted=(CAMERA["pp"], vignetted.vignetting_onset_px),
    )
    # over the whole sensor the cut discs bend the shading (the micro-images tilt the
    # wrong way); inside the onset it is the unvignetted white's
    assert not cut_all.interior_consistent
    assert inside.interior_consistent
    assert inside.plateau_fraction == pytest.approx(ref.plateau_fraction, abs=0.03)
    c, c_ref = inside.angular_curvature()[0], ref.angular_curvature()[0]
    assert c == pytest.approx(c_ref, rel=0.3, abs=2e-6)


def _mask(
    white: NDArray[np.float64], grid: Any, *, onset_px: float | None = None
) -> tuple[ApertureMask | None, float]:
    """The pipeline's steps: the shading inside the grid's onset, then the aperture mask of
    the micro-images beyond ``onset_px`` (default the grid's); and the plateau's radius."""
    shading = measure_shading(
        white,
        grid.image_grid,
        lens_grid=grid.lens_grid,
        unvignetted=(CAMERA["pp"], grid.vignetting_onset_px),
    )
    flat = shading.flat_field(0.0)
    assert flat is not None
    plateau_px = shading.plateau_fraction * 0.5 * grid.image_pitch_px
    mask = full_aperture_mask(
        white,
        grid.image_grid,
        grid.lens_grid,
        flat,
        plateau_px=plateau_px,
        principal_point_px=CAMERA["pp"],
        onset_px=grid.vignetting_onset_px if onset_px is None else onset_px,
    )
    return mask, plateau_px


@pytest.mark.parametrize("kind", ["rear", "front"])
def test_the_mask_keeps_the_pixels_that_see_the_whole_aperture(kind: str) -> None:
    vignetted = _grid(kind)
    white, cam = _white(kind)
    mask, plateau_px = _mask(white, vignetted)
    assert mask is not None and mask.micro_images > 30
    assert _mask(white, vignetted, onset_px=math.inf)[0] is None
    # the truth: a pixel sees its whole aperture where the stop passes all its rays; the
    # renderer without the stop (same seed, no noise) against with it
    spec_kw = {"rays": 4, "white_rays": 64, "subpixel": 2, "seed": 3}
    plain_spec = build_spec(**CAMERA, **spec_kw)
    stop_spec = build_spec(**CAMERA, **_stop(kind), **spec_kw)
    plain_signal, _ = white_signal(plain_spec, frame_rng(plain_spec.seed, WHITE))
    stop_signal, _ = white_signal(stop_spec, frame_rng(stop_spec.seed, WHITE))
    passed = stop_signal / np.maximum(plain_signal, 1e-9)
    ii, jj = vignetted.image_grid.indices_in(cam.width, cam.height, margin_px=plateau_px + 1)
    cx, cy = vignetted.image_grid.centre(ii, jj)
    far = np.hypot(cx - CAMERA["pp"][0], cy - CAMERA["pp"][1]) > vignetted.vignetting_onset_px
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    kept_clipped, unclipped, unclipped_dropped, cut_side = [], 0, 0, []
    for x, y in zip(cx[far], cy[far], strict=True):
        disc = (xs - x) ** 2 + (ys - y) ** 2 <= plateau_px**2
        keep = mask.full[disc]
        frac = passed[disc]
        kept_clipped.extend((1.0 - frac[keep]).tolist())
        whole = frac >= 1.0 - 1e-6
        unclipped += int(whole.sum())
        unclipped_dropped += int((whole & ~keep).sum())
        if (~keep).sum() > 30:  # a cut, not a few noisy pixels near the onset
            # where the cut lies: + towards the axis (on the +x side of these micro-images)
            cut_side.append(float(np.mean(xs[disc][~keep]) - x))
    # no kept pixel loses more than a few % of its aperture and hardly any more than 1 %
    # (the tolerance is 0.56 %, on the ratio smoothed over 5 px); of the pixels that lose
    # nothing few are dropped (the smoothing's reach)
    clips = np.array(kept_clipped)
    assert clips.max() < 0.05, clips.max()
    assert np.mean(clips > 0.01) < 0.01, np.mean(clips > 0.01)
    assert unclipped_dropped < 0.15 * unclipped, (unclipped_dropped, unclipped)
    sign = 1.0 if kind == "rear" else -1.0
    assert all(sign * dx > 3.0 for dx in cut_side) and len(cut_side) > 20, cut_side


def test_a_micro_image_the_vignetting_darkens_whole_keeps_no_pixel() -> None:
    """At the far corners of a full sensor the vignetting can take a micro-image's whole
    light (a 5120×5120 white image of the paper's camera had such discs): its level is 0,
    and none of its pixels may count as seeing the whole aperture."""
    vignetted = _grid("rear")
    white, cam = _white("rear")
    white = white.copy()
    ii, jj = vignetted.image_grid.indices_in(cam.width, cam.height, margin_px=30.0)
    cx, cy = vignetted.image_grid.centre(ii, jj)
    far = int(np.argmax(np.hypot(cx - CAMERA["pp"][0], cy - CAMERA["pp"][1])))
    x, y = round(float(cx[far])), round(float(cy[far]))
    white[y - 26 : y + 27, x - 26 : x + 27] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mask, _ = _mask(white, vignetted)
    assert mask is not None
    assert not mask.full[y - 5 : y + 6, x - 5 : x + 6].any()
    assert 0.002 <= mask.tolerance < 0.02
