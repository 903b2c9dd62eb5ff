"""The design of the whole-sweep defocus fit: what a unit static mass does to each bin.

:class:`calibration.defocus_problem.DefocusProblem` fits with it. Here are the
closed-form integrals of the geometric defocus kernels (a box, a uniform disk and their
mixture) and :class:`DefocusDesign`: for given ``(Q0, κ, α, s)`` the kernel's integrated
cumulative line spread tabulated on a fine lattice per observation (geometric or
wave-optical, :mod:`calibration.wave_defocus`, averaged over each observation's placement
jitter) and interpolated at the ends of every bin's interval for every static node:
``A[k, b, i]``. Its per-observation work runs in blocks of observations on a thread pool.
Positions in pixels along the edge normal, ``Q`` dimensionless.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from concurrent.futures import Executor
from typing import TypeVar

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray
from scipy.ndimage import uniform_filter1d

from .wave_defocus import WAVE_MIN_PX, defocus_integral_rest, jittered_ramp_rest

STATIC_STEP_PX = 0.05
"""Spacing of the static kernel's nodes (pixels). The kernel is piecewise linear between
them: each node's mass is spread over a triangle reaching the next nodes (two passes of a
moving average of about the spacing), not a point. Point masses make every edge-spread
function a staircase of 0.05 px steps; a geometric defocus smooths it, but the
wave-optical kernel near focus is almost a point, and bins whose profiles share one
sub-pixel phase (edges along the pixel rows) sample the staircase: on exact wave-optical
edges of a diffraction-limited microlens (f/15.6, 550 nm) one frame's function could not
be fitted with any static kernel (chi-square 17 where the noise gives 0)."""

FIT_HALF_PX = 4.5
"""Only bins within this distance of the edge are fitted (pixels)."""

STATIC_HALF_PX = FIT_HALF_PX + 1.5
"""Half width of the static kernel (pixels); mass beyond it goes into the offsets. It
reaches past the fitted window: a diffraction-limited microlens (a square aperture at
f/12.5 in green light has its first zero at λN = 2.75 px of 2.5 µm) spreads light into
lobes and 1/x² tails that cross the whole window, and a kernel cut at 3 px left them to
the per-frame offset and gain, which cannot take their shape: on exact functions Q0 came
out 0.67 % low, on a Monte-Carlo sweep with that diffraction 12 % off with κ = 0.5
(tests/test_defocus.py); with the kernel 1.5 px past the window it is exact again."""


def _box_integral(t: NDArray[np.floating], d: NDArray[np.floating]) -> NDArray[np.float64]:
    """``∫_{-∞}^{t} C(τ) dτ`` of the cumulative line-spread ``C`` of a box of width ``d``."""
    dd = np.maximum(d, 1e-9)
    inside = np.clip(t + 0.5 * dd, 0.0, dd)
    return np.where(t > 0.5 * dd, t, inside * inside / (2.0 * dd))


def _disk_integral(t: NDArray[np.floating], d: NDArray[np.floating]) -> NDArray[np.float64]:
    """``∫_{-∞}^{t} C(τ) dτ`` of the cumulative line-spread of a uniform disk of diameter ``d``.

    With ``u = 2t/d``: ``C = ½ + (u√(1-u²) + asin u)/π`` and its integral is
    ``(d/2)·[u/2 + (u·asin u + √(1-u²))/π - (1-u²)^{3/2}/(3π)]``: 0 below the
    disk, ``t`` above it; the special functions are evaluated only inside.
    """
    t, dd = np.broadcast_arrays(t, np.maximum(d, 1e-9))
    out = np.where(t >= 0.5 * dd, t, 0.0).astype(np.float64)
    inside = np.abs(t) < 0.5 * dd
    u = 2.0 * t[inside] / dd[inside]
    root = np.sqrt(1.0 - u * u)
    j = 0.5 * u + (u * np.arcsin(u) + root) / np.pi - root**3 / (3.0 * np.pi)
    out[inside] = 0.5 * dd[inside] * j
    return out


def _aperture_integral(
    t: NDArray[np.floating], d: NDArray[np.floating], alpha: float
) -> NDArray[np.float64]:
    """``∫C`` of the aperture's line spread at diameter ``d``: box (``α``) and disk mixture."""
    out = alpha * _box_integral(t, d) if alpha > 0.0 else np.zeros(np.broadcast(t, d).shape)
    if alpha < 1.0:
        out = out + (1.0 - alpha) * _disk_integral(t, d)
    return np.asarray(out, dtype=np.float64)


def _aperture_rest_on_lattice(
    lattice: NDArray[np.floating], d: NDArray[np.float64], alpha: float
) -> NDArray[np.float64]:
    """``∫C - max(t, 0)`` of the aperture at diameters ``d`` (one row each) on ``lattice``
    (uniformly spaced, increasing; px).

    It is zero outside the kernel, ``|t| > d/2`` (``∫C`` is 0 below it and ``t`` above), so
    the closed forms of :func:`_aperture_integral` are evaluated only on the lattice nodes
    within ``d/2`` (and one node either side) of each row; the rest of the row is 0.
    """
    n_nodes = lattice.size
    spacing = float(lattice[1] - lattice[0])
    half = 0.5 * np.maximum(d, 1e-9)
    first = np.clip(np.floor((-half - lattice[0]) / spacing).astype(np.int64) - 1, 0, n_nodes)
    last = np.clip(np.ceil((half - lattice[0]) / spacing).astype(np.int64) + 1, -1, n_nodes - 1)
    counts = np.maximum(last - first + 1, 0)
    rest = np.zeros((d.size, n_nodes))
    if not counts.any():
        return rest
    ends = np.cumsum(counts)
    along = np.arange(int(ends[-1])) - np.repeat(ends - counts, counts) + np.repeat(first, counts)
    row = np.repeat(np.arange(d.size), counts)
    t = lattice[along]
    rest[row, along] = _aperture_integral(t, d[row], alpha) - np.maximum(t, 0.0)
    return rest


JITTER_NEGLIGIBLE_PX = 0.01
"""Placement jitter (px) below which an observation's model is not averaged over it (its
variance, 1e-4 px², is far below what the defocus fit resolves)."""

_HERMITE_NODES, _HERMITE_WEIGHTS = np.polynomial.hermite_e.hermegauss(5)
_JITTER_NODES = (_HERMITE_NODES, _HERMITE_WEIGHTS / np.sum(_HERMITE_WEIGHTS))
"""Gauss-Hermite nodes and weights of the standard normal: the average over the placement
jitter of an observation (:attr:`BinnedEsf.jitter_px`)."""


def diameter_factor(kappa: float, alpha: float) -> float:
    """Aperture diameter factor for RMS scale ``κ`` and shape ``α``.

    ``κ`` scales the kernel's RMS width to that of a box of diameter ``κ·d``
    whatever the shape, so ``κ`` and ``α`` are nearly uncorrelated: a box of
    width ``d`` has variance ``d²/12``, a uniform disk's projection ``d²/16``.
    """
    return kappa * float(np.sqrt((1.0 / 12.0) / (alpha / 12.0 + (1.0 - alpha) / 16.0)))


_T = TypeVar("_T")


def _node_spread(rows: NDArray[np.floating], lattice_px: float) -> NDArray[np.floating]:
    """``rows`` (functions on a lattice of spacing ``lattice_px``) convolved with the
    triangle that spreads a static node's mass to its neighbours (two centred moving
    averages of the odd number of lattice steps nearest ``STATIC_STEP_PX``)."""
    taps = 2 * int(round(0.5 * STATIC_STEP_PX / lattice_px)) + 1
    once = uniform_filter1d(rows, taps, axis=-1, mode="nearest")
    return np.asarray(uniform_filter1d(once, taps, axis=-1, mode="nearest"), dtype=rows.dtype)


class DefocusDesign:
    """``A[k, b, i]``, bin ``b`` of observation ``k`` for a unit static mass at ``±g_i``.

    The static kernel is a set of point masses at ``g_i = i·STATIC_STEP_PX``
    (mirrored: it is symmetric). Each bin of the data is the mean of samples
    spread about its mean position ``x̄`` with standard deviation ``σ``; the
    model of a bin is the function averaged over the uniform interval of the
    same mean and spread, ``x̄ ± w`` with ``w = √3·σ`` (a point value when the
    profiles share one sub-pixel phase, the bin average when their phases
    cover it). For the mass at ``±g`` that is ``[IC(x̄+w∓g) - IC(x̄-w∓g)]/(2w)``
    with ``IC`` the integral of the defocus kernel's cumulative line spread,
    tabulated per observation on a fine lattice and interpolated.
    """

    LATTICE_PX = 0.005

    def __init__(
        self,
        q: NDArray[np.float64],
        jitter: NDArray[np.float64],
        xbar: NDArray[np.float64],
        half: NDArray[np.float64],
        lens_pitch_px: float,
        *,
        pool: Executor | None = None,
        blocks: int = 1,
    ) -> None:
        """``q`` and ``jitter`` (px) per observation, ``xbar`` and ``half`` (px) per
        observation and bin: the bins' mean positions and their intervals' half widths.
        ``pool`` and ``blocks``: the per-observation work (the kernels' lattices, the
        interpolation; :meth:`map_blocks` for a caller's) is cut into ``blocks`` contiguous
        runs of observations, run on ``pool`` (threads: numpy releases the GIL for these
        array operations); the result is the same as in one block."""
        self.pitch = lens_pitch_px
        self.pool = pool
        self.q = q
        self.jitter = jitter
        # the jitter the wave kernel takes (negligible ones as none): derived once here
        self.wave_jitter = np.where(jitter > JITTER_NEGLIGIBLE_PX, jitter, 0.0)
        self._ramp_rest: NDArray[np.float64] | None = None  # the wave kernel's jittered ramp
        n, n_bins = xbar.shape
        n_cells = int(round(STATIC_HALF_PX / STATIC_STEP_PX)) + 1
        self.grid = np.arange(n_cells) * STATIC_STEP_PX
        half = np.maximum(half, 2 * self.LATTICE_PX)
        g = self.grid[None, None, :]
        xb, wb = xbar[:, :, None], half[:, :, None]
        self.start = -FIT_HALF_PX - STATIC_HALF_PX - 1.0
        self.n_lattice = (
            int(np.ceil(2 * (FIT_HALF_PX + STATIC_HALF_PX + 1.0) / self.LATTICE_PX)) + 2
        )
        self._locate_windows(xbar + half, xbar - half, n_cells)
        self.shape = (n, n_bins, n_cells)
        self._set_blocks(blocks if pool is not None else 1)
        self.lattice = self.start + np.arange(self.n_lattice) * self.LATTICE_PX
        ramp = np.maximum(self.lattice, 0.0)
        # what spreading the nodes (:func:`_node_spread`) adds to the ramp max(t, 0)
        self.ramp_spread = (_node_spread(ramp, self.LATTICE_PX) - ramp).astype(np.float32)
        self.norm = (4.0 * half)[:, :, None].astype(np.float32)  # 2w (bin average) x 2 (mirror)
        # ∫C follows the ramp max(t, 0) outside the kernel: its part of every interval's
        # difference, IC(x̄+w∓g) - IC(x̄-w∓g), is clip(x̄+w∓g, 0, 2w), taken exactly here
        # (float64); the float32 lattice holds only the bounded rest, IC - max(t, 0), whose
        # kink sits on the lattice node t = 0 (so the interpolation is the same as of IC)
        self.ramp = (np.clip(xb + wb - g, 0.0, 2.0 * wb) + np.clip(xb + wb + g, 0.0, 2.0 * wb)) / (
            4.0 * wb
        )

    def _locate_windows(
        self, upper: NDArray[np.float64], lower: NDArray[np.float64], n_cells: int
    ) -> None:
        """Where each bin's interval ends ``upper`` = x̄+w and ``lower`` = x̄-w (px, per
        observation and bin) read the lattice for every static node.

        The nodes lie on the lattice (node ``i`` at ``i·node_steps`` lattice steps), so the
        end ``x̄ ± w ∓ g_i`` sits ``∓i·node_steps`` lattice steps from ``x̄ ± w``, at the same
        fraction of a step: over the nodes it reads a window of lattice values
        ``node_steps`` apart, backwards for ``-g_i`` and forwards for ``+g_i``. Stored by
        phase (:meth:`_by_phase`), the lattice holds each window contiguously; here are the
        windows' starts within their observation's phase-ordered lattice, in the order
        ``x̄+w-g, x̄-w-g, x̄+w+g, x̄-w+g`` (``window``), and the fractions (``window_frac``).
        """
        steps = STATIC_STEP_PX / self.LATTICE_PX
        self.node_steps = int(round(steps))
        if abs(steps - self.node_steps) > 1e-9:
            raise ValueError("the static nodes must lie on the lattice")
        self.n_phase_nodes = -(-self.n_lattice // self.node_steps)
        reach = n_cells - 1
        backward: list[NDArray[np.intp]] = []
        forward: list[NDArray[np.intp]] = []
        self.window_frac: list[NDArray[np.float32]] = []
        for end in (upper, lower):
            t = (end - self.start) / self.LATTICE_PX
            node = np.floor(t)
            along, phase = np.divmod(node.astype(np.intp), self.node_steps)
            if along.min() < reach or along.max() + reach >= self.n_phase_nodes:
                raise ValueError("a bin's interval reaches beyond the design's lattice")
            backward.append(phase * self.n_phase_nodes + (self.n_phase_nodes - 1 - along))
            forward.append(phase * self.n_phase_nodes + along)
            self.window_frac.append((t - node).astype(np.float32))
        self.window = [backward[0], backward[1], forward[0], forward[1]]
        self.window_frac = self.window_frac * 2  # x̄+w, x̄-w, x̄+w, x̄-w

    def _by_phase(
        self, rows: NDArray[np.float32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Lattice rows (one per observation) reordered by phase: the nodes ``r, r+m, r+2m,
        ...`` (``m = node_steps``) of each row one after the other, forwards and, for the
        backward windows, each phase reversed; as sliding windows of the static nodes'
        count (row ``k`` of the result starts at element ``k``)."""
        n_rows = rows.shape[0]
        m, n_phase = self.node_steps, self.n_phase_nodes
        padded = np.zeros((n_rows, m * n_phase), dtype=np.float32)
        padded[:, : self.n_lattice] = rows
        by_phase = padded.reshape(n_rows, n_phase, m).transpose(0, 2, 1)
        n_cells = self.shape[2]
        forward = sliding_window_view(np.ascontiguousarray(by_phase).ravel(), n_cells)
        backward = sliding_window_view(np.ascontiguousarray(by_phase[:, :, ::-1]).ravel(), n_cells)
        return forward, backward

    def _set_blocks(self, blocks: int) -> None:
        """Cut the observations into ``blocks`` contiguous runs, with each run's windows
        (:meth:`_locate_windows`) as starts in its own phase-ordered lattice."""
        n = self.shape[0]
        bounds = np.linspace(0, n, max(1, min(blocks, n)) + 1).round().astype(int)
        self.blocks = [
            slice(int(k0), int(k1)) for k0, k1 in zip(bounds[:-1], bounds[1:], strict=True)
        ]
        per_row = self.node_steps * self.n_phase_nodes
        self.block_window = [
            [(w[b] + (np.arange(b.stop - b.start) * per_row)[:, None]).ravel() for w in self.window]
            for b in self.blocks
        ]
        self.block_window_frac = [[f[b].ravel() for f in self.window_frac] for b in self.blocks]

    def map_blocks(self, work: Callable[[int], _T]) -> list[_T]:
        """``work(k)`` of every block ``k`` (``self.blocks[k]``, a slice of the observations),
        on the pool when there is one."""
        if self.pool is None or len(self.blocks) == 1:
            return [work(k) for k in range(len(self.blocks))]
        return list(self.pool.map(work, range(len(self.blocks))))

    def _geometric_rest(
        self, d: NDArray[np.float64], alpha: float, rows: slice = slice(None)
    ) -> NDArray[np.float64]:
        """``∫C - max(t, 0)`` on the lattice of the geometric aperture at diameters ``d`` (of
        the observations ``rows``), each observation's placement jitter averaged over
        (Gauss-Hermite, where not negligible)."""
        integral = _aperture_rest_on_lattice(self.lattice, d, alpha)
        jitter = self.jitter[rows]
        jittered = np.flatnonzero(jitter > JITTER_NEGLIGIBLE_PX)
        if jittered.size:
            t = self.lattice[None, :]
            dj = d[jittered, None]
            smooth = np.zeros((jittered.size, self.lattice.size))
            for node, weight in zip(*_JITTER_NODES, strict=True):
                smooth += weight * _aperture_integral(t + node * jitter[jittered, None], dj, alpha)
            integral[jittered] = smooth - np.maximum(t, 0.0)
        return integral

    def _wave_rest(
        self, d: NDArray[np.float64], alpha: float, s: float, rows: slice = slice(None)
    ) -> NDArray[np.float64]:
        """The same for the effective defocus kernel of diffraction scale ``s`` px
        (:mod:`calibration.wave_defocus`; its jitter exactly, as a Gaussian factor)."""
        if not self.wave_jitter.any():
            return defocus_integral_rest(self.lattice, d, s, alpha)
        rest = defocus_integral_rest(self.lattice, d, s, alpha, self.wave_jitter[rows])
        return rest + self._jittered_ramp()[rows]

    def _jittered_ramp(self) -> NDArray[np.float64]:
        """The wave kernel's jittered ramp (:func:`jittered_ramp_rest`) of every observation,
        made at its first use (the same at every evaluation)."""
        if self._ramp_rest is None:
            self._ramp_rest = jittered_ramp_rest(self.lattice, self.wave_jitter)
        return self._ramp_rest

    def design(self, theta: NDArray[np.float64], rows: NDArray[np.int64]) -> NDArray[np.float64]:
        """``A[k, b, i]``: bin ``b`` of observation ``k`` for a unit static mass at ``±g_i``.

        ``theta = (Q0, κ, α, s)``: the diffraction scale ``s`` (px) makes the defocus kernel
        the wave-optical one (:mod:`calibration.wave_defocus`); 0 is geometric, and below
        ``WAVE_MIN_PX`` the two are blended linearly."""
        if rows.size != self.shape[0]:
            raise ValueError("the design is built for every observation at once")
        q0, kappa, alpha, s = theta
        d = diameter_factor(kappa, alpha) * self.pitch * np.abs(self.q[rows] - q0)
        if s > 0.0 and self.wave_jitter.any():
            self._jittered_ramp()  # made once, before the blocks share it
        out = np.empty(self.shape)
        self.map_blocks(lambda k: self._design_block(d, float(alpha), float(s), k, out))
        return out

    def _design_block(
        self, d: NDArray[np.float64], alpha: float, s: float, block: int, out: NDArray[np.float64]
    ) -> None:
        """:meth:`design` of the observations of block ``block``, written into their rows of
        ``out``."""
        rows = self.blocks[block]
        d = d[rows]
        if s >= WAVE_MIN_PX:
            integral = self._wave_rest(d, alpha, s, rows)
        else:
            integral = self._geometric_rest(d, alpha, rows)
            if s > 0.0:
                share = s / WAVE_MIN_PX
                wave = self._wave_rest(d, alpha, WAVE_MIN_PX, rows)
                integral = (1.0 - share) * integral + share * wave
        # linear interpolation on the lattice from its values and forward differences, of the
        # part beyond the ramp (bounded: float32 keeps ~1e-8 of it where ∫C itself reaches
        # 12 px and lost ~1e-6 in the differences, enough to move Q0 by 0.1σ of its noise)
        # the static nodes spread (:func:`_node_spread`), in the lattice's float32
        spread = _node_spread(integral.astype(np.float32), self.LATTICE_PX)
        lattice = spread + self.ramp_spread
        step = np.zeros_like(lattice)
        np.subtract(lattice[:, 1:], lattice[:, :-1], out=step[:, :-1])
        value_forward, value_backward = self._by_phase(lattice)
        step_forward, step_backward = self._by_phase(step)
        n_rows = (rows.stop - rows.start) * self.shape[1]
        values = np.zeros((n_rows, self.shape[2]), dtype=np.float32)
        for sign, window, fractions, backward in zip(
            (1.0, -1.0, 1.0, -1.0),
            self.block_window[block],
            self.block_window_frac[block],
            (True, True, False, False),
            strict=True,
        ):
            value = (step_backward if backward else step_forward)[window]
            value *= fractions[:, None]
            value += (value_backward if backward else value_forward)[window]
            if sign > 0:
                values += value
            else:
                values -= value
        shape = (rows.stop - rows.start, *self.shape[1:])
        np.add(values.reshape(shape) / self.norm[rows], self.ramp[rows], out=out[rows])  # float64

    def subset(self, keep: NDArray[np.int64]) -> DefocusDesign:
        """The design of the observations at ``keep`` (in order) alone, in one block, as if
        built from them (a jackknife's refit)."""
        sub = copy.copy(self)
        for name in ("q", "jitter", "wave_jitter", "norm", "ramp"):
            setattr(sub, name, getattr(self, name)[keep])
        sub._ramp_rest = None if self._ramp_rest is None else self._ramp_rest[keep]
        sub.window = [w[keep] for w in self.window]
        sub.window_frac = [f[keep] for f in self.window_frac]
        sub.shape = (keep.size, *self.shape[1:])
        sub.pool = None
        sub._set_blocks(1)
        return sub
