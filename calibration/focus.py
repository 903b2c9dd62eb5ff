"""Focus-plane confirmation as published (ESIF Eq. 7–9).

Per frame: ``Ls``, ``Lr`` (corner pixel sizes of the standard and reference
corner), ``Lp = Cr/(Lr - Ls)`` (object mm per pixel, Eq. 7), ``La = Lp·Ls``
(corner size in mm, Eq. 8). The paper's focus plane is ``argmin La`` (Eq. 9);
here it is refined below the rail step by a weighted quadratic through the
frames around the minimum. It is reported beside the delivered focus plane
(:mod:`calibration.defocus`) for comparison only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


@dataclass(frozen=True)
class PaperFocus:
    """Eq. 9: the frame with the smallest ``La`` and the refined argmin (mm)."""

    best_index: int
    object_distance_mm: float


def corner_size_mm(
    Ls_px: ArrayLike, Lr_px: ArrayLike, reference_gap_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``Lp = Cr/(Lr - Ls)`` (mm/px, Eq. 7) and ``La = Lp·Ls`` (mm, Eq. 8); NaN where undefined."""
    ls = np.asarray(Ls_px, dtype=np.float64)
    lr = np.asarray(Lr_px, dtype=np.float64)
    diff = lr - ls
    with np.errstate(divide="ignore", invalid="ignore"):
        lp = np.where(diff > 0, reference_gap_mm / diff, np.nan)
    return lp, lp * ls


def paper_focus(
    object_distance_mm: ArrayLike, La_mm: ArrayLike, *, half_window: int = 6
) -> PaperFocus | None:
    """Eq. 9: ``argmin La(u)``, refined by a quadratic over ``±half_window`` frames.

    Returns None when fewer than 3 frames have a finite ``La``.
    """
    u = np.asarray(object_distance_mm, dtype=np.float64)
    la = np.asarray(La_mm, dtype=np.float64)
    good = np.flatnonzero(np.isfinite(la))
    if good.size < 3:
        return None
    order = good[np.argsort(u[good])]
    us, las = u[order], la[order]
    # a light median smoothing so that one noisy frame cannot win the argmin
    k = int(np.argmin(_median3(las)))
    lo, hi = max(0, k - half_window), min(len(us), k + half_window + 1)
    u_best = float(us[k])
    if hi - lo >= 3:
        c = np.polyfit(us[lo:hi] - us[k], las[lo:hi], 2)
        if c[0] > 0:
            vertex = -c[1] / (2 * c[0])
            if abs(vertex) <= (us[hi - 1] - us[lo]) / 2:
                u_best = float(us[k] + vertex)
    return PaperFocus(int(order[k]), u_best)


def _median3(x: NDArray[np.float64]) -> NDArray[np.float64]:
    if x.size < 3:
        return x
    padded = np.concatenate([[x[0]], x, [x[-1]]])
    return np.median(np.stack([padded[:-2], padded[1:-1], padded[2:]]), axis=0)
