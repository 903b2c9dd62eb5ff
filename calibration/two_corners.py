"""What the two board corners give beyond each one's Q: the main-lens magnification between
them, their agreement, and the systematic spreads of the camera fitted either way.

- ``1/M = u/v`` per frame from the distance of the corners' main images, ``2s`` on the
  board (:func:`inverse_magnification`), or with the main images placed again with the
  camera's ``Q(u)`` (:func:`magnification_on_camera`, :mod:`calibration.main_image`);
- the coherent systematics no per-frame error describes: half the difference between
  cameras fitted with the main images placed with the shading's pull one standard error
  above and below its value (:func:`main_image_systematic`), and with each corner's disparity alone
  (:func:`corner_systematic`), added in quadrature by :func:`add_half_spread`;
- the standard and the reference corner must measure the same ``Q`` in a frame
  (:func:`corner_agreement`: a difference means MLA tilt or field curvature).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera_model import (
    CameraModelFit,
    ModelError,
    Priors,
    SweepMeasurements,
    fit_camera_model,
)
from .main_image import inverse_magnification_from_distance, lever_arm_inverse_magnification
from .mla_grid import MlaGrid
from .summary import FrameSummary, SweepGeometry

CORNER_AGREEMENT_RELATIVE = 2e-4
"""The two corners' Q may differ by this fraction before a significant difference is
reported as a warning (MLA tilt or field curvature)."""


def corner_of(fs: FrameSummary, name: str) -> dict[str, Any] | None:
    """The frame's ``standard`` or ``reference`` corner (None when not measured)."""
    return fs.standard if name == "standard" else fs.reference


def both_found(fs: FrameSummary) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """The frame's (standard, reference) corners when both were found, else None."""
    a, b = fs.standard, fs.reference
    return (a, b) if a and b and a.get("found") and b.get("found") else None


def inverse_magnification(
    frames: list[FrameSummary], g: SweepGeometry
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``1/M = u/v`` per frame from the two corners' main images, ``2s`` apart on the board.

    NaN where either corner is missing. The main image of board point X lies
    at ``-X·M`` (OPTICS.md §3), so ``|r_ref - r_std|·δ = 2s·M``.
    """
    inv = np.full(len(frames), np.nan)
    se = np.full(len(frames), np.nan)
    for k, fs in enumerate(frames):
        pair = both_found(fs)
        if pair is None:
            continue
        a, b = pair
        ra, rb = np.array(a["main_image_px"], float), np.array(b["main_image_px"], float)
        sa = np.array(a.get("main_image_se_px") or [np.nan, np.nan], float)
        sb = np.array(b.get("main_image_se_px") or [np.nan, np.nan], float)
        delta = rb - ra
        dist = float(np.hypot(*delta))
        if not (np.all(np.isfinite(delta)) and dist > 0 and np.all(np.isfinite(sa + sb))):
            continue
        dist_se = float(np.sqrt(np.sum((delta / dist) ** 2 * (sa**2 + sb**2))))
        inv[k], se[k] = inverse_magnification_from_distance(
            dist, dist_se, square_mm=g.board.square_mm, pixel_pitch_mm=g.pixel_pitch_mm
        )
    return inv, se


def magnification_on_camera(
    cam: CameraModelFit,
    frames: list[FrameSummary],
    rails: NDArray[np.float64],
    grid: MlaGrid,
    g: SweepGeometry,
    *,
    shading_eta: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``1/M`` per frame from main images placed with the camera's ``Q(u)`` and the shading's pull.

    The angular shading inside each micro-image (a ray's weight falls with its angle at
    the sensor: cos⁴, the pixels' acceptance; :mod:`calibration.shading`) pulls every
    corner's micro-image positions toward their lens centres by a fraction that grows
    with defocus, the main image staying put, so the positions follow
    ``Q·(1 + η_s·(Q - Q0))`` about the lens centres:
    ``shading_eta`` is that ``η_s``, predicted from the white image (the measurement's
    ``eta``), not the disparity's fitted bias ``η``, which also carries how the corner
    fits respond to the blur, a bias of the disparity's reading that moves no
    position. The camera's ``Q`` uncertainty goes through the lever arms
    (:mod:`calibration.main_image`); ``η_s``'s goes into :func:`main_image_systematic`.
    """
    q, q_se = cam.q_at_rail(rails)
    pull = q * shading_eta * (q - cam.values["Q0"])
    return lever_arm_inverse_magnification(
        [fs.corners for fs in frames],
        grid.lens_grid,
        q=q + pull,
        q_se=q_se,
        square_mm=g.board.square_mm,
        pixel_pitch_mm=g.pixel_pitch_mm,
    )


def add_half_spread(
    cam: CameraModelFit, one: CameraModelFit, other: CameraModelFit
) -> dict[str, float]:
    """Half the difference of two alternative cameras, added in quadrature to ``cam``'s
    uncertainty of every quantity; returns the halves."""
    spread = {}
    for key in cam.values:
        half = 0.5 * abs(one.values[key] - other.values[key])
        if math.isfinite(half):
            spread[key] = half
            cam.uncertainty[key] = float(math.hypot(cam.uncertainty[key], half))
    return spread


def main_image_systematic(
    frames: list[FrameSummary],
    measurements: SweepMeasurements,
    priors: Priors,
    cam: CameraModelFit,
    grid: MlaGrid,
    g: SweepGeometry,
) -> dict[str, float]:
    """Half the difference between the cameras whose main images were placed with the
    shading's pull ``η_s`` one standard error above and below its value
    (:func:`magnification_on_camera`; ``measurements.eta`` and ``eta_se``, which carries the
    shading model's own uncertainty): it moves every frame's ``1/M`` coherently (F and the
    rail zero), which no per-frame error describes. Added in quadrature to every quantity;
    empty without magnification.
    """
    if not np.isfinite(measurements.inv_magnification).any():
        return {}
    fits = []
    for sign in (-1.0, 1.0):
        inv_m, inv_m_se = magnification_on_camera(
            cam,
            frames,
            measurements.rail_mm,
            grid,
            g,
            shading_eta=measurements.eta + sign * measurements.eta_se,
        )
        try:
            fits.append(
                fit_camera_model(
                    replace(measurements, inv_magnification=inv_m, inv_magnification_se=inv_m_se),
                    priors,
                )
            )
        except ModelError:
            return {}
    return add_half_spread(cam, fits[0], fits[1])


def corner_systematic(
    frames: list[FrameSummary],
    measurements: SweepMeasurements,
    priors: Priors,
    cam: CameraModelFit,
) -> dict[str, float]:
    """Half the difference between the cameras calibrated from each corner's disparity alone.

    The two corners sit in different parts of the field; a bias of the
    disparity that grows with defocus (a shading or clipping of the aperture
    the model does not describe) tilts ``1/Q(v)`` differently for each, and
    ``b``, ``L`` and ``a`` come from that tilt. Their disagreement is taken as a
    systematic uncertainty, added in quadrature to every quantity (it is
    zero when one corner alone was measured).
    """
    series = {}
    for name in ("standard", "reference"):
        q = np.array([corner_value(fs, name, "Q") for fs in frames])
        q_se = np.array([corner_value(fs, name, "Q_se") for fs in frames])
        if np.sum(np.isfinite(q)) < max(10, len(frames) // 3):
            return {}
        series[name] = (q, q_se)
    fits = []
    for q, q_se in series.values():
        try:
            fits.append(fit_camera_model(replace(measurements, Q=q, Q_se=q_se), priors))
        except ModelError:
            return {}
    return add_half_spread(cam, fits[0], fits[1])


def corner_value(fs: FrameSummary, name: str, key: str) -> float:
    corner = corner_of(fs, name)
    value = None if not corner else corner.get(key)
    return float("nan") if value is None else float(value)


def corner_agreement(frames: list[FrameSummary]) -> dict[str, Any]:
    """Standard vs reference corner Q in the same frames: they must agree."""
    diff, err, u = [], [], []
    for fs in frames:
        pair = both_found(fs)
        if pair is None:
            continue
        a, b = pair
        if a.get("Q") is None or b.get("Q") is None:
            continue
        diff.append(a["Q"] - b["Q"])
        err.append(math.hypot(a["Q_se"], b["Q_se"]))
        u.append(fs.object_distance_mm)
    if len(diff) < 3:
        return {"frames": len(diff), "consistent": None}
    d, e = np.array(diff), np.array(err)
    w = 1.0 / e**2
    mean = float(np.sum(w * d) / np.sum(w))
    z = d / e
    chi = float(np.sqrt(np.mean((d - mean) ** 2 / e**2)))
    mean_se = float(np.sqrt(1.0 / np.sum(w)) * max(chi, 1.0))
    slope = float(np.polyfit(np.array(u), d, 1, w=np.sqrt(w))[0]) if len(d) >= 5 else float("nan")
    q_typ = float(np.median([fs.Q for fs in frames if math.isfinite(fs.Q)]))
    significant = abs(mean) > 3 * mean_se and abs(mean) > CORNER_AGREEMENT_RELATIVE * q_typ
    return {
        "frames": len(d),
        "mean_difference": mean,
        "mean_difference_se": mean_se,
        "relative_difference": mean / q_typ,
        "slope_per_mm": slope,
        "rms_z": float(np.sqrt(np.mean(z**2))),
        "consistent": not significant,
    }
