"""Focus-plane models against constructed ground truth (no simulator involved).

The edge widths are made the way the corner detector measures them: an ideal
step blurred by the geometric defocus (a box as wide as OPTICS.md's blur
diameter ``D·b·|1/a_f − 1/a(u)|``) and a Gaussian PSF, integrated over the
pixel, sampled at several sub-pixel phases and fitted with the edge-spread
model of :mod:`calibration.edge_fit`.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.special import ndtr

from calibration.edge_fit import fit_edges
from calibration.focus import (
    FocusAtSweepEdge,
    corner_size_mm,
    fit_blur_model,
    paper_focus,
    width_squared_px2,
)
from calibration.optics import image_distance, paper_optics
from calibration.parameters import global_fit

PSF_SIGMA_PX = 0.4


def measured_edge_width_px(box_px: float, psf_sigma_px: float = PSF_SIGMA_PX) -> float:
    """Mean fitted edge spread of a box ⊗ Gaussian blurred step, over 8 sub-pixel phases."""
    fine = 200  # samples per pixel for the blur and the pixel integral
    x = np.arange(-12 * fine, 12 * fine) / fine  # px
    n_box = max(1, int(round(box_px * fine)))
    shifts = (np.arange(n_box) + 0.5) / n_box * box_px - box_px / 2 if box_px > 0 else [0.0]
    edge = np.mean([ndtr((x - s) / psf_sigma_px) for s in shifts], axis=0)
    cum = np.concatenate([[0.0], np.cumsum(edge) / fine])
    profiles = []
    for phase in np.arange(8) / 8:
        centres = np.arange(-7, 8) + phase  # pixel centres relative to the edge (px)
        lo = np.searchsorted(x, centres - 0.5)
        hi = np.searchsorted(x, centres + 0.5)
        profiles.append(100.0 + 1000.0 * (cum[hi] - cum[lo]))
    fits = fit_edges(np.array(profiles))
    assert fits.ok.all()
    return float(np.mean(fits.width))


def test_blur_model_finds_the_focus_plane_from_box_blur_widths() -> None:
    o = paper_optics()  # focus plane at u = 300 mm
    u = 250.0 + np.arange(100.0)  # the paper's sweep: more frames on the near side in s
    widths = np.array([measured_edge_width_px(float(o.blur_px(ui))) for ui in u])
    fit = fit_blur_model(u, widths, F=o.F, a_f=o.a_f)
    # widths do not add in quadrature exactly; a quadratic model alone is 0.1-0.2 mm off here
    assert fit.object_distance_mm == pytest.approx(o.u0, abs=0.03)
    assert fit.A_px2 == pytest.approx(PSF_SIGMA_PX**2, rel=0.05)
    assert_allclose(fit.width_model_px, widths, atol=2e-3)


def test_blur_model_recovers_its_own_parameters_between_rail_steps() -> None:
    F, a_f, u0 = 50.0, 12.0, 432.37
    v0 = float(image_distance(u0, F))
    u = 380.0 + 1.0 * np.arange(100)
    w = np.sqrt(width_squared_px2(image_distance(u, F), v0, a_f, 0.2, 30.0, 400.0))
    fit = fit_blur_model(u, w, F=F, a_f=a_f)
    assert fit.object_distance_mm == pytest.approx(u0, abs=1e-4)
    assert (fit.A_px2, fit.B_px2, fit.C_px2) == pytest.approx((0.2, 30.0, 400.0), rel=1e-3)


def test_blur_minimum_outside_the_sweep_says_extend_the_range() -> None:
    o = paper_optics()
    u = 310.0 + np.arange(40.0)  # starts behind the focus plane at 300 mm
    widths = np.array([measured_edge_width_px(float(o.blur_px(ui))) for ui in u])
    with pytest.raises(FocusAtSweepEdge, match="extend the range"):
        fit_blur_model(u, widths, F=o.F, a_f=o.a_f)


def test_paper_focus_refines_the_argmin_below_the_rail_step() -> None:
    u = 250.0 + np.arange(100.0)
    la = 0.02 + 1e-5 * (u - 287.4) ** 2
    la[40] = np.nan  # a frame without a reference corner is skipped
    found = paper_focus(u, la)
    assert found is not None
    assert found.best_index in (37, 38)
    assert found.object_distance_mm == pytest.approx(287.4, abs=1e-6)


def test_corner_size_eq7_eq8_by_hand() -> None:
    lp, la = corner_size_mm([0.8, 1.0, 1.0], [1.3, 1.0, 0.5], 0.1)
    assert_allclose(lp[0], 0.1 / 0.5)  # Lp = Cr / (Lr - Ls)
    assert_allclose(la[0], 0.1 / 0.5 * 0.8)  # La = Lp * Ls
    assert np.isnan(lp[1:]).all() and np.isnan(la[1:]).all()  # Lr <= Ls: undefined


def test_global_fit_recovers_b_and_L_from_the_disparity() -> None:
    o = paper_optics()
    u = 250.0 + np.arange(100.0)
    q = np.asarray(o.Q(u))
    rng = np.random.default_rng(3)
    q_se = np.full(u.shape, 2e-5)
    noisy = q + rng.normal(0.0, 2e-5, u.shape)
    fit = global_fit(u, noisy, q_se, F=o.F, f=o.f, D=o.D, delta=o.delta)
    est = fit.estimate
    assert est.b_mm == pytest.approx(o.b, abs=4 * est.b_se_mm)
    assert est.L_mm == pytest.approx(o.L, abs=4 * est.L_se_mm)
    assert est.a_mm == pytest.approx(o.a_f, rel=5e-4)
    assert est.focus_object_distance_mm == pytest.approx(o.u0, abs=4 * est.focus_se_mm)
