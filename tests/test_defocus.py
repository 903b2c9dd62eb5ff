"""The whole-sweep defocus model against edge-spread functions built from the physics.

The synthetic functions here are made by brute-force numerical convolution
(independent of :mod:`calibration.defocus`, which uses closed-form integrals):
the unit step, the pixel response (area integration, or 2 point samples as a
ray tracer takes them), the microlens aperture scaled to the defocus diameter
``(D/δ)·|Q - Q0|`` (a square aperture projects to a box, a round one to a
half-ellipse) and a static blur (Gaussian, or a heavy-tailed mixture standing
in for diffraction). The fit must find ``Q0`` whatever these shapes are, and
its uncertainty must cover the error.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from edge_shapes import fresnel_edge, sinc2_cdf
from scipy.special import ndtr

from calibration.defocus import (
    DefocusNotDetermined,
    EdgeObservation,
    blur_model_warning,
    fit_defocus,
)
from calibration.defocus_corners import sweep_corners
from calibration.edge_spread import BinnedEsf, EdgeProfiles, frame_esf
from calibration.result_notes import aperture_scale_warning
from calibration.white_rim import WhiteRim

LENS_PITCH_PX = 100.0
Q0 = 0.2
Q_SWEEP = np.linspace(0.1907, 0.2155, 50)  # the paper's optics over 100 mm of rail


def _esf(
    x: np.ndarray,
    diameter_px: float,
    *,
    aperture: str = "square",
    static: str = "gauss",
    sigma_px: float = 0.4,
    pixel: str = "area",
) -> np.ndarray:
    """Step ⊗ pixel ⊗ aperture(diameter) ⊗ static blur, at positions ``x`` (px)."""
    if pixel == "area":
        t = (np.arange(12) + 0.5) / 12 - 0.5
    else:  # two point samples per pixel along the profile
        t = np.array([-0.25, 0.25])
    if diameter_px > 0:
        k = (np.arange(48) + 0.5) / 48 * diameter_px - diameter_px / 2
        across = 1 - (2 * k / diameter_px) ** 2
        # a square's line spread is flat, a round one's a half ellipse; a round lens whose
        # transmission falls towards its rim (apodized) spreads even more in the centre
        wk = {"square": np.ones_like(k), "round": np.sqrt(across), "apodized": across}[aperture]
    else:
        k, wk = np.zeros(1), np.ones(1)
    wk = wk / wk.sum()
    shift = (t[:, None] + k[None, :]).ravel()
    weight = np.repeat(wk[None, :] / t.size, t.size, axis=0).ravel()
    z = x[:, None] - shift[None, :]
    if static == "gauss":
        cdf = ndtr(z / sigma_px) if sigma_px > 0 else (z > 0).astype(float)
    elif static == "diffraction":  # a square aperture's Fraunhofer pattern, first zero at sigma_px
        cdf = sinc2_cdf(z / sigma_px)
    else:  # heavy tails: a narrow core and a wide halo, like an Airy pattern's rings
        cdf = 0.8 * ndtr(z / 0.3) + 0.2 * ndtr(z / 1.5)
    return cdf @ weight


def _sweep(seed: int, *, noise: float = 0.003, q0: float = Q0, qs=Q_SWEEP, scale=1.0, **shape):
    rng = np.random.default_rng(seed)
    obs = []
    centres = np.arange(-5.95, 6.0, 0.1)
    for k, q in enumerate(qs):
        # what the pipeline bins: samples at random sub-pixel phases, averaged per 0.1 px bin
        samples = (centres[:, None] + rng.uniform(-0.05, 0.05, (centres.size, 40))).ravel()
        fine = np.arange(-6.1, 6.1, 0.005)
        curve = _esf(fine, scale * LENS_PITCH_PX * abs(q - q0), **shape)
        value = np.interp(samples, fine, curve).reshape(centres.size, -1).mean(axis=1)
        value = value + rng.normal(0.0, noise, centres.size)
        x = centres
        esf = BinnedEsf(x, value, np.full(x.size, noise), np.full(x.size, 40), 200)
        obs.append(EdgeObservation(k, "standard", float(q), esf))
    return obs


@pytest.mark.parametrize(
    "shape",
    [
        {"aperture": "square", "static": "gauss", "sigma_px": 0.4},
        {"aperture": "round", "static": "gauss", "sigma_px": 0.7},
        {"aperture": "square", "static": "gauss", "sigma_px": 0.0, "pixel": "points"},
        {"aperture": "round", "static": "halo"},
    ],
    ids=["square-gauss", "round-gauss", "square-point-samples", "round-heavy-tails"],
)
def test_q0_is_found_whatever_the_aperture_and_static_blur(shape: dict) -> None:
    fit = fit_defocus(_sweep(1, **shape), lens_pitch_px=LENS_PITCH_PX)
    assert abs(fit.Q0 - Q0) <= 3 * fit.Q0_se
    # informative: the focus plane to half a millimetre (dQ/du ≈ 2.3e-4 per mm)
    assert fit.Q0_se < 1.2e-4
    # the aperture's RMS width is that of a box of the full diameter (round: √12/4)
    expected = 1.0 if shape["aperture"] == "square" else np.sqrt(12) / 4
    assert fit.kappa == pytest.approx(expected, rel=0.08)
    assert aperture_scale_warning(fit.kappa) is None  # a plausible lens is not flagged


def test_an_aperture_smaller_than_the_pitch_does_not_bias_the_focus() -> None:
    fit = fit_defocus(_sweep(2, scale=0.8), lens_pitch_px=LENS_PITCH_PX)
    assert fit.kappa == pytest.approx(0.8, rel=0.08)
    assert abs(fit.Q0 - Q0) <= 3 * fit.Q0_se


def test_a_small_fill_factor_is_found_and_reported() -> None:
    fit = fit_defocus(_sweep(3, scale=0.6), lens_pitch_px=LENS_PITCH_PX)
    assert fit.kappa == pytest.approx(0.6, rel=0.08)
    assert abs(fit.Q0 - Q0) <= 3 * fit.Q0_se
    note = aperture_scale_warning(fit.kappa)
    assert note is not None and "fill factor" in note


def test_focus_plane_eight_millimetres_from_the_end_of_the_sweep() -> None:
    qs = np.linspace(Q0 - 0.0019, Q0 + 0.0210, 50)  # starts ~8 mm beyond the focus plane
    fit = fit_defocus(_sweep(3, qs=qs), lens_pitch_px=LENS_PITCH_PX)
    assert abs(fit.Q0 - Q0) <= 3 * fit.Q0_se
    assert fit.Q0_se < 1.5e-4  # 0.65 mm: one arm of the V is only 8 mm long


def test_uncertainty_covers_the_error_over_seeds() -> None:
    """20 noisy sweeps: the truth within 1σ about 68 % of the time, within 3σ nearly always."""
    z = []
    for seed in range(20):
        fit = fit_defocus(
            _sweep(100 + seed, noise=0.006, qs=Q_SWEEP[::2]), lens_pitch_px=LENS_PITCH_PX
        )
        z.append((fit.Q0 - Q0) / fit.Q0_se)
    z = np.abs(np.array(z))
    # bounds twice as loose as the claim (68 % within 1σ, ~100 % within 3σ)
    assert 0.36 <= np.mean(z <= 1.0) <= 1.0
    assert np.mean(z <= 3.0) >= 0.9


def test_a_sweep_that_never_defocuses_is_refused() -> None:
    qs = np.linspace(Q0 - 0.002, Q0 + 0.002, 30)  # the blur never exceeds 0.2 px
    with pytest.raises(DefocusNotDetermined, match="cannot be located"):
        fit_defocus(_sweep(4, qs=qs), lens_pitch_px=LENS_PITCH_PX)


def test_too_few_frames_are_refused() -> None:
    with pytest.raises(DefocusNotDetermined, match="only 3 frames"):
        fit_defocus(_sweep(5)[:3], lens_pitch_px=LENS_PITCH_PX)


def _exact_sweep(qs: np.ndarray, *, pitch_px: float, q0: float, **shape) -> list:
    """Noise-free binned functions: each 0.1 px bin the exact average over its interval
    (20 sub-samples), as the model describes a bin whose samples cover it evenly."""
    centres = np.arange(-5.95, 6.0, 0.1)
    sub = (np.arange(20) + 0.5) / 20 * 0.1 - 0.05
    points = (centres[:, None] + sub[None, :]).ravel()
    obs = []
    for k, q in enumerate(qs):
        value = _esf(points, pitch_px * abs(q - q0), **shape).reshape(centres.size, -1).mean(1)
        esf = BinnedEsf(centres, value, np.full(centres.size, 1e-4), np.full(centres.size, 40), 200)
        obs.append(EdgeObservation(k, "standard", float(q), esf))
    return obs


@pytest.mark.parametrize(
    "shape",
    [
        {"aperture": "square", "static": "gauss", "sigma_px": 0.4},
        {"aperture": "square", "static": "gauss", "sigma_px": 0.0, "pixel": "points"},
        {"aperture": "round", "static": "gauss", "sigma_px": 0.4},
    ],
    ids=["square-area", "square-point-samples", "round-area"],
)
def test_exact_edge_spreads_give_q0_exactly(shape: dict) -> None:
    """Without noise the fit is exact: a bias of Q0 on rendered sweeps comes from the edge
    spreads a frame yields, not from the fit (an asymmetric sweep, 50 px lenses, Q0 = 0.3,
    where a 0.01 % error is 0.0015 px of defocus diameter)."""
    q0 = 0.3
    qs = q0 + np.linspace(-0.026, 0.044, 36)
    fit = fit_defocus(_exact_sweep(qs, pitch_px=50.0, q0=q0, **shape), lens_pitch_px=50.0)
    assert fit.Q0 == pytest.approx(q0, rel=2e-5)
    expected = 1.0 if shape["aperture"] == "square" else np.sqrt(12) / 4
    assert fit.kappa == pytest.approx(expected, rel=2e-3)
    # edges formed the convolution's way: the wave-optical kernel is not even tried, so no
    # disagreement between blur models enters the uncertainty
    assert np.isnan(fit.Q0_other_kernel) and fit.Q0_se_kernel == 0.0
    assert blur_model_warning(fit) is None


def test_a_diffraction_limited_static_blur_with_long_tails_gives_q0() -> None:
    """A microlens at f/12.5 in green light is diffraction-limited: its square aperture's
    pattern has its first zero at λN = 2.75 px (2.5 µm pixels) and 1/x² tails, wider than
    the defocus over most of the sweep. The static kernel must reach past the pattern's
    second lobe: with 3 px of support the fit put Q0 12 % off (κ 0.5) on a Monte-Carlo
    sweep with this diffraction; here the exact functions of that sweep (80 px lenses,
    Q0 = 0.25, ending 8.5 mm past focus) must give Q0 to 0.01 % (they give 0.002 %; 0.67 %
    low with 3 px of support)."""
    q0 = 0.25
    qs = q0 + np.linspace(-0.0203, 0.0034, 30)
    shape = {"aperture": "square", "static": "diffraction", "sigma_px": 2.75}
    fit = fit_defocus(_exact_sweep(qs, pitch_px=80.0, q0=q0, **shape), lens_pitch_px=80.0)
    assert fit.Q0 == pytest.approx(q0, rel=1e-4)
    assert fit.kappa == pytest.approx(1.0, abs=0.01)
    # the pattern convolved with the geometric blur (rays deflected by it) is geometric
    # optics with a static pattern: the wave-optical kernel is not taken
    assert fit.diffraction_px == 0.0


def test_one_corner_is_fitted_throughout_the_sweep_when_the_other_is_seen_in_part() -> None:
    """The reference corner's half-edges are offset by the board's gap, so wherever a blur
    reaches along an edge past the corner its function is not the standard corner's (here:
    a static blur 0.1 px wider). When only the far part of the sweep shows it (its
    micro-images enter the windows there), merging the two corners' functions per frame
    changed their shape along the sweep as a defocus does, and put Q0 1.1 % off (15σ);
    with the standard corner throughout, these exact functions give Q0 to 1e-5."""
    q0, pitch = 0.3, 50.0
    qs = q0 + np.linspace(-0.02, 0.03, 26)
    standard = _exact_sweep(qs, pitch_px=pitch, q0=q0, static="gauss", sigma_px=0.5)
    wider = _exact_sweep(qs, pitch_px=pitch, q0=q0, static="gauss", sigma_px=0.6)
    reference = [replace(o, corner="reference") for o in wider if o.Q < q0 - 0.005]
    fit = fit_defocus(standard + reference, lens_pitch_px=pitch)
    assert fit.Q0 == pytest.approx(q0, rel=1e-5)
    assert fit.frames == len(qs)
    assert fit.corners == "standard"


def test_corners_seen_in_every_frame_are_merged_each_centred_on_its_edge() -> None:
    """Both corners in every frame: their functions are merged (the same mixture along the
    sweep, which the static kernel takes up), each centred on its own edge first: the
    reference corner's lattice puts its edge up to 0.3 px off, differently in each frame
    (uncentred, the merged functions widen by a different amount in each frame: Q0 off by
    0.1 % here), and its static blur is 0.1 px wider."""
    q0, pitch = 0.3, 50.0
    qs = q0 + np.linspace(-0.02, 0.03, 26)
    standard = _exact_sweep(qs, pitch_px=pitch, q0=q0, static="gauss", sigma_px=0.5)
    wider = _exact_sweep(qs, pitch_px=pitch, q0=q0, static="gauss", sigma_px=0.6)
    offsets = np.random.default_rng(3).uniform(-0.3, 0.3, len(qs))
    reference = [
        replace(o, corner="reference", esf=o.esf.shifted(float(dx)))
        for o, dx in zip(wider, offsets, strict=True)
    ]
    merged = sweep_corners(standard + reference)
    assert [o.corner for o in merged] == ["both"] * len(qs)
    assert [o.esf.profiles for o in merged] == [400] * len(qs)
    fit = fit_defocus(standard + reference, lens_pitch_px=pitch)
    assert fit.Q0 == pytest.approx(q0, rel=1e-4)
    assert fit.frames == len(qs)
    assert fit.corners == "both"


def test_the_corner_seen_in_most_frames_is_the_one_fitted() -> None:
    def obs(frame: int, corner: str) -> EdgeObservation:
        return EdgeObservation(frame, corner, 0.3, _binned(lambda x: ndtr(x)))

    standard = [obs(k, "standard") for k in (0, 1, 2)]
    reference = [obs(k, "reference") for k in (1, 2, 3, 4)]
    assert sweep_corners(standard + reference) == reference
    # on a tie the standard corner (straight edges through the corner)
    assert sweep_corners(standard + reference[:3]) == standard
    assert sweep_corners(standard[:1]) == standard[:1]
    assert sweep_corners([]) == []


def _binned(curve) -> BinnedEsf:
    """A noise-free 0.1 px binned function: each bin the exact average over its interval."""
    centres = np.arange(-5.95, 6.0, 0.1)
    sub = (np.arange(20) + 0.5) / 20 * 0.1 - 0.05
    value = curve((centres[:, None] + sub[None, :]).ravel()).reshape(centres.size, -1).mean(1)
    return BinnedEsf(centres, value, np.full(centres.size, 1e-4), np.full(centres.size, 40), 200)


@pytest.mark.parametrize(
    ("s_px", "arm"), [(2.64, "near"), (1.0, "near"), (2.64, "symmetric")], ids=str
)
def test_wave_optical_edges_give_q0_and_the_diffraction_scale(s_px: float, arm: str) -> None:
    """Light, not rays: the paper's camera (100 px lenses, f/12, 2.5 µm pixels: the pattern's
    first zero λN = 2.64 px in green light; 1.0 px as at f/4.5) stays within its microlenses'
    diffraction-limited depth of focus over the whole sweep, where a defocus moves light from
    the pattern's core into its rings instead of widening it. Geometric optics convolved with
    the pattern fitted these exact Fresnel edges with κ 0.43-0.67 and put Q0 +0.36 % (2.64 px)
    and +0.72 % (1.0 px) off on a sweep whose focus plane is 8 mm from its near end (−0.015 %
    on a symmetric one). The wave-optical kernel recovers Q0, a full aperture and the
    pattern's scale."""
    q0 = 0.2
    qs = q0 + (
        np.linspace(-0.0020, 0.0230, 40) if arm == "near" else np.linspace(-0.0093, 0.0155, 40)
    )
    obs = [
        EdgeObservation(k, "standard", float(q), _binned(fresnel_edge(100.0 * (q - q0), s_px)))
        for k, q in enumerate(qs)
    ]
    fit = fit_defocus(obs, lens_pitch_px=100.0)
    assert fit.Q0 == pytest.approx(q0, rel=1e-4)
    assert fit.diffraction_px == pytest.approx(s_px, rel=0.03)
    assert fit.kappa == pytest.approx(1.0, abs=0.03)
    assert aperture_scale_warning(fit.kappa) is None
    # geometric optics was fitted too and put Q0 elsewhere (by the amounts above): that
    # disagreement is part of the uncertainty, whichever model is taken
    assert abs(fit.Q0_other_kernel - q0) > 1e-4 * q0
    assert fit.Q0_se_kernel == pytest.approx(abs(fit.Q0 - fit.Q0_other_kernel), rel=1e-12)
    assert fit.Q0_se >= fit.Q0_se_kernel
    # where the two models disagree by more than the data's uncertainty (a sweep starting
    # near its focus plane), the result says so; on the symmetric sweep they agree
    warning = blur_model_warning(fit)
    if arm == "near":
        assert "wave-optical blur model (taken)" in (warning or "")
    else:
        assert warning is None


def test_wave_optical_edges_sampled_at_a_few_sub_pixel_phases_give_q0() -> None:
    """Edges along the pixel rows: a frame's profiles then share a few sub-pixel phases, so
    each bin holds samples at one position (a point value, not a bin average). A
    diffraction-limited microlens (f/15.6, 550 nm: pattern scale 3.43 px on 2.5 µm pixels;
    50 px lenses, geometric defocus at most 1.5 px over the sweep) has an effective wave
    kernel that is almost a point near focus, so the static kernel alone must follow the
    function between its nodes. As point masses 0.05 px apart it made every function a
    staircase, and frames whose phases fell on its steps could not be fitted at all (chi-square
    760 at the truth where the noise gives 0; geometric optics with κ 0.42 fitted better,
    with a wrong model). The static kernel is piecewise linear; these exact functions give
    Q0, the pattern's scale and a full aperture."""
    q0, s_px, pitch = 0.3, 3.432, 50.0
    qs = q0 + np.linspace(-0.0184, 0.0297, 31)
    obs = []
    for k, q in enumerate(qs):
        phases = (np.array([0.13, 0.37, 0.52, 0.71, 0.94]) + 0.17 * k) % 1.0
        x = np.sort((np.arange(-6, 7)[:, None] + phases[None, :]).ravel())
        value = fresnel_edge(pitch * (q - q0), s_px)(x)
        n = x.size
        esf = BinnedEsf(x, value, np.full(n, 1e-4), np.full(n, 40), 200, np.zeros(n))
        obs.append(EdgeObservation(k, "standard", float(q), esf))
    fit = fit_defocus(obs, lens_pitch_px=pitch)
    assert fit.Q0 == pytest.approx(q0, rel=1e-4)
    assert fit.diffraction_px == pytest.approx(s_px, rel=0.03)
    assert fit.kappa == pytest.approx(1.0, abs=0.03)


def test_wave_optical_uncertainty_covers_the_error_over_seeds() -> None:
    """Noisy Fresnel edges (0.003 of the contrast per 0.1 px bin, samples at random
    sub-pixel phases) of a camera at f/4.5 (``s`` = 1 px) whose focus plane is 8 mm from the
    near end of a 25-frame sweep: the truth within 3σ of every seed's ``Q0`` (with geometric
    optics alone it was +0.72 % off on the exact edges, about 6σ of these)."""
    q0, s_px = 0.2, 1.0
    qs = q0 + np.linspace(-0.0020, 0.0230, 25)
    centres = np.arange(-5.95, 6.0, 0.1)
    curves = [fresnel_edge(100.0 * (q - q0), s_px) for q in qs]
    z = []
    for seed in range(8):
        rng = np.random.default_rng(300 + seed)
        obs = []
        for k, (q, curve) in enumerate(zip(qs, curves, strict=True)):
            x = (centres[:, None] + rng.uniform(-0.05, 0.05, (centres.size, 40))).ravel()
            value = curve(x).reshape(centres.size, -1).mean(1)
            value = value + rng.normal(0.0, 0.003, centres.size)
            esf = BinnedEsf(
                centres, value, np.full(centres.size, 0.003), np.full(centres.size, 40), 200
            )
            obs.append(EdgeObservation(k, "standard", float(q), esf))
        fit = fit_defocus(obs, lens_pitch_px=100.0)
        assert fit.diffraction_px > 0.5
        z.append((fit.Q0 - q0) / fit.Q0_se)
    z = np.abs(np.array(z))
    assert np.all(z <= 3.0), z
    assert np.mean(z <= 1.0) >= 0.36, z


def _noisy_fresnel_sweep(seed: int, *, q0: float, s_px: float, pitch: float, qs: np.ndarray):
    """Fresnel edges at random sub-pixel phases, 0.001 of the contrast of noise per bin."""
    rng = np.random.default_rng(seed)
    centres = np.arange(-5.95, 6.0, 0.1)
    obs = []
    for k, q in enumerate(qs):
        x = (centres[:, None] + rng.uniform(-0.05, 0.05, (centres.size, 40))).ravel()
        curve = fresnel_edge(pitch * (q - q0), s_px)
        value = curve(x).reshape(centres.size, -1).mean(1) + rng.normal(0.0, 0.001, centres.size)
        esf = BinnedEsf(
            centres, value, np.full(centres.size, 0.001), np.full(centres.size, 40), 200
        )
        obs.append(EdgeObservation(k, "standard", float(q), esf))
    return obs


def _rim(pitch: float, defocus: float, kappa: float = 1.0, static_px: float = 0.3) -> WhiteRim:
    """The rims a white image shows: the aperture (RMS scale ``kappa``) at ``defocus``
    (``|Q0 - b/L|``) and a static blur."""
    variance = (kappa * pitch * defocus) ** 2 / 12.0 + static_px**2
    return WhiteRim(variance_px2=variance, radius_px=0.5 * pitch, micro_images=100)


def test_white_rims_rule_out_a_geometric_kernel_that_imitates_diffraction() -> None:
    """wavesim's coverage camera (50 px square lenses at f/15.6 in green light: pattern
    scale 3.43 px; the sweep defocuses at most 1.5 px): within the microlenses' depth of
    focus geometric optics fits these edges with a third of the aperture (κ 0.35) and the
    chi-square keeps it, as on 10 of wavesim's 20 coverage sweeps, whose focus planes it put
    up to 4 mm off. The white image's rims, 12 px out of focus at ``b/L`` = 0.0562, show the
    whole aperture: geometric optics is ruled out, the wave-optical kernel is taken (the
    pattern's scale, a full aperture) and its ``Q0`` is within 2σ, without the two
    kernels' disagreement in the uncertainty."""
    q0, s_px, pitch, beta = 0.3, 3.432, 50.0, 0.0562
    obs = _noisy_fresnel_sweep(301, q0=q0, s_px=s_px, pitch=pitch,
                               qs=q0 + np.linspace(-0.0184, 0.0297, 31))  # fmt: skip
    plain = fit_defocus(obs, lens_pitch_px=pitch)
    assert plain.diffraction_px == 0.0 and plain.kappa < 0.5
    assert not plain.geometric_excluded and np.isnan(plain.rim_kappa)
    fit = fit_defocus(obs, lens_pitch_px=pitch, rim=_rim(pitch, q0 - beta), rim_q=beta)
    assert fit.geometric_excluded
    assert fit.rim_kappa == pytest.approx(0.85, abs=0.05)  # the geometric static blur off
    assert fit.diffraction_px == pytest.approx(s_px, rel=0.1)
    assert fit.kappa > 0.8
    assert fit.Q0_se_kernel == 0.0 and fit.Q0_other_kernel == pytest.approx(plain.Q0)
    assert abs(fit.Q0 - q0) <= 2.0 * fit.Q0_se


def test_rims_of_the_same_aperture_leave_the_geometric_fit_alone() -> None:
    """Edges formed the convolution's way (square aperture, Gaussian static blur) with the
    rims of that aperture: the rims show κ near the fit's and change nothing; rims 14 %
    wider (as ray-traced diffraction widens them) neither; rims a quarter of the aperture
    would have ruled nothing out either (κ 4 times the rims'), and rims barely out of focus
    (``b/L`` near ``Q0``) are not read at all."""
    obs = _sweep(5, aperture="square", static="gauss", sigma_px=0.4)
    plain = fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX)
    for rim, rim_q in (
        (_rim(LENS_PITCH_PX, Q0 - 0.05), 0.05),
        (_rim(LENS_PITCH_PX, Q0 - 0.05, kappa=1.14), 0.05),
        (_rim(LENS_PITCH_PX, Q0 - 0.05, kappa=0.25), 0.05),
        (_rim(LENS_PITCH_PX, 0.02, kappa=4.0), Q0 - 0.02),
    ):
        fit = fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX, rim=rim, rim_q=rim_q)
        assert not fit.geometric_excluded
        assert fit.Q0 == plain.Q0 and fit.Q0_se == plain.Q0_se
    assert fit_defocus(
        obs, lens_pitch_px=LENS_PITCH_PX, rim=_rim(LENS_PITCH_PX, Q0 - 0.05), rim_q=0.05
    ).rim_kappa == pytest.approx(plain.kappa, rel=0.1)
    assert np.isnan(
        fit_defocus(
            obs, lens_pitch_px=LENS_PITCH_PX, rim=_rim(LENS_PITCH_PX, 0.02), rim_q=Q0 - 0.02
        ).rim_kappa
    )


def test_diffraction_limited_profiles_through_the_levels_give_q0() -> None:
    """The whole path from profiles: a diffraction-limited edge (square microlens at
    f/15.6 in green light, first zero 3.43 px, 50 px lenses, 2x2 point samples) cut into
    ±6 px profiles at random sub-pixel phases, levels read off tails 4-6 px out (where
    the pattern is still 5-9 % short of them), pooled, then the defocus fit. Flat-fielded
    profiles, levels read at fixed points of tails whose shape is fitted: ``Q0`` within
    0.1 % (−0.04 %). With the drift fitted, as before the white image flat-fielded the
    profiles, it was 0.32 % low; with flat tails and no drift 0.11 % low (each profile's
    levels then depend on its sampling phase)."""
    q0 = 0.3
    qs = q0 + np.linspace(0.062, -0.029, 26)
    rng = np.random.default_rng(11)
    fine = np.arange(-7.0, 7.01, 0.01)
    obs = []
    for k, q in enumerate(qs):
        curve = _esf(fine, 50.0 * abs(q - q0), static="diffraction", sigma_px=3.43, pixel="points")
        x = np.arange(-6, 7)[None, :] + rng.uniform(-0.5, 0.5, (300, 1))
        profiles = EdgeProfiles(x, 40.0 + 600.0 * np.interp(x, fine, curve), np.arange(300) // 30)
        esf = frame_esf(profiles, start_width_px=1.2, max_flat_px=4.0, drift=False)
        assert esf is not None
        obs.append(EdgeObservation(k, "standard", float(q), esf))
    fit = fit_defocus(obs, lens_pitch_px=50.0)
    assert fit.Q0 == pytest.approx(q0, rel=1e-3)
    assert fit.kappa == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("seed", [0, 1])
def test_round_lenses_keep_a_finite_uncertainty_wherever_the_shape_ends(seed: int) -> None:
    """Round lenses put the aperture's shape ``α`` near its bound 0, in a valley so flat
    that the optimizer's last steps (BLAS's summation order, rounding) leave it anywhere
    from the bound to a few tenths: ``Q0``'s uncertainty must stay finite and cover the
    error either way. (At the bound it was infinite once, on a ray-traced round-lens sweep
    with a wrong data sheet, whose focal length then fell back to the data sheet and whose
    focus plane came out 46 mm off.)"""
    obs = _sweep(seed, aperture="round", static="gauss", sigma_px=0.7)
    fit = fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX, start=(Q0, 0.866, 0.0, 0.0))
    assert fit.kappa == pytest.approx(np.sqrt(12) / 4, rel=0.05)
    assert np.isfinite(fit.Q0_se_curvature) and 0 < fit.Q0_se_curvature < 2e-4
    assert abs(fit.Q0 - Q0) <= 3 * fit.Q0_se


@pytest.mark.parametrize("pixel", ["area", "points"])
def test_q0_does_not_move_with_rounding_noise_in_q(pixel: str) -> None:
    """Each frame's ``Q`` changed by 1e-10 of itself (rounding in an upstream step) moves
    ``Q0`` by a negligible fraction of its statistical uncertainty: the fit's design carries
    the ramp that ∫C follows exactly and interpolates only the bounded rest in float32
    (interpolating ∫C itself, up to 12 px, lost ~1e-6 to cancellation in the intervals'
    differences and moved ``Q0`` by up to 0.13σ here)."""
    shape = {"aperture": "square", "static": "gauss", "sigma_px": 0.4 if pixel == "area" else 0.0}
    obs = _sweep(1, **shape, **({"pixel": "points"} if pixel == "points" else {}))
    rng = np.random.default_rng(0)
    fits = [fit_defocus(obs, lens_pitch_px=LENS_PITCH_PX)]
    for _ in range(4):
        nudged = [replace(o, Q=o.Q * (1.0 + rng.normal(0.0, 1e-10))) for o in obs]
        fits.append(fit_defocus(nudged, lens_pitch_px=LENS_PITCH_PX))
    spread = np.ptp([f.Q0 for f in fits])
    assert spread < 0.05 * fits[0].Q0_se_curvature, spread / fits[0].Q0_se_curvature
