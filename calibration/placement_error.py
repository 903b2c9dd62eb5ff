"""How far a corner's lattice may have misplaced each of its edge profiles, and the spread
that leaves in a pooled edge-spread function.

:mod:`calibration.edge_profiles` places every profile at its distance from the edge the
corner lattice predicts. The prediction errs: linearly in the lattice's parameters
``(1+Q, c_x, c_y, half_x, half_y)`` (each profile with its own gradient, the lattice's
covariance giving their errors) and in the edge's slope (a profile moves by the slope's
error times its distance along the edge from its micro-image's corner image). The pooled
function (:func:`calibration.edge_spread.frame_esf`) is the edge spread convolved with the
spread of those errors about their common shift, as the pooled function weighs its
profiles: its weights (each profile's contrast squared, none for a profile that shows no
edge) are known only once the profiles' levels are read, so the errors are kept here per
profile and the spread is taken with whatever weights the caller pools with.

Why the weights matter: the profiles that err most are the farthest from the micro-images
the lattice was measured in (the largest levers on its scale and on the slopes), and
those are often the faintest (the rim of the field, or outside what the frame shows: no
edge, no weight). Their unweighted spread over-states what the pooled function carries;
on a ray-traced 50 px camera by a third, which the defocus model then took as blur that
is not there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .edge_bins import group_means


@dataclass(frozen=True)
class PlacementError:
    """Per profile (``P`` rows, the order of the profiles): ``gradients`` ``(P, 5)``, how
    its position (px) moves per unit error of the lattice's ``(1+Q, c_x, c_y, half_x,
    half_y)``; ``covariance`` ``(5, 5)``, their errors'; ``slope_lever_px`` its lever on
    its edge's slope (px of position per unit of slope: its signed distance along the
    edge), ``slope_var`` the variance of the slope it was placed with (0 when not known)
    and ``axis`` its edge (0 vertical, 1 horizontal: each edge has its own slope)."""

    gradients: NDArray[np.float64]
    covariance: NDArray[np.float64]
    slope_lever_px: NDArray[np.float64]
    slope_var: NDArray[np.float64]
    axis: NDArray[np.int64]

    @staticmethod
    def none() -> PlacementError:
        """No profiles."""
        return PlacementError(
            np.zeros((0, 5)), np.zeros((5, 5)), np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
        )

    def jitter_px(
        self,
        weights: NDArray[np.float64] | None = None,
        *,
        scale_known: bool = False,
        groups: NDArray[np.int64] | None = None,
    ) -> float:
        """RMS spread (px) of the profiles' placement errors about their common shift, the
        profiles weighted by ``weights`` (equal when None; weights that sum to 0 give 0).
        ``scale_known``: the spread left once the lattice's scale is known (its other
        parameters conditioned on it), as when the sweep places the profiles again with a
        scale smoothed over its frames (:mod:`calibration.lattice_scale`). ``groups``: a
        label per profile when each group's common shift is taken out on its own (the
        half-edges, each centred on its own edge: :mod:`calibration.edge_centres`); None:
        one group.

        With errors ``e_p = g_p·δ``, ``δ ~ N(0, Σ)``, the weighted spread is
        ``Σ_p w_p·(g_p - ḡ)ᵀΣ(g_p - ḡ)`` in expectation (``ḡ`` the weighted mean gradient
        of the profile's group, weights normalised); the common shift ``ḡ·δ`` moves the
        group as a whole. The slopes add, per edge, their variance times the weighted
        variance of the levers on that edge (within each group)."""
        n = self.gradients.shape[0]
        if n == 0:
            return 0.0
        w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
        total = float(np.sum(w))
        if not total > 0:
            return 0.0
        w = w / total
        label = np.zeros(n, dtype=np.int64) if groups is None else np.asarray(groups)
        sigma = scale_known_covariance(self.covariance) if scale_known else self.covariance
        centred = self.gradients - group_means(self.gradients, w, label)
        lattice = float(w @ np.einsum("pi,ij,pj->p", centred, sigma, centred))
        slopes = 0.0
        for edge in np.unique(self.axis):
            on = self.axis == edge
            lever = self.slope_lever_px[on]
            lever = lever - group_means(lever, w[on], label[on])
            slopes += float(np.sum(w[on] * self.slope_var[on] * lever**2))
        return float(np.sqrt(max(lattice, 0.0) + max(slopes, 0.0)))


def scale_known_covariance(sigma: NDArray[np.float64]) -> NDArray[np.float64]:
    """The covariance of the other parameters given the first (the scale): zero in its
    row and column, ``Σ_rr - Σ_r0·Σ_0r/Σ_00`` elsewhere."""
    out = np.zeros_like(sigma)
    if sigma[0, 0] > 0:
        out[1:, 1:] = sigma[1:, 1:] - np.outer(sigma[1:, 0], sigma[0, 1:]) / sigma[0, 0]
    else:
        out[1:, 1:] = sigma[1:, 1:]
    return out
