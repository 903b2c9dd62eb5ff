"""Half-edges centred on their own edges before pooling (calibration.edge_centres).

Ground truth: profiles synthesised from a known edge spread, each half-edge's samples
placed with a known common error (as a lattice's offset error places them: the two
halves of an edge moved by opposite amounts), at random sub-pixel phases with noise.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from calibration.edge_bins import group_means
from calibration.edge_centres import centre_half_edges, lsf_centroid
from calibration.edge_spread import EdgeProfiles, frame_esf
from calibration.placement_error import PlacementError


def _truth(x: np.ndarray, width_px: float = 0.25) -> np.ndarray:
    """A sharp, symmetric edge spread: a step blurred by a Gaussian of ``width_px``."""
    return np.asarray(ndtr(x / width_px), dtype=np.float64)


@pytest.mark.parametrize("centre", [-0.37, 0.0, 0.11, 0.8])
def test_the_line_spread_centroid_is_where_a_symmetric_edge_lies(centre: float) -> None:
    x = np.linspace(-4.0, 4.0, 321)
    found, se = lsf_centroid(x, _truth(x - centre, 0.6), half_window_px=4.0)
    assert found == pytest.approx(centre, abs=2e-4)
    assert se == 0.0


@pytest.mark.parametrize("half_window_px", [3.0, 2.0])
def test_the_centroid_standard_error_describes_its_scatter(half_window_px: float) -> None:
    """With the levels read off the end points (window 3 px) or off the tails beyond it."""
    rng = np.random.default_rng(7)
    x = np.linspace(-3.0, 3.0, 121)
    clean = _truth(x - 0.05, 0.4)
    noise = 0.02 * (0.3 + clean * (1 - clean))  # more noise on the edge, as ray noise has
    draws = [
        lsf_centroid(x, clean + rng.normal(0.0, noise), half_window_px=half_window_px, se=noise)
        for _ in range(2000)
    ]
    found = np.array([d[0] for d in draws])
    claimed = np.array([d[1] for d in draws])
    assert np.std(found) == pytest.approx(float(np.median(claimed)), rel=0.08)
    assert np.mean(found) == pytest.approx(0.05, abs=3 * np.std(found) / np.sqrt(found.size))


def test_too_few_points_or_no_rise_give_no_centroid() -> None:
    x = np.linspace(-1.0, 1.0, 9)
    assert np.isnan(lsf_centroid(x, _truth(x), half_window_px=1.0)[0])
    x = np.linspace(-3.0, 3.0, 61)
    assert np.isnan(lsf_centroid(x, 1.0 - _truth(x), half_window_px=3.0)[0])


def _half_edge_profiles(
    seed: int, offsets: dict[int, float], *, per_half_edge: int = 60, noise: float = 0.01
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Point-sampled profiles of sharp half-edges: positions as the lattice placed them
    (the true distance plus the half-edge's error), values and labels."""
    rng = np.random.default_rng(seed)
    xs, vs, labels = [], [], []
    for label, offset in offsets.items():
        for _ in range(per_half_edge):
            true_x = np.arange(-6, 7) + rng.uniform(-0.5, 0.5)
            xs.append(true_x + offset)
            vs.append(_truth(true_x) + rng.normal(0.0, noise, true_x.size))
            labels.append(label)
    x, v = np.array(xs), np.array(vs)
    return x, v, np.ones_like(x), np.array(labels, dtype=np.int64)


def test_each_half_edge_is_moved_onto_its_own_edge() -> None:
    # a lattice offset error of 0.12 px across the vertical edge and 0.07 px across the
    # horizontal one: opposite on the two halves of each; half-edge 4 has 5 profiles only
    offsets = {0: 0.12, 1: -0.12, 2: 0.07, 3: -0.07, 4: 0.3}
    x, v, w, label = _half_edge_profiles(3, offsets)
    few = np.flatnonzero(label == 4)[5:]
    usable = np.ones(label.size, dtype=np.bool_)
    usable[few] = False
    centres = centre_half_edges(x, v, w, label, usable=usable, half_window_px=3.0, min_profiles=8)
    for h, offset in offsets.items():
        on = label == h
        if h == 4:
            assert not centres.kept[on].any()
            continue
        assert centres.kept[on].all()
        np.testing.assert_allclose(centres.shift_px[on], offset, atol=0.01)
    # what the centroids' errors leave between the half-edges: small and positive
    assert 0.0 < centres.spread_px2 < 0.005**2


def test_pooled_half_edges_give_back_the_edge_spread_not_their_placement_errors() -> None:
    offsets = {0: 0.15, 1: -0.15, 2: 0.1, 3: -0.1}
    x, v, _, label = _half_edge_profiles(5, offsets, per_half_edge=40, noise=0.004)
    dark, contrast = 100.0, 800.0
    y = dark + contrast * v
    block = np.arange(label.size)  # one block per profile: no drift shared
    placed = EdgeProfiles(x, y, block, None, label)
    unlabelled = EdgeProfiles(x, y, block)
    centred = frame_esf(placed, start_width_px=0.25, drift=False)
    pooled = frame_esf(unlabelled, start_width_px=0.25, drift=False)
    assert centred is not None and pooled is not None
    inside = np.abs(centred.x) < 2.0
    np.testing.assert_allclose(centred.value[inside], _truth(centred.x[inside]), atol=0.03)
    # the lattice's placement alone mixes four copies 0.1-0.15 px apart into the function
    assert centred.spread_px() == pytest.approx(0.25, abs=0.02)
    assert pooled.spread_px() > centred.spread_px() + 0.03


def test_the_jitter_left_is_the_spread_within_each_group() -> None:
    """Each group's common shift is taken out: a placement error common to a half-edge
    leaves nothing; what varies within one (its lever on the scale, on the slope) is drawn
    many times and matched."""
    rng = np.random.default_rng(11)
    n = 160
    label = np.repeat(np.arange(4), n // 4)
    sign = np.where(label % 2 == 0, 1.0, -1.0)
    axis = (label // 2).astype(np.int64)
    lever = rng.uniform(-80.0, 80.0, n)
    gradients = np.zeros((n, 5))
    gradients[:, 0] = sign * lever
    gradients[np.arange(n), 1 + axis] = -sign
    gradients[np.arange(n), 3 + axis] = sign
    sigma = np.diag([1e-7, 4e-3, 2e-3, 1e-3, 1e-3])
    slope_var = np.full(n, 1e-8)
    placement = PlacementError(gradients, sigma, sign * lever, slope_var, axis)
    weights = rng.uniform(0.5, 2.0, n)
    spreads = []
    for _ in range(4000):
        delta = rng.normal(0.0, np.sqrt(np.diag(sigma)))
        slope = rng.normal(0.0, 1e-4, 2)
        e = gradients @ delta + slope[axis] * sign * lever
        e = e - group_means(e, weights, label)
        spreads.append(np.average(e**2, weights=weights))
    grouped = placement.jitter_px(weights, groups=label)
    assert grouped == pytest.approx(np.sqrt(np.mean(spreads)), rel=0.03)
    # the offsets alone (constant within every half-edge) leave nothing once grouped
    offsets_only = PlacementError(
        gradients * np.array([0.0, 1, 1, 1, 1]), sigma, np.zeros(n), np.zeros(n), axis
    )
    assert offsets_only.jitter_px(weights, groups=label) == pytest.approx(0.0, abs=1e-9)
    assert offsets_only.jitter_px(weights) > 0.05
