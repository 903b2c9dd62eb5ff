"""Thin-lens relations of OPTICS.md §1 against values computed by hand."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from calibration import optics
from calibration.optics import CameraOptics, paper_optics


def test_main_lens_image_distance_by_hand() -> None:
    # 1/300 + 1/v = 1/35  ->  v = 300*35/265
    assert_allclose(optics.image_distance(300.0, 35.0), 10500.0 / 265.0, rtol=1e-12)
    assert_allclose(optics.object_distance(10500.0 / 265.0, 35.0), 300.0, rtol=1e-12)


def test_paper_values_f_and_patch_size() -> None:
    # the paper: F = 35, a = 15, b = 3  ->  f = 2.5, Q = 0.2, p = 20 px with D/delta = 100
    assert_allclose(optics.f_from_ab(15.0, 3.0), 2.5, rtol=1e-12)
    assert_allclose(optics.focused_virtual_distance(2.5, 3.0), 15.0, rtol=1e-12)
    q = optics.q_ratio(15.0, 3.0)
    assert_allclose(q, 0.2, rtol=1e-12)
    assert_allclose(optics.patch_size_px(q, 0.25, 0.0025), 20.0, rtol=1e-12)
    assert_allclose(optics.b_from_q(0.2, 2.5), 3.0, rtol=1e-12)
    assert_allclose(optics.a_from_q(0.2, 2.5), 15.0, rtol=1e-12)


def test_paper_optics_focus_plane_at_300() -> None:
    o = paper_optics()
    # L = v(300) + a_f = 10500/265 + 15 = 54.6226...
    assert_allclose(o.L, 10500.0 / 265.0 + 15.0, rtol=1e-12)
    assert_allclose(o.L, 54.6226, atol=1e-4)
    assert_allclose(o.u0, 300.0, rtol=1e-12)
    assert_allclose(o.Q(300.0), 0.2, rtol=1e-12)
    assert_allclose(o.patch_px(300.0), 20.0, rtol=1e-12)
    # f-number matching L/A = b/D
    assert_allclose(o.L / o.aperture, o.b / o.D, rtol=1e-12)


def test_blur_diameter_by_hand() -> None:
    o = paper_optics()
    u = 250.0
    v = 250.0 * 35.0 / 215.0
    a = o.L - v
    expected_mm = 0.25 * 3.0 * abs(1.0 / 15.0 - 1.0 / a)
    assert_allclose(optics.blur_diameter(u, o.F, o.f, o.D, o.b, o.L), expected_mm, rtol=1e-12)
    assert_allclose(o.blur_px(u), expected_mm / 0.0025, rtol=1e-12)
    assert o.blur_px(300.0) == pytest.approx(0.0, abs=1e-9)
    # about 1.5 px at the near end of the paper's sweep, as ESIF.md says
    assert 1.4 < o.blur_px(250.0) < 1.6


def test_micro_image_scaling_and_count() -> None:
    o = paper_optics()
    k = optics.image_centre_scale(o.L, o.b)
    assert_allclose(k, (o.L + 3.0) / o.L, rtol=1e-12)
    assert_allclose(o.image_pitch_px, 100.0 * k, rtol=1e-12)
    n = optics.micro_images_per_point(15.0, 3.0, o.L)
    assert_allclose(n, 5.0 * (o.L + 3.0) / (o.L - 15.0), rtol=1e-12)
    assert 7.0 < n < 7.5  # about 7 per axis, not 1/Q = 5


def test_vectorized_over_arrays() -> None:
    o = paper_optics()
    u = np.array([250.0, 300.0, 350.0])
    q = o.Q(u)
    assert q.shape == (3,)
    assert q[0] > q[1] > q[2]


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"b": 2.0}, "must exceed f"),
        ({"D": -0.25}, "D = -0.25"),
        ({"delta": 0.0}, "delta = 0.0"),
        ({"L": 20.0}, "no object distance is in focus"),
        ({"F": math.nan}, "F = nan"),
    ],
)
def test_impossible_optics_rejected(changes: dict[str, float], message: str) -> None:
    base = dict(F=35.0, f=2.5, D=0.25, delta=0.0025, b=3.0, L=54.6, aperture=4.5)
    base.update(changes)
    with pytest.raises(ValueError, match=message):
        CameraOptics(**base)
