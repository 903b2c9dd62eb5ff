"""The paper's focus-plane confirmation (Eq. 7-9) against constructed ground truth.

The delivered focus plane (the whole-sweep defocus model) is tested in
``test_defocus.py``; these are the published quantities reported beside it.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from calibration.focus import corner_size_mm, paper_focus


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
