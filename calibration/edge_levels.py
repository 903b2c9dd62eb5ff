"""The levels of edge profiles: each profile's dark level and contrast from its tails.

Both readers return ``(z, C)``: every sample mapped to the unit step,
``z = (y - B_p)/C_p`` (0 dark, 1 light), and each profile's contrast ``C_p`` (NaN
when a tail has fewer than 2 samples). Samples are placed at their signed distance
``x`` from the edge (pixels, dark side negative), one profile per row;
``x_flat`` is where the tails start (:func:`calibration.edge_window.flat_distance`).

* :func:`levels_with_drift`: for profiles not flat-fielded, the levels of flat tails
  with a relative drift per block across the edge (vignetting and cos⁴ change the
  brightness across a micro-image and multiply dark and light alike);
* :func:`levels_with_tail_shape`: for flat-fielded profiles, no drift; the levels read
  at fixed points of tails whose shape (a parabola per side) the frame's profiles share.

Used by :func:`calibration.edge_spread.frame_esf`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def levels_with_drift(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    block: NDArray[np.int64],
    x_flat: float,
    *,
    iterations: int = 4,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(z, C)``: samples mapped to the unit step by levels read off the flat tails.

    Least squares of ``y = (1 + γ_k·x)·(B_p + C_p·H(x))`` over the samples with
    ``|x| ≥ x_flat``: for given drifts ``γ_k`` the levels of each profile are a
    2×2 linear problem, solved in closed form and projected out (variable
    projection), and each block's ``γ_k`` takes Gauss–Newton steps on what is
    left. ``C`` is NaN for a profile with fewer than 2 tail samples on either side.
    """
    n_blocks = int(block.max()) + 1
    light = x >= x_flat
    dark = x <= -x_flat
    tail = (light | dark).astype(np.float64)
    step = light.astype(np.float64)
    gamma = np.zeros(n_blocks)
    b = c = np.zeros(x.shape[0])
    for _ in range(iterations):
        one = 1.0 + gamma[block][:, None] * x
        basis = _LevelBasis(one * tail, one * step)  # (the light tail is inside the tails)
        b, c = basis.solve(y)
        resid = (y - b[:, None] * one - c[:, None] * one * step) * tail
        g = x * (b[:, None] + c[:, None] * step) * tail  # d model / d gamma
        g_perp = basis.residual_of(g)
        num = np.bincount(block, np.nan_to_num(_dot(g_perp, resid)), n_blocks)
        den = np.bincount(block, np.nan_to_num(_dot(g_perp, g_perp)), n_blocks)
        gamma = gamma + np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)
    one = 1.0 + gamma[block][:, None] * x
    z = (y / one - b[:, None]) / np.where(c == 0, np.nan, c)[:, None]
    enough = (dark.sum(axis=1) >= 2) & (light.sum(axis=1) >= 2)
    return z, np.where(enough, c, np.nan)


def levels_with_tail_shape(
    x: NDArray[np.float64], y: NDArray[np.float64], x_flat: float, *, iterations: int = 3
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(z, C)`` of flat-fielded profiles whose tails may still fall off (no drift).

    Least squares of ``y = B_p + C_p·T(x)`` over the samples with ``|x| ≥ x_flat``,
    where ``T`` is 1 plus a parabola in ``x - r`` on the light tail and a parabola in
    ``x + r`` on the dark one (``r = x_flat + 1``): the levels are read at ``±r``
    whatever the profile's sampling phase, and the tails' shape (four coefficients) is
    the frame's, shared by every profile. A diffraction-limited edge's tails still fall
    off as 1/x there (5-9 % short of the levels 4-6 px out at f/15.6 in green light);
    read as if flat, each profile's levels depend on where its samples fall, which
    leaves a ripple of one pixel's period in the pooled function. For a given shape the
    levels are closed-form per profile (projected out); the shape's coefficients take
    Gauss–Newton steps on what is left. The samples keep that shape (``z`` is not
    flattened in the tails). ``C`` is NaN for a profile with fewer than 2 tail samples
    on either side.
    """
    light = x >= x_flat
    dark = x <= -x_flat
    ref = x_flat + 1.0
    sums = _TailSums(
        np.stack(
            [
                (light | dark).astype(np.float64),  # the dark level's column
                light.astype(np.float64),
                np.where(light, x - ref, 0.0),  # the four levers of the tails' shape
                np.where(dark, x + ref, 0.0),
                np.where(light, (x - ref) ** 2, 0.0),
                np.where(dark, (x + ref) ** 2, 0.0),
            ]
        ),
        y,
    )
    levers = slice(2, 6)
    slopes = np.zeros(4)
    b = c = np.zeros(x.shape[0])
    for k in range(iterations + 1):
        shape = np.concatenate([[0.0, 1.0], slopes])  # T's coefficients on the columns
        with_shape = sums.dot(shape)  # (P, 6): each column's dot with T
        aa, ab, bb = sums.gram[:, 0, 0], with_shape[:, 0], with_shape @ shape
        det = _level_det(aa, ab, bb)
        b, c = _level_solve(aa, ab, bb, det, sums.y_dot[:, 0], sums.y_dot @ shape)
        if k == iterations:
            break
        ok = np.isfinite(det)
        # Gauss-Newton on the shape with the levels projected out (variable projection):
        # the derivative of profile p's model by lever i is c_p·L_i; what the two level
        # columns A = (tail, T) leave of it has the Gram matrix
        # c²·L_iᵀL_j - u_iᵀ(AᵀA)⁻¹u_j, u_i = c_p·AᵀL_i; the residual is orthogonal to A,
        # so its dot with the projected derivative is c_p·L_iᵀ(y - b - c·T). Profiles
        # without levels (det NaN) weigh nothing.
        c_ok = np.where(ok, c, 0.0)
        inv_det = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        u_b = c_ok[:, None] * sums.gram[:, 0, levers]
        u_c = c_ok[:, None] * with_shape[:, levers]
        normal = (
            np.tensordot(c_ok * c_ok, sums.gram[:, levers, levers], axes=1)
            - (u_b.T * (bb * inv_det)) @ u_b
            + (u_b.T * (ab * inv_det)) @ u_c
            + (u_c.T * (ab * inv_det)) @ u_b
            - (u_c.T * (aa * inv_det)) @ u_c
        )
        rhs = c_ok @ (
            sums.y_dot[:, levers] - np.where(ok, b, 0.0)[:, None] * sums.gram[:, 0, levers] - u_c
        )
        if not (np.all(np.isfinite(normal)) and np.all(np.isfinite(rhs))):
            break
        # least norm: profiles at one sampling phase leave the shape partly free (any
        # choice then maps every profile alike)
        slopes = slopes + np.linalg.lstsq(normal, rhs, rcond=1e-10)[0]
    z = (y - b[:, None]) / np.where(c == 0, np.nan, c)[:, None]
    enough = (dark.sum(axis=1) >= 2) & (light.sum(axis=1) >= 2)
    return z, np.where(enough, c, np.nan)


class _TailSums:
    """Per profile, the dot products of a few sample columns with each other (``gram``,
    ``(P, m, m)``) and with the data (``y_dot``, ``(P, m)``): every least-squares sum over
    combinations of those columns, without another pass over the samples."""

    def __init__(self, columns: NDArray[np.float64], y: NDArray[np.float64]) -> None:
        m = columns.shape[0]
        self.gram = np.empty((y.shape[0], m, m))
        for i in range(m):
            for j in range(i, m):
                self.gram[:, i, j] = self.gram[:, j, i] = _dot(columns[i], columns[j])
        self.y_dot = np.stack([_dot(col, y) for col in columns], axis=1)

    def dot(self, coefficients: NDArray[np.float64]) -> NDArray[np.float64]:
        """Per profile, each column's dot with the combination of the columns with these
        coefficients, ``(P, m)`` (one matrix-vector product over all profiles)."""
        p, m, _ = self.gram.shape
        return (self.gram.reshape(p * m, m) @ coefficients).reshape(p, m)


class _LevelBasis:
    """Per profile, the least squares onto two columns (the dark level's and the
    contrast's, over the tail samples): coefficients of a data array, and what of a
    derivative is left once the levels are projected out (variable projection)."""

    def __init__(self, col_b: NDArray[np.float64], col_c: NDArray[np.float64]) -> None:
        self.col_b, self.col_c = col_b, col_c
        self.aa, self.ab, self.bb = _dot(col_b, col_b), _dot(col_b, col_c), _dot(col_c, col_c)
        self.det = _level_det(self.aa, self.ab, self.bb)

    def solve(self, v: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per profile, the coefficients of the two columns fitted to ``v``."""
        vb, vc = _dot(v, self.col_b), _dot(v, self.col_c)
        return _level_solve(self.aa, self.ab, self.bb, self.det, vb, vc)

    def residual_of(self, g: NDArray[np.float64]) -> NDArray[np.float64]:
        """``g`` less its per-profile projection onto the two columns."""
        pb, pc = self.solve(g)
        return g - pb[:, None] * self.col_b - pc[:, None] * self.col_c


def _level_det(
    aa: NDArray[np.float64], ab: NDArray[np.float64], bb: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Per profile, the determinant of the two level columns' normal matrix
    ``[[aa, ab], [ab, bb]]``; NaN where it is below 1e-12 of ``aa·bb`` (no levels)."""
    det = aa * bb - ab * ab
    return np.where(np.abs(det) > 1e-12 * np.maximum(aa * bb, 1e-300), det, np.nan)


def _level_solve(
    aa: NDArray[np.float64],
    ab: NDArray[np.float64],
    bb: NDArray[np.float64],
    det: NDArray[np.float64],
    vb: NDArray[np.float64],
    vc: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per profile, the dark level and the contrast from the normal matrix
    ``[[aa, ab], [ab, bb]]`` (determinant ``det``) and the columns' dots ``vb``, ``vc``
    with the data."""
    return (bb * vb - ab * vc) / det, (aa * vc - ab * vb) / det


def _dot(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise dot products."""
    return np.einsum("pk,pk->p", u, v)
