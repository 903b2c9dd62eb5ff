"""The white image's rims against the geometric fit's aperture (:mod:`calibration.defocus_kernels`).

The rims are the microlens aperture far from focus; a geometric fit near focus whose
aperture is clearly smaller than theirs, beyond its own uncertainty, imitates
diffraction and is ruled out. The Fresnel edges are exact wave optics
(``edge_shapes.fresnel_edge``, written apart from :mod:`calibration.wave_defocus`).
"""

from __future__ import annotations

import numpy as np
import pytest
from test_defocus import _noisy_fresnel_sweep, _rim

from calibration.defocus import fit_defocus
from calibration.defocus_kernels import (
    RIM_KAPPA_MIN_FRACTION,
    RIM_KAPPA_SIGMAS,
    rims_exclude_geometric,
)


def _geometric(kappa: float, kappa_se: float, robust_se: float = 0.0):
    """A geometric fit's ``(theta, cov, robust, chi2)`` with ``κ`` and its two errors."""
    theta = np.array([0.2, kappa, 1.0, 0.0])
    cov = np.diag([1e-8, kappa_se**2, 1e-4, 0.0])
    robust = np.diag([1e-8, robust_se**2, 1e-4, 0.0])
    return theta, cov, robust, 1.0


def test_an_aperture_far_below_the_rims_is_ruled_out_only_beyond_its_uncertainty() -> None:
    """κ 0.44 ± 0.017 against rims of 0.84 (noisy Fresnel edges of wavesim's camera) is
    ruled out; the same κ fixed to ± 0.1 (a sweep that hardly constrains it) is not, by
    either of its errors; neither is a κ 0.88 of the rims' (ray-traced diffraction widens
    rims by up to 14 %), nor anything without rims."""
    assert rims_exclude_geometric(_geometric(0.44, 0.017), 0.84)
    assert not rims_exclude_geometric(_geometric(0.44, 0.1), 0.84)
    assert not rims_exclude_geometric(_geometric(0.44, 0.017, robust_se=0.1), 0.84)
    assert not rims_exclude_geometric(_geometric(0.88, 0.0), 1.0)
    assert not rims_exclude_geometric(_geometric(0.44, 0.0), float("nan"))
    # the boundary: κ plus its sigmas exactly at the fraction of the rims' is kept
    edge = RIM_KAPPA_MIN_FRACTION * 0.84 - RIM_KAPPA_SIGMAS * 0.01
    assert not rims_exclude_geometric(_geometric(edge + 1e-9, 0.01), 0.84)
    assert rims_exclude_geometric(_geometric(edge - 1e-6, 0.01), 0.84)


def test_fresnel_edges_fitted_by_half_the_rims_aperture_take_the_wave_kernel() -> None:
    """wavesim's coverage camera (50 px square lenses at f/15.6 in green light), noisy
    Fresnel edges of seed 304: geometric optics fits κ 0.44, just over half of the rims'
    0.84, and put ``Q0`` 0.79 % off (1.4σ, the kernels' disagreement in σ) while the
    rims ruled out only below half their aperture (session 54). It is ruled out now; the
    wave kernel's ``Q0`` is within 0.4 % and 1.5σ."""
    q0, s_px, pitch, beta = 0.3, 3.432, 50.0, 0.0562
    obs = _noisy_fresnel_sweep(304, q0=q0, s_px=s_px, pitch=pitch,
                               qs=q0 + np.linspace(-0.0184, 0.0297, 31))  # fmt: skip
    fit = fit_defocus(obs, lens_pitch_px=pitch, rim=_rim(pitch, q0 - beta), rim_q=beta)
    assert fit.geometric_excluded
    assert fit.rim_kappa == pytest.approx(0.84, abs=0.05)
    assert fit.Q0_other_kernel == pytest.approx(q0 * 1.0079, rel=0.002)  # geometric's
    assert fit.diffraction_px == pytest.approx(s_px, rel=0.1)
    assert abs(fit.Q0 / q0 - 1.0) < 0.004
    assert abs(fit.Q0 - q0) <= 1.5 * fit.Q0_se
