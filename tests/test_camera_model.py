"""The camera calibrated from the sweep: F, the rail zero, L, b and f against a known thin-lens camera.

The measurements are generated straight from OPTICS.md's thin-lens relations
(``M = v/u``, ``Q = b/(L - v)``, ``Q0 = b/a_f``) with noise of the size the
corner fits give, and the data-sheet values handed to the fit are off by
the amounts a lab sees (F and f by 2 %, the rail zero by 2 mm).
"""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera_model import ModelError, Priors, SweepMeasurements, fit_camera_model
from calibration.optics import focused_virtual_distance, image_distance, mla_distance_for_focus

F, f, b, U_RAIL0, DIRECTION = 35.0, 2.5, 3.0, 250.0, 1
L = mla_distance_for_focus(300.0, F, f, b)
A_F = focused_virtual_distance(f, b)


RAIL_MM = np.arange(100.0)


def _measurements(
    seed: int,
    *,
    magnification: bool = True,
    eta: float = 0.0,
    q_noise: float = 2e-5,
    white: bool = True,
) -> SweepMeasurements:
    """A sweep's measurements; ``white``: with the white image's ``(L+b)/L`` (read 3e-6)."""
    rng = np.random.default_rng(seed)
    rail = RAIL_MM
    u = U_RAIL0 + DIRECTION * rail
    v = np.asarray(image_distance(u, F))
    q0 = b / A_F
    q = b / (L - v)
    q_meas = q * (1 + eta * (q - q0)) * (1 + rng.normal(0, q_noise, q.size))
    inv_m = u / v * (1 + rng.normal(0, 1e-5, q.size))
    if not magnification:
        inv_m = np.full(q.size, np.nan)
    beta = b / L
    scale = 1 + beta * (1 + (beta - q0) * eta) + rng.normal(0, 3e-6) if white else np.nan
    return SweepMeasurements(
        rail_mm=rail,
        Q=q_meas,
        Q_se=np.full(q.size, q_noise) * q,
        inv_magnification=inv_m,
        inv_magnification_se=np.full(q.size, 1e-5) * u / v,
        Q0=q0 + rng.normal(0, 1e-5),
        Q0_se=1e-5,
        eta=eta,
        eta_se=0.1 * abs(eta),
        image_scale=scale,
        image_scale_se=3e-6,
    )


def _priors(dF: float = 0.0, df: float = 0.0, du: float = 0.0) -> Priors:
    return Priors(
        main_focal_mm=F + dF,
        main_focal_tolerance_mm=0.02 * F,
        mla_focal_mm=f + df,
        mla_focal_tolerance_mm=0.02 * f,
        rail_zero_object_distance_mm=U_RAIL0 + du,
        rail_zero_tolerance_mm=2.0,
        direction=DIRECTION,
    )


TRUTH = {
    "main_focal_mm": F,
    "mla_focal_mm": f,
    "rail_zero_object_distance_mm": U_RAIL0,
    "L_mm": L,
    "b_mm": b,
    "a_mm": A_F,
    "focus_object_distance_mm": 300.0,
    "focus_rail_mm": 50.0,
}


@pytest.mark.parametrize("off", [(0.0, 0.0, 0.0), (0.7, -0.05, 2.0), (-0.7, 0.05, -2.0)])
def test_the_sweep_replaces_wrong_data_sheet_values(off: tuple[float, float, float]) -> None:
    fit = fit_camera_model(_measurements(1), _priors(*off))
    assert fit.determined_by == {
        "main_focal_mm": "sweep",
        "mla_focal_mm": "sweep",
        "rail_zero_object_distance_mm": "sweep",
    }
    for key, true in TRUTH.items():
        err = fit.values[key] - true
        assert abs(err) <= 4 * fit.uncertainty[key], (key, err, fit.uncertainty[key])
    # and precisely: F and f to 0.1 %, the rail zero to 0.2 mm, a and b to 0.05 %
    assert fit.uncertainty["main_focal_mm"] < 1e-3 * F
    assert fit.uncertainty["mla_focal_mm"] < 1e-3 * f
    assert fit.uncertainty["rail_zero_object_distance_mm"] < 0.2
    assert fit.uncertainty["b_mm"] < 5e-4 * b and fit.uncertainty["a_mm"] < 5e-4 * A_F


def test_without_the_reference_corner_the_priors_carry_their_tolerance() -> None:
    fit = fit_camera_model(_measurements(2, magnification=False), _priors(0.7, -0.05, 2.0))
    assert fit.determined_by["main_focal_mm"] == "prior"
    assert fit.determined_by["rail_zero_object_distance_mm"] == "prior"
    # the uncertainty of b (and a) now carries the data sheets' tolerances: about 2 %
    assert fit.uncertainty["b_mm"] > 0.5e-2 * b
    for key in ("b_mm", "a_mm", "mla_focal_mm"):
        assert abs(fit.values[key] - TRUTH[key]) <= 3 * fit.uncertainty[key]


def test_shading_bias_of_the_disparity_is_removed() -> None:
    # without the white image's pitch, b comes from the slope of 1/Q(v)
    biased = fit_camera_model(_measurements(3, eta=0.003, white=False), _priors())
    ignored = fit_camera_model(
        SweepMeasurements(
            **{**_measurements(3, eta=0.003, white=False).__dict__, "eta": 0.0, "eta_se": 0.0}
        ),
        _priors(),
    )
    # ignoring it biases b by about -eta·Q0 (-0.06 %); modelling it removes the bias
    assert ignored.values["b_mm"] / b - 1 == pytest.approx(-0.003 * 0.2, rel=0.2)
    assert abs(biased.values["b_mm"] - b) <= 3 * biased.uncertainty["b_mm"]


def test_a_focal_length_longer_than_the_object_distance_is_refused() -> None:
    with pytest.raises(ModelError, match="main_focal_mm = 300 mm"):
        fit_camera_model(_measurements(4), _priors(dF=300.0 - F))


def test_a_negative_tolerance_is_refused() -> None:
    priors = Priors(F, -1.0, f, 0.05, U_RAIL0, 2.0, 1)
    with pytest.raises(ModelError, match="tolerance of main_focal_mm"):
        fit_camera_model(_measurements(5), priors)


def test_uncertainties_cover_the_truth_over_seeds() -> None:
    z = []
    for seed in range(20):
        fit = fit_camera_model(_measurements(100 + seed), _priors(0.7, -0.05, 2.0))
        z += [(fit.values[k] - TRUTH[k]) / fit.uncertainty[k] for k in ("b_mm", "main_focal_mm")]
    z = np.abs(np.array(z))
    assert 0.36 <= np.mean(z <= 1.0) and np.mean(z <= 3.0) >= 0.9


def _with_scale(data: SweepMeasurements, scale: float, scale_se: float = 3e-6) -> SweepMeasurements:
    return SweepMeasurements(**{**data.__dict__, "image_scale": scale, "image_scale_se": scale_se})


BETA = b / L
Q0 = b / A_F


def test_the_micro_image_pitch_holds_b_against_a_disparity_bias_that_grows_with_defocus() -> None:
    # the corner fits add a defocus bias of their own (eta 0.008) to the shading's (0.002 ±
    # 0.0006): b from the slope of 1/Q(v) alone is off by about -(0.008 - 0.002)·Q0, within
    # its uncertainty; the white image's (L+b)/L, read low by the rims' shading, holds b.
    # Q to 1e-4 per frame, as in micro-images of 50 px
    data = SweepMeasurements(
        **{
            **_measurements(6, eta=0.008, q_noise=1e-4, white=False).__dict__,
            "eta": 0.002,
            "eta_se": 6e-4,
        }
    )
    alone = fit_camera_model(data, _priors(0.7, -0.05, 2.0))
    assert alone.values["b_mm"] / b - 1 == pytest.approx(-0.006 * Q0, rel=0.5)
    assert abs(alone.values["b_mm"] - b) <= 2 * alone.uncertainty["b_mm"]
    assert alone.image_scale == {"measured": None, "used": False}
    measured = 1 + BETA * (1 + (BETA - Q0) * 0.002) + 2e-6
    held = fit_camera_model(_with_scale(data, measured), _priors(0.7, -0.05, 2.0))
    assert held.image_scale["used"] and abs(held.image_scale["z"]) < 3
    assert held.image_scale["rim_shading"] == pytest.approx(BETA * (BETA - Q0) * 0.002, rel=0.01)
    assert abs(held.values["b_mm"] / b - 1) < 2e-4
    assert held.values["eta"] == pytest.approx(0.008, abs=3 * held.uncertainty["eta"])
    for key in ("b_mm", "L_mm", "a_mm", "mla_focal_mm"):
        assert abs(held.values[key] - TRUTH[key]) <= 3 * held.uncertainty[key], key


def test_a_micro_image_pitch_the_sweep_contradicts_is_not_used() -> None:
    # a thick main lens: the micro-images are centred by its exit pupil, 8 mm in front of the
    # principal plane, so the white image's pitch says (L'+b)/L' with L' = L - 8 mm
    data = _measurements(7, white=False)
    alone = fit_camera_model(data, _priors())
    thick = fit_camera_model(_with_scale(data, 1 + b / (L - 8.0)), _priors())
    assert not thick.image_scale["used"] and thick.image_scale["z"] > 3
    assert thick.image_scale["sweep"] == pytest.approx(
        1 + BETA, abs=5 * thick.image_scale["sweep_se"]
    )
    assert thick.values["b_mm"] == pytest.approx(alone.values["b_mm"], rel=1e-9)
    assert thick.to_dict()["image_scale"]["used"] is False
