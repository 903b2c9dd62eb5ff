"""The blur models on a ray-traced sweep whose diffraction is a fixed pattern per ray.

``tests/fixtures/mcsim_between_airy_edges.npz`` holds the defocus fit's input from one sweep
of the Monte-Carlo ray tracer (``bench/mcsim``, written from OPTICS.md without the core;
the accuracy sweep ``between-airy``, seed 24): 59 frames of 80 px square microlenses at
f/12.5, each ray deflected by the square aperture's Fraunhofer pattern at 550 nm (first
zero 2.75 px), 30 rays per point, 2×2 points per pixel; both corners' edge-spread
functions merged per frame, as the pipeline made them, and each frame's ``Q`` from the
calibrated camera. That is exactly geometric optics with a static kernel. The sweep ends
9 frames (0.5 mm on the board's image side) past the focus plane and its edges barely widen (windowed RMS width 1.14 → 1.23
px), so the focus plane comes from the curvature of one arm.

The truth on the sweep's own ``Q`` scale: the renderer's ``Q`` at its focus plane, 0.25,
mapped by the straight line through the frames' (true ``Q``, calibrated ``Q``) pairs
(RMS 1.5e-7; the calibrated scale reads 0.10 % compressed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration.defocus import EdgeObservation, blur_model_warning, fit_defocus
from calibration.edge_spread import BinnedEsf

FIXTURE = Path(__file__).parent / "fixtures" / "mcsim_between_airy_edges.npz"
Q0_TRUE = 0.249906
LENS_PITCH_PX = 80.0


def _observations() -> list[EdgeObservation]:
    data = np.load(FIXTURE)
    ends = np.cumsum(data["sizes"])
    starts = ends - data["sizes"]
    obs = []
    for k, (a, b) in enumerate(zip(starts, ends, strict=True)):
        esf = BinnedEsf(
            data["x"][a:b],
            data["value"][a:b],
            data["se"][a:b],
            data["count"][a:b],
            int(data["profiles"][k]),
            data["x_sd"][a:b],
            jitter_px=float(data["jitter_px"][k]),
        )
        obs.append(EdgeObservation(int(data["frame"][k]), "both", float(data["Q"][k]), esf))
    return obs


@pytest.fixture(scope="module")
def fit():
    return fit_defocus(_observations(), lens_pitch_px=LENS_PITCH_PX)


def test_a_blend_below_the_smallest_pattern_does_not_replace_geometric_optics(fit) -> None:
    """The wave-optical fit lands at a diffraction scale below ``WAVE_MIN_PX`` (0.5 px; a blend of the
    geometric kernel with the narrowest pattern), 45 of chi-square better: not a pattern
    the edges resolve. Taken, it put ``Q0`` 0.0010 high (the focus plane 2.0 mm off, a
    0.36 %); geometric optics, exact here, is taken instead."""
    assert fit.diffraction_px == 0.0
    # the blend was fitted, and put the focus plane elsewhere
    assert np.isfinite(fit.Q0_other_kernel)
    assert fit.Q0_other_kernel - Q0_TRUE > 6e-4
    assert fit.Q0 == pytest.approx(Q0_TRUE, abs=4e-4)


def test_the_models_disagreement_is_in_the_uncertainty_and_reported(fit) -> None:
    assert fit.Q0_se_kernel == pytest.approx(abs(fit.Q0 - fit.Q0_other_kernel), rel=1e-12)
    assert fit.Q0_se >= fit.Q0_se_kernel
    assert abs(fit.Q0 - Q0_TRUE) <= fit.Q0_se
    warning = blur_model_warning(fit) or ""
    assert "geometric blur model (taken)" in warning


def test_the_fixture_is_a_sweep_ending_just_past_its_focus_plane() -> None:
    """59 frames, both corners merged, 9 of them beyond the focus plane."""
    obs = _observations()
    q = np.array([o.Q for o in obs])
    assert len(obs) == 59
    assert {o.corner for o in obs} == {"both"}
    assert int(np.sum(q > Q0_TRUE)) == 9
