"""The paper's parameters from ``Q`` at the focus plane (ESIF Eq. 1–5).

``b = f(1+Q)``, ``a = b/Q``, ``p = Q·D/δ`` with the data-sheet microlens focal
length ``f``: reported beside the sweep-wide calibration
(:mod:`calibration.camera_model`), which does not trust ``f``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Estimate:
    """A set of calibrated parameters with 1-sigma uncertainties (mm, px)."""

    a_mm: float
    b_mm: float
    Q: float
    patch_size_px: float
    focus_object_distance_mm: float
    a_se_mm: float = float("nan")
    b_se_mm: float = float("nan")
    Q_se: float = float("nan")
    patch_size_se_px: float = float("nan")
    focus_se_mm: float = float("nan")
    L_mm: float = float("nan")
    L_se_mm: float = float("nan")

    def to_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


def paper_estimate(
    Q_focus: float,
    Q_focus_se: float,
    *,
    f: float,
    D: float,
    delta: float,
    focus_object_distance_mm: float,
    focus_se_mm: float = float("nan"),
) -> Estimate:
    """Eq. 1–5 from ``Q`` at the focus plane: ``b = f(1+Q)``, ``a = b/Q``, ``p = Q D/δ``."""
    b = f * (1.0 + Q_focus)
    a = b / Q_focus
    return Estimate(
        a_mm=a,
        b_mm=b,
        Q=Q_focus,
        patch_size_px=Q_focus * D / delta,
        focus_object_distance_mm=focus_object_distance_mm,
        a_se_mm=f * Q_focus_se / Q_focus**2,
        b_se_mm=f * Q_focus_se,
        Q_se=Q_focus_se,
        patch_size_se_px=Q_focus_se * D / delta,
        focus_se_mm=focus_se_mm,
    )
