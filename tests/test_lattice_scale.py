"""A corner's lattice scale smoothed over the sweep (calibration.lattice_scale).

Ground truth from the thin-lens model of OPTICS.md §1 (``Q = b/a(u)``), the data
sheet's F and rail zero off by 2 % and 2 mm, the disparity's smooth shading bias
on top and per-frame noise that grows near the focus plane (where one frame's
``Q`` is worst): the smoothed ``Q`` must be several times closer to the truth
than the frames' own, its standard error must cover its error over seeds, and a
wild frame must not pull it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration.defocus_problem import EdgeObservation
from calibration.edge_spread import BinnedEsf, LeverGroup
from calibration.lattice_scale import MIN_FRAMES, replace_profiles, smooth_corner_q
from calibration.optics import image_distance

F, B, L = 35.0, 3.0, 54.6226
ETA = 0.01  # the disparity's shading bias: Q·(1 + η(Q - Q0))


def _sweep(seed: int, n: int = 31) -> tuple[np.ndarray, ...]:
    """True Q (biased as the disparity reads it), u from a data sheet that is off, Q_se."""
    rng = np.random.default_rng(seed)
    rail = np.arange(n) * 2.0
    u_true = 250.0 + rail
    q = B / (L - np.asarray(image_distance(u_true, F)))
    q0 = float(np.median(q))
    q_read = q * (1.0 + ETA * (q - q0))
    se = q * np.where(np.abs(q - q0) < 0.004, 2e-3, 3e-4)  # sharp corners near focus: worse
    measured = q_read + rng.normal(0.0, se)
    u_sheet = 252.0 + rail  # rail zero 2 mm off
    return q_read, measured, se, u_sheet


def test_the_smoothed_scale_is_far_closer_to_the_truth_than_each_frame() -> None:
    truth, measured, se, u = _sweep(1)
    fit = smooth_corner_q(u, measured, se, main_focal_mm=F * 1.02)
    assert fit is not None
    own = np.sqrt(np.mean((measured - truth) ** 2))
    smooth = np.sqrt(np.mean((fit.smooth - truth) ** 2))
    assert smooth < own / 4.0
    assert np.all(np.abs(fit.smooth - truth) < 4.0 * fit.smooth_se)


def test_its_standard_error_covers_its_error_over_seeds() -> None:
    z = []
    for seed in range(200):
        truth, measured, se, u = _sweep(seed)
        fit = smooth_corner_q(u, measured, se, main_focal_mm=F * 0.98)
        assert fit is not None
        z.append((fit.smooth[15] - truth[15]) / fit.smooth_se[15])
    inside = float(np.mean(np.abs(np.array(z)) < 1.0))
    assert 0.58 < inside < 0.78  # 68 % ± 3 binomial sd of 200


def test_a_wild_frame_does_not_pull_the_curve() -> None:
    truth, measured, se, u = _sweep(2)
    measured[7] *= 1.02  # a mis-identified micro-image: 2 % off, far beyond its error
    fit = smooth_corner_q(u, measured, se, main_focal_mm=F)
    assert fit is not None
    assert abs(fit.smooth[7] - truth[7]) < 4.0 * fit.smooth_se[7]
    assert np.max(np.abs(fit.smooth - truth) / fit.smooth_se) < 4.0


def test_too_few_frames_give_no_curve() -> None:
    truth, measured, se, u = _sweep(3, n=MIN_FRAMES - 1)
    assert smooth_corner_q(u, measured, se, main_focal_mm=F) is None


def _esf(shift_px: float) -> BinnedEsf:
    x = np.arange(-3.0, 3.0, 0.1) + 0.05
    value = 0.5 * (1.0 + np.tanh((x - shift_px) / 0.4))
    n = np.full(x.size, 20)
    return BinnedEsf(x, value, np.full(x.size, 1e-3), n, 40, None, 0.01)


def test_each_frame_is_placed_again_by_its_error_against_the_curve() -> None:
    """Two lever groups (±100 px) of a frame whose lattice scale is 1e-3 too large: their
    functions sit ±0.1 px apart; placed again they coincide and the jitter they carried is
    what the groups leave."""
    truth, measured, se, u = _sweep(4)
    frames = np.arange(truth.size)
    measured = truth + 1e-3  # every frame's scale 1e-3 too large: the curve is truth + 1e-3
    measured[10] = truth[10] + 2e-3  # this frame 1e-3 more than the curve
    groups = (
        LeverGroup(-100.0, 0.0, _esf(-0.2)),
        LeverGroup(100.0, 0.0, _esf(0.0)),
    )
    pooled = BinnedEsf.merge([g.esf for g in groups])
    obs = [
        EdgeObservation(
            int(f),
            "standard",
            float(measured[f]),
            BinnedEsf(
                pooled.x,
                pooled.value,
                pooled.se,
                pooled.count,
                80,
                pooled.x_sd,
                0.1,
                0.005,
                groups,
            ),
        )
        for f in frames
    ]
    out = replace_profiles(
        obs,
        {int(f): float(d) for f, d in zip(frames, u, strict=True)},
        {(int(f), "standard"): float(s) for f, s in zip(frames, se, strict=True)},
        main_focal_mm=F,
    )
    moved = out[10].esf
    # 1e-3 · ±100 px: the groups move by ∓0.1 px and meet at -0.1
    assert moved.centre_px() == pytest.approx(-0.1, abs=0.01)
    assert moved.jitter_px == pytest.approx(0.005, abs=0.002)
    half = np.abs(moved.value - 0.5).argmin()
    assert moved.x[half] == pytest.approx(-0.1, abs=0.06)
    # frames on the curve stay where their groups' mean lever puts them
    assert out[3].esf.centre_px() == pytest.approx(-0.1, abs=0.01)
    # observations without lever groups are left as they are
    bare = [replace(o, esf=pooled) for o in obs]
    again = replace_profiles(
        bare,
        {int(f): float(d) for f, d in zip(frames, u, strict=True)},
        {(int(f), "standard"): float(s) for f, s in zip(frames, se, strict=True)},
        main_focal_mm=F,
    )
    assert all(a.esf is pooled for a in again)
