"""The Monte-Carlo renderer's second circular stop (mechanical vignetting of the main
lens) against OPTICS.md's formulas, with no project code: a stop that blocks nothing
changes nothing, a stop's cut lies where its image through the lens centre predicts,
bad stops are refused and the truth and the cache key carry it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_mcsim import SMALL, _render, refused

from bench.mcsim import sweep as mcsweep
from bench.mcsim.render import WHITE, frame_rng, white_signal
from bench.mcsim.spec import build_spec

# ---- mechanical vignetting: a second circular stop ------------------------------------------
# TINY_SWEEP's camera: L = v(150) + a_f = 300/13 + 4.95 ≈ 28.03 mm, A = L·D/b ≈ 1.91 mm


def _images(out: Path) -> dict[str, bytes]:
    names = ["white.png", *sorted(f"frames/{p.name}" for p in (out / "frames").iterdir())]
    return {name: (out / name).read_bytes() for name in names}


def test_a_stop_that_never_clips_changes_no_pixel(tmp_path: Path) -> None:
    # the same seed draws the same rays; a stop that blocks none leaves every pixel as it was
    plain = _render(tmp_path, "plain", "--seed", "7")
    L = json.loads((plain / "truth.json").read_text())["L_mm"]
    A = 28.026923 * 0.075 / 1.1
    rear = _render(
        tmp_path, "rear", "--seed", "7",
        "--vignetting-stop-mm", f"{L / 2}", "--vignetting-diameter-mm", f"{10 * A}",
    )  # fmt: skip
    front = _render(
        tmp_path, "front", "--seed", "7",
        "--vignetting-stop-mm", "-10", "--vignetting-diameter-mm", f"{20 * A}",
    )  # fmt: skip
    images = _images(plain)
    assert len(images) == 4
    assert _images(rear) == images
    assert _images(front) == images


def _stop_image_px(cam, i: int, j: int, z_mm: float | None, diameter_mm: float | None):
    """Centre (x, y) and radius (px) of a stop's image in the micro-image of lens (i, j).

    A stop between the main lens and the MLA (0 < z < L) is seen as it is; one in
    front of the main lens (z < 0, object distance -z) through the main lens
    (OPTICS.md §1, 1/u + 1/v = 1/F): its image lies at z' = zF/(z + F) (in front of
    the lens for -z < F), magnified F/(z + F). A point r of a plane at z' projects
    through the lens centre c (z = L) onto the sensor (z = L + b) at
    c + (c - r)·b/(L - z'): the rim of a centred stop of radius R' becomes a circle
    of radius R'·b/(L - z') around c·(1 + b/(L - z')). The half-light edge of the
    micro-image lies there: the rays a sensor point sends through its lens cover
    a square around the ray through the lens centre, half of which passes when
    that ray grazes the rim. ``z_mm = None``: the main aperture (z' = 0).
    """
    F, L, b = cam.main_focal_mm, cam.mla_distance_mm, cam.sensor_distance_mm
    if z_mm is None or diameter_mm is None:
        z_img, r_img = 0.0, cam.main_aperture_mm / 2
    elif z_mm > 0:
        z_img, r_img = z_mm, diameter_mm / 2
    else:
        z_img, r_img = z_mm * F / (z_mm + F), diameter_mm / 2 * F / (z_mm + F)
    t = math.radians(cam.theta_deg)
    pitch = cam.mla_pitch_mm / cam.pixel_mm
    ox, oy = cam.lens_origin_px
    cx, cy = cam.principal_point_px
    lx = ox + pitch * (i * math.cos(t) - j * math.sin(t)) - cx  # lens centre, px from the axis
    ly = oy + pitch * (i * math.sin(t) + j * math.cos(t)) - cy
    scale = 1 + b / (L - z_img)
    return cx + lx * scale, cy + ly * scale, r_img * b / (L - z_img) / cam.pixel_mm


def _half_light_crossing(profile, xs, owned, level: float, start: int, step: int) -> float:
    """Where the profile first falls below ``level`` from ``start`` in direction ``step``."""
    k = start
    while profile[k] >= level:
        k += step
    assert owned[k] and owned[k - step]  # measured inside the lens's own cell
    high, low = profile[k - step], profile[k]
    return float(xs[k - step] + step * (high - level) / (high - low))


# the optical axis near the frame's left edge: lens 22 sits 1.65 mm off axis
OFF_AXIS = {
    **SMALL, "width": 768, "height": 48, "pp": (40.0, 23.5), "frames": 1, "rays": 4,
    "white_rays": 256, "subpixel": 2,
}  # fmt: skip
FAR_LENS = 22


@pytest.mark.parametrize(
    ("stop_mm", "diameter_mm", "clipped_side"),
    [(14.0, 2.0, "inner"), (-15.0, 1.9, "outer")],
    ids=["rear", "front"],
)
def test_stop_cuts_far_micro_images_where_its_image_predicts(
    stop_mm: float, diameter_mm: float, clipped_side: str
) -> None:
    # Along the radial direction the stop's image is shifted against the micro-image
    # by c·b·(1/(L - z') - 1/L): outward for a rear stop (z' > 0), so it cuts the side
    # towards the axis; inward for a front stop (z' < 0), so it cuts the side away
    # from it. Near the axis it is concentric and wider than the micro-image.
    plain_spec = build_spec(**OFF_AXIS)
    spec = build_spec(**OFF_AXIS, vignetting_stop_mm=stop_mm, vignetting_diameter_mm=diameter_mm)
    cam = spec.camera
    plain, _ = white_signal(plain_spec, frame_rng(plain_spec.seed, WHITE))
    stopped, _ = white_signal(spec, frame_rng(spec.seed, WHITE))
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    li, lj = cam.lens_of_pixels(xs, ys)
    # near the axis: every ray passes the stop, so the same seed gives the same pixels
    for i in (0, 1):
        cell = (li == i) & (lj == 0)
        assert cell.sum() > 800
        np.testing.assert_array_equal(stopped[cell], plain[cell])
    # far off axis: the half-light edge on the clipped side is the stop's image
    mx, my = cam.micro_image_centre_px(np.array(FAR_LENS), np.array(0))
    row, centre = round(float(my)), round(float(mx))
    owned = (li[row] == FAR_LENS) & (lj[row] == 0)
    plateau = float(plain[row, centre - 3 : centre + 4].mean())
    step = -1 if clipped_side == "inner" else 1  # the lens lies on the +x side of the axis
    sx, sy, radius = _stop_image_px(cam, FAR_LENS, 0, stop_mm, diameter_mm)
    predicted = sx + step * math.sqrt(radius**2 - (row - sy) ** 2)
    ax, ay, a_radius = _stop_image_px(cam, FAR_LENS, 0, None, None)
    main_edge = ax + step * math.sqrt(a_radius**2 - (row - ay) ** 2)
    assert 4.0 < step * (main_edge - predicted) < a_radius  # the cut lies inside the disc
    measured = _half_light_crossing(stopped[row], xs[row], owned, plateau / 2, centre, step)
    print(f"{clipped_side} edge: predicted {predicted:.2f} px, measured {measured:.2f} px")
    assert measured == pytest.approx(predicted, abs=0.5)
    # the edge is as sharp as the stop's defocus: D·b·|1/a_f - 1/(L - z')| wide; beyond
    # it (and a pixel) the clipped side is dark and the other side untouched
    F, L, b, f = cam.main_focal_mm, cam.mla_distance_mm, cam.sensor_distance_mm, cam.mla_focal_mm
    z_img = stop_mm if stop_mm > 0 else stop_mm * F / (stop_mm + F)
    blur = cam.mla_pitch_mm * b * abs(1 / f - 1 / b - 1 / (L - z_img)) / cam.pixel_mm
    reach = blur / 2 * math.sqrt(2) + 1.0
    along = step * (xs[row] - predicted)
    dark = owned & (along > reach)
    kept = owned & (along < -reach)
    assert dark.sum() >= 3 and kept.sum() >= 10
    assert np.all(stopped[row][dark] == 0.0) and np.any(plain[row][dark] > 0.5)
    np.testing.assert_array_equal(stopped[row][kept], plain[row][kept])
    # the lit area of the far micro-image shrinks; the near one's does not
    far = (li == FAR_LENS) & (lj == 0)
    assert stopped[far].sum() < 0.85 * plain[far].sum()


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["--vignetting-stop-mm", "14"], "needs both"),
        (["--vignetting-diameter-mm", "2"], "needs both"),
        (["--vignetting-stop-mm", "14", "--vignetting-diameter-mm", "0"], "diameter must be > 0"),
        (["--vignetting-stop-mm", "14", "--vignetting-diameter-mm", "-2"], "diameter must be > 0"),
        (["--vignetting-stop-mm", "0", "--vignetting-diameter-mm", "2"], "main lens itself"),
        (
            ["--vignetting-stop-mm", "28.5", "--vignetting-diameter-mm", "2"],
            "between the MLA and the sensor",
        ),
        (["--vignetting-stop-mm", "40", "--vignetting-diameter-mm", "2"], "behind the sensor"),
        (  # u = 148, 149, 150 mm: the first frame's board is in front of the stop
            ["--vignetting-stop-mm", "-148.5", "--vignetting-diameter-mm", "2"],
            "not beyond the vignetting stop",
        ),
    ],
)
def test_bad_vignetting_stops_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], reason: str
) -> None:
    err = refused(tmp_path, capsys, args)
    assert reason in err and err.startswith("mcsim: error: ")


def test_truth_and_render_log_carry_the_vignetting_stop(tmp_path: Path) -> None:
    plain = _render(tmp_path, "plain", "--frames", "1")
    stopped = _render(
        tmp_path, "stopped", "--frames", "1",
        "--vignetting-stop-mm=-12.5", "--vignetting-diameter-mm", "3.25",
    )  # fmt: skip
    for out, expected in ((plain, (None, None)), (stopped, (-12.5, 3.25))):
        for name in ("truth.json", "render_log.json"):
            data = json.loads((out / name).read_text())
            assert (data["vignetting_stop_mm"], data["vignetting_diameter_mm"]) == expected
    # the manifest is what a station knows: no stop there
    assert "vignetting" not in (stopped / "sweep.json").read_text()


def test_cache_key_tells_renders_with_and_without_the_stop_apart() -> None:
    options = {**SMALL, "frames": 2}
    plain = mcsweep._cache_key(options)
    assert "vignetting" not in plain  # renders cached before the option stay valid
    rear = mcsweep._cache_key({**options, "vignetting_stop_mm": 14.0, "vignetting_diameter_mm": 2})
    front = mcsweep._cache_key({**options, "vignetting_stop_mm": -5, "vignetting_diameter_mm": 2})
    assert len({plain, rear, front}) == 3
    assert build_spec(**options).camera.vignetting_stop_mm is None
