"""Edge profiles cut by a corner's lattice from every micro-image that shows its half-edges.

A synthetic frame of micro-images, each showing the standard corner where the
disparity model puts it (``s = (1+Q)·m + c``), blurred by a known Gaussian:
the profiles, placed against the predicted edges and pooled, must give back
that edge spread; they must come from micro-images beyond those that contain
the corner; and the placement jitter must count only how the placement errors
spread over the profiles, not their common shift.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.special import ndtr

from calibration.edge_profiles import CornerLattice, ProfileWindow, half_edge_profiles
from calibration.edge_spread import LEVER_GROUPS, BinnedEsf, EdgeProfiles, frame_esf
from calibration.flat_field import FlatField
from calibration.lens_grid import LensGrid
from calibration.placement_error import PlacementError

PITCH, Q, SIGMA, RADIUS = 40.0, 0.25, 0.7, 14.0
DARK, LIGHT = 100.0, 900.0


def _frame(
    *,
    width: int = 720,
    height: int = 480,
    corner: tuple[float, float] = (-3.3, 2.6),
    slopes: tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, LensGrid, LensGrid, tuple[float, float, float]]:
    """Micro-images on a lens lattice; each shows the corner at ``s = (1+Q)·m + c``, its
    vertical edge at ``x = s_x + slopes[0]·(y - s_y)``, its horizontal one at
    ``y = s_y + slopes[1]·(x - s_x)`` (a board turned about the axis)."""
    lens = LensGrid((361.2, 239.7), PITCH, np.radians(0.3))
    image = LensGrid(lens.origin_px, PITCH * 1.02, lens.rotation_rad)  # centres ≈ (L+b)/L apart
    # the main image of the corner, r, sits at `corner` (in lens pitches) from lens (0, 0)
    rx, ry = lens.centre(*corner)
    coef = (1.0 + Q, -Q * float(rx), -Q * float(ry))
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    i, j = image.nearest(xx, yy)
    cx, cy = image.centre(i, j)
    mx, my = lens.centre(i, j)
    sx, sy = coef[0] * mx + coef[1], coef[0] * my + coef[2]
    u = ndtr((xx - sx - slopes[0] * (yy - sy)) / SIGMA)
    v = ndtr((yy - sy - slopes[1] * (xx - sx)) / SIGMA)
    light = u * (1 - v) + (1 - u) * v  # the standard corner: dark where x, y have one sign
    frame = DARK + (LIGHT - DARK) * light
    frame[np.hypot(xx - cx, yy - cy) > 0.5 * image.pitch_px - 1] = 10.0  # dark gaps
    rng = np.random.default_rng(3)
    return frame + rng.normal(0.0, 2.0, frame.shape), lens, image, coef


def _window() -> ProfileWindow:
    return ProfileWindow(plateau_px=RADIUS, clearance_px=3.0, reach_px=400.0, half_px=6)


def test_profiles_of_every_micro_image_give_back_the_edge_spread() -> None:
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    placed = half_edge_profiles(frame, lattice, lens, image, _window())
    profiles = placed.profiles
    # an exact lattice: what is left is the slopes' own uncertainty (edge_slope)
    assert placed.jitter_px < 0.002
    np.testing.assert_allclose(placed.slope_corrections, 0.0, atol=2e-5)
    esf = frame_esf(profiles, start_width_px=SIGMA)
    assert esf is not None
    inside = np.abs(esf.x) < 4.0
    np.testing.assert_allclose(esf.value[inside], ndtr(esf.x[inside] / SIGMA), atol=0.004)
    # the blocks come from many more micro-images than the few that show the corner itself
    assert int(profiles.block.max()) + 1 > 40


@pytest.mark.parametrize("slopes", [(3e-3, -2e-3), (-1e-3, 1.5e-3)])
def test_the_edges_slopes_come_from_all_the_profiles(slopes: tuple[float, float]) -> None:
    """A board turned about the axis by a few milliradians, the lattice's slopes left at
    0 (as a median of a few noisy micro-images' own can be): profiles up to 400 px along
    the edge would sit ~1 px off. The slopes measured on the pooled profiles put them
    back: the pooled function is the edge spread again."""
    frame, lens, image, coef = _frame(slopes=slopes)
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    placed = half_edge_profiles(frame, lattice, lens, image, _window())
    np.testing.assert_allclose(placed.slope_corrections, slopes, atol=3e-5)
    esf = frame_esf(placed.profiles, start_width_px=SIGMA)
    assert esf is not None
    inside = np.abs(esf.x) < 4.0
    np.testing.assert_allclose(esf.value[inside], ndtr(esf.x[inside] / SIGMA), atol=0.004)


def test_no_profile_reaches_the_corner_or_leaves_the_plateau() -> None:
    frame, lens, image, coef = _frame()
    window = _window()
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    profiles = half_edge_profiles(frame, lattice, lens, image, window).profiles
    # a profile through the corner's other edge, or through a dark gap, would not be a
    # clean step: every profile is flat at both ends
    z = (profiles.y - DARK) / (LIGHT - DARK)
    first, last = z[:, :2], z[:, -2:]
    assert np.all(np.minimum(np.abs(first), np.abs(first - 1.0)) < 0.05)
    assert np.all(np.minimum(np.abs(last), np.abs(last - 1.0)) < 0.05)
    assert np.all(np.abs(first.mean(axis=1) - last.mean(axis=1)) > 0.9)


def test_profiles_are_flat_fielded_by_the_white_images_shading() -> None:
    """A micro-image's brightness is the white image's smooth shading about its centre
    ``c_i``: a bowl (the rims blurred inwards, vignetting; curvature ``c``) tilted by the
    angular shading off the axis (``-c_t·(c_i - m_i)``). Given both, every profile is
    flat-fielded before its levels are read, and the pooled function is the edge spread
    without any drift fitted; left in, the bowl bends the function's tails."""
    frame, lens, image, coef = _frame()
    height, width = frame.shape
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    i, j = image.nearest(xx, yy)
    cx, cy = image.centre(i, j)
    mx, my = lens.centre(i, j)
    curvature, tilt, gap = 4e-4, 2e-3, 10.0
    log_w = -tilt * ((cx - mx) * (xx - cx) + (cy - my) * (yy - cy)) - 0.5 * curvature * (
        (xx - cx) ** 2 + (yy - cy) ** 2
    )
    shaded = gap + (frame - gap) * np.exp(log_w)
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    window = ProfileWindow(
        plateau_px=RADIUS,
        clearance_px=3.0,
        reach_px=400.0,
        half_px=6,
        flat_field=FlatField(curvature_px2=curvature, background=gap, tilt_curvature_px2=tilt),
    )
    flat = frame_esf(
        half_edge_profiles(shaded, lattice, lens, image, window).profiles,
        start_width_px=SIGMA,
        drift=False,
    )
    assert flat is not None
    np.testing.assert_allclose(flat.value, ndtr(flat.x / SIGMA), atol=0.004)
    bent = frame_esf(
        half_edge_profiles(shaded, lattice, lens, image, _window()).profiles,
        start_width_px=SIGMA,
        drift=False,
    )
    assert bent is not None
    assert np.max(np.abs(bent.value - ndtr(bent.x / SIGMA))) > 0.01


def test_an_error_of_the_lattice_offset_blurs_the_pooled_function() -> None:
    """The halves of an edge on either side of the corner have opposite polarity, so an
    error of ``c`` moves their profiles' signed distances in opposite directions: it
    spreads them by its whole size."""
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.diag([0.0, 0.04, 0.04]))
    placed = half_edge_profiles(frame, lattice, lens, image, _window())
    assert placed.jitter_px == pytest.approx(0.2, rel=0.1)
    # not the scale's: knowing the scale leaves it
    assert placed.jitter_fixed_scale_px == pytest.approx(placed.jitter_px, rel=1e-9)


def test_an_error_of_1_plus_q_blurs_by_the_lenses_spread() -> None:
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.diag([1e-6, 0.0, 0.0]))
    placed = half_edge_profiles(frame, lattice, lens, image, _window())
    # lens centres spread over the frame by about ±300 px: a 1e-3 error of 1+Q, ~0.2 px
    assert 0.1 < placed.jitter_px < 0.3
    # with the scale known there is no error left but the measured slopes' (edge_slope)
    assert placed.jitter_fixed_scale_px < 0.002
    # the levers are the lens centres' coordinates across the edge: their spread is the
    # jitter per unit scale error
    lever = placed.profiles.lever
    assert lever is not None and lever.shape == (placed.profiles.count,)
    assert np.std(lever) * 1e-3 == pytest.approx(placed.jitter_px, rel=0.01)


def test_the_pooled_function_records_the_spread_of_the_profiles_it_weighs() -> None:
    """The frame's profiles with the largest levers show no edge (their micro-images are
    dark, as outside a renderer's window): the function drops them, and the jitter it
    records is the spread of the others' placement errors, less than over all of them."""
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.diag([1e-6, 0.0, 0.0]))
    placed = half_edge_profiles(frame, lattice, lens, image, _window())
    lever = placed.profiles.lever
    assert lever is not None
    far = np.abs(lever - np.median(lever)) > 0.6 * np.max(np.abs(lever - np.median(lever)))
    dark_y = placed.profiles.y.copy()
    dark_y[far] = 10.0 + np.random.default_rng(5).normal(0.0, 2.0, dark_y[far].shape)
    profiles = EdgeProfiles(placed.profiles.x, dark_y, placed.profiles.block, lever)
    esf = frame_esf(profiles, start_width_px=SIGMA, placement=placed.placement)
    assert esf is not None
    shown = ~far
    expected = float(np.sqrt(np.var(lever[shown]))) * 1e-3  # the scale's error, 1e-3
    assert esf.jitter_px == pytest.approx(expected, rel=0.1)
    assert esf.jitter_px < 0.8 * placed.jitter_px


def test_a_wrong_lattice_scale_blurs_and_placing_again_by_lever_undoes_it() -> None:
    """Profiles placed with a scale 1e-3 off are moved by up to ~0.3 px (lens centres up to
    ~250 px from the fit's pivot): pooled they are a blurred step. Binned by lever and moved back by the
    scale error (as the sweep does with its smoothed scale) they give back the true function."""
    frame, lens, image, coef = _frame()
    error = 1e-3
    mx, my = lens.centre(0, 0)
    wrong = (coef[0] + error, coef[1] - error * float(mx), coef[2] - error * float(my))
    # the fit's errors pivot about lens (0, 0): the offset errs with the scale
    along = np.array([1.0, -float(mx), -float(my)])
    covariance = 1e-8 * np.outer(along, along)
    placed = half_edge_profiles(
        frame, CornerLattice(coef=wrong, covariance=covariance), lens, image, _window()
    )
    # pooled as placed (each half-edge not centred on its own edge first)
    unlabelled = dataclasses.replace(placed.profiles, half_edge=None)
    esf = frame_esf(unlabelled, start_width_px=SIGMA, jitter_fixed_scale_px=0.0)
    assert esf is not None and len(esf.lever_groups) == LEVER_GROUPS

    # a shift common to all profiles is the defocus model's to fit: compare about each centre
    def worst(f: BinnedEsf, sigma: float) -> float:
        x = f.x - f.centre_px()
        inside = np.abs(x) < 4.0
        return float(np.max(np.abs(f.value[inside] - ndtr(x[inside] / sigma))))

    assert worst(esf, SIGMA) > 0.03
    again = esf.replaced(error, 0.0)
    # the groups' own spread of levers (a small part of the whole) is left as jitter
    assert 0.0 < again.jitter_px < 0.3 * float(np.std(placed.profiles.lever)) * error
    assert worst(again, float(np.hypot(SIGMA, again.jitter_px))) < 0.006
    # and the function survives its round trip through the frame summary's JSON
    back = BinnedEsf.from_dict(esf.to_dict()).replaced(error, 0.0)
    np.testing.assert_allclose(back.value, again.value, atol=1e-5)  # JSON rounding
    # each half-edge centred on its own edge: the scale error's part common to a half-edge
    # is gone, what varies within one is left, and placing again by lever undoes that too
    centred = frame_esf(placed.profiles, start_width_px=SIGMA, jitter_fixed_scale_px=0.0)
    assert centred is not None and len(centred.lever_groups) == LEVER_GROUPS
    assert worst(centred, SIGMA) < 0.5 * worst(esf, SIGMA)
    centred_again = centred.replaced(error, 0.0)
    assert worst(centred_again, float(np.hypot(SIGMA, centred_again.jitter_px))) < 0.006


def _lattice_only(gradients: np.ndarray, sigma: np.ndarray) -> PlacementError:
    n = gradients.shape[0]
    return PlacementError(gradients, sigma, np.zeros(n), np.zeros(n), np.zeros(n, np.int64))


def test_a_shift_common_to_every_profile_is_not_counted_as_jitter() -> None:
    """The defocus model fits each function's position; only the spread about it blurs."""
    sigma = np.diag([0.0, 0.0, 0.0, 0.01, 0.0])
    same = np.tile([0.0, 0.0, 0.0, 1.0, 0.0], (50, 1))
    assert _lattice_only(same, sigma).jitter_px() == pytest.approx(0.0, abs=1e-8)  # rounding
    mixed = same * np.repeat([1.0, -1.0], 25)[:, None]
    assert _lattice_only(mixed, sigma).jitter_px() == pytest.approx(0.1)


def test_the_jitter_is_the_spread_the_pooled_function_weighs() -> None:
    """Profiles that err far more than the rest but carry no weight in the pooled function
    (no edge where they were cut) add nothing to its spread; weighted, it is the spread of
    the weighted errors, drawn many times."""
    rng = np.random.default_rng(3)
    n = 200
    lever = np.linspace(-100.0, 100.0, n)  # a profile's lever on the scale and on a slope
    gradients = np.zeros((n, 5))
    gradients[:, 0] = lever
    gradients[:, 1] = 1.0
    sigma = np.diag([1e-7, 1e-4, 0.0, 0.0, 0.0])
    axis = (np.arange(n) % 2).astype(np.int64)
    slope_var = np.where(axis == 0, 4e-8, 1e-8)
    placement = PlacementError(gradients, sigma, lever, slope_var, axis)
    weights = np.where(np.abs(lever) > 60.0, 0.0, 1.0 + rng.uniform(size=n))
    # Monte-Carlo: draw the lattice's and the slopes' errors, spread the profiles by them
    spreads = []
    for _ in range(4000):
        delta = rng.normal(0.0, np.sqrt(np.diag(sigma)))
        slope = rng.normal(0.0, np.sqrt([4e-8, 1e-8]))
        e = gradients @ delta + slope[axis] * lever
        mean = np.average(e, weights=weights)
        spreads.append(np.average((e - mean) ** 2, weights=weights))
    assert placement.jitter_px(weights) == pytest.approx(np.sqrt(np.mean(spreads)), rel=0.03)
    assert placement.jitter_px(weights) < 0.7 * placement.jitter_px()
    # the scale known: only the slopes' part is left (the offset moves every profile alike)
    slopes_only = PlacementError(np.zeros((n, 5)), sigma, lever, slope_var, axis)
    assert placement.jitter_px(weights, scale_known=True) == pytest.approx(
        slopes_only.jitter_px(weights), rel=1e-9
    )


def _scale_only_esf(
    frame: np.ndarray, lens: LensGrid, image: LensGrid, coef: tuple[float, float, float]
) -> BinnedEsf:
    """The frame's pooled function, its lattice uncertain in the scale only (lever groups)."""
    along = np.array([1.0, 0.0, 0.0])
    placed = half_edge_profiles(
        frame,
        CornerLattice(coef=coef, covariance=1e-8 * np.outer(along, along)),
        lens,
        image,
        _window(),
    )
    esf = frame_esf(placed.profiles, start_width_px=SIGMA, jitter_fixed_scale_px=0.0)
    assert esf is not None and esf.lever_groups
    return esf


def test_placed_again_with_no_error_is_the_whole_function() -> None:
    """The lever groups hold the same samples with the same weights: merged back without a
    shift they are the pooled function, bin for bin."""
    esf = _scale_only_esf(*_frame())
    again = BinnedEsf.from_dict(esf.to_dict()).replaced(0.0, 0.0)
    np.testing.assert_allclose(again.x, esf.x, atol=1e-4)  # JSON rounding
    np.testing.assert_allclose(again.value, esf.value, atol=1e-5)  # JSON rounding
    np.testing.assert_allclose(again.se, esf.se, rtol=1e-3)  # JSON rounding
    np.testing.assert_allclose(again.position_sd_px, esf.position_sd_px, atol=1e-4)


def test_dim_profiles_keep_their_weights_through_json() -> None:
    """A profile weighs its contrast squared, so weights span decades: a frame whose left
    half is 40x dimmer (weights 6e-4 of the others) still gives finite functions placed
    again, the dim bins kept (rounded to fixed decimals their weights were 0: NaN bins).
    (Profiles below 1/50 of the typical step are dropped as unlit,
    ``test_edge_spread.py::test_profiles_in_unlit_parts_of_the_frame_are_dropped``.)"""
    frame, lens, image, coef = _frame()
    dim = frame.astype(np.float64)
    dim[:, : dim.shape[1] // 2] /= 40.0
    esf = _scale_only_esf(dim, lens, image, coef)
    weights = np.concatenate([g.esf.sample_weight for g in esf.lever_groups])
    assert weights.min() < 1e-3 * weights.max()  # the dim profiles' bins are there
    again = BinnedEsf.from_dict(esf.to_dict())
    for error in (0.0, 1e-3):
        moved = again.replaced(error, 1e-4)
        assert np.all(np.isfinite(moved.x)) and np.all(np.isfinite(moved.value))
    np.testing.assert_allclose(again.replaced(0.0, 0.0).value, esf.value, atol=1e-4)


def _brightened(frame: np.ndarray, image: LensGrid, where: np.ndarray, clip: float) -> np.ndarray:
    """``frame`` 1.3x brighter in the micro-images ``where`` (by centre), clipped at ``clip``."""
    yy, xx = np.mgrid[0 : frame.shape[0], 0 : frame.shape[1]].astype(np.float64)
    cx, _ = image.centre(*image.nearest(xx, yy))
    bright = where(cx)
    return np.where(bright, np.minimum(frame * 1.3, clip), frame)


def test_clipped_half_edges_are_left_out_whole() -> None:
    frame, lens, image, coef = _frame()
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    whole = half_edge_profiles(frame, lattice, lens, image, _window())
    # a clip no sample reaches changes nothing
    high = dataclasses.replace(_window(), clip_count=float(frame.max()) + 1.0)
    same = half_edge_profiles(frame, lattice, lens, image, high)
    assert same.clipped_half_edges == 0
    np.testing.assert_array_equal(same.profiles.y, whole.profiles.y)
    # lone pixels stuck at full scale are defects, not a clip: nothing is left out
    stuck = frame.copy()
    stuck[::7, ::11] = 1000.0
    window = dataclasses.replace(_window(), clip_count=1000.0)
    defective = half_edge_profiles(stuck, lattice, lens, image, window)
    assert defective.clipped_half_edges == 0
    assert defective.profiles.count == whole.profiles.count
    # the micro-images right of x = 400 overexposed: their light squares clip at 1000
    clip = 1000.0
    bright = _brightened(frame, image, lambda cx: cx > 400.0, clip)
    window = dataclasses.replace(_window(), clip_count=clip)
    placed = half_edge_profiles(bright, lattice, lens, image, window)
    kept = placed.profiles
    assert kept.y.max() < clip
    lost = (int(whole.profiles.block.max()) + 1) - (int(kept.block.max()) + 1)
    assert placed.clipped_half_edges == lost > 10
    # what is left are the other micro-images' profiles, as they were
    original = {row.tobytes() for row in whole.profiles.y}
    assert all(row.tobytes() in original for row in kept.y)
    assert 0.3 * whole.profiles.count < kept.count < 0.8 * whole.profiles.count
    esf = frame_esf(kept, start_width_px=SIGMA)
    assert esf is not None
    inside = np.abs(esf.x) < 4.0
    np.testing.assert_allclose(esf.value[inside], ndtr(esf.x[inside] / SIGMA), atol=0.006)


def test_when_every_edge_clips_no_edge_free_micro_image_stands_in() -> None:
    """Every lit micro-image clipped; those left of x = 250 show no board (a flat dark level,
    as outside the window a renderer drew): none of their profiles is kept."""
    frame, lens, image, coef = _frame()
    yy, xx = np.mgrid[0 : frame.shape[0], 0 : frame.shape[1]].astype(np.float64)
    cx, _ = image.centre(*image.nearest(xx, yy))
    frame = np.where(cx < 250.0, DARK + np.random.default_rng(5).normal(0, 2, frame.shape), frame)
    clip = 1000.0
    bright = _brightened(frame, image, lambda cx: cx >= 250.0, clip)
    lattice = CornerLattice(coef=coef, covariance=np.zeros((3, 3)))
    window = dataclasses.replace(_window(), clip_count=clip)
    placed = half_edge_profiles(bright, lattice, lens, image, window)
    assert placed.clipped_half_edges > 20
    assert placed.profiles.count == 0
    # without the clip the edge-free micro-images would be cut like any other
    unclipped = half_edge_profiles(frame, lattice, lens, image, _window())
    assert unclipped.profiles.count > 0
