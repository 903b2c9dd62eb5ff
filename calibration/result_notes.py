"""The result's notes: the warnings a calibration carries and the reasons it gives up.

Each function turns one finding of :func:`calibration.combine.combine` into the
sentence an operator reads (what was seen, with numbers, and what to do): an
implausible aperture scale, a white image whose rims are blurred, data-sheet values
the sweep contradicts (:func:`priors_section`), the sensor's clip in the frames or the
white image, the two corners disagreeing, and why no frame showed a measurable corner.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .camera_model import PRIORS, CameraModelFit, Priors
from .frame_analysis import MIN_MICRO_IMAGES
from .mla_grid import MlaGrid
from .shading import WhiteShading
from .summary import FrameSummary

KAPPA_PLAUSIBLE_MIN = 0.80
"""A fitted aperture scale ``κ`` below this is reported. ``κ`` is the defocus kernel's RMS
width over that of a box of the full pitch: 1 for a square lens filling its cell,
``√12/4 = 0.866`` for a round one. Round lenses ray-traced by the Monte-Carlo renderer
fit 0.849-0.852 (three seeds; the kernel's shape trades a little against its scale), so
the bound sits below them; a Monte-Carlo sweep with strong diffraction whose focus plane
is 16 ± 15 mm off fits 0.71, and before the edge profiles were flat-fielded four such
seeds of five fitted 0.41-0.84 with the focus plane 5-38 mm off at 4-14σ."""


def aperture_scale_warning(kappa: float) -> str | None:
    """The warning for an implausibly small fitted aperture scale ``κ`` (None when plausible)."""
    if not kappa < KAPPA_PLAUSIBLE_MIN:
        return None
    return (
        f"the defocus blur is {kappa:.2f} times the full microlens aperture, well below a "
        "round lens filling its cell (0.87): either the microlenses' fill factor is small "
        "or the defocus model does not describe these edges (seen with strong diffraction, "
        "where the focus plane came out 5-38 mm off, far outside its uncertainty): check "
        "the focus plane and a independently"
    )


def rim_shading_warning(sh: WhiteShading) -> str:
    """The warning for a white image whose curvature inside the micro-images is not angular
    shading alone (:attr:`~calibration.shading.WhiteShading.interior_consistent` false)."""
    seen = (
        f"the white image's shading curves by {sh.curvature_px2:.2e} px^-2 inside the "
        f"micro-images ({sh.inner_curvature_px2:.2e} px^-2 inside half their radius)"
    )
    if sh.tilt_measured:
        return (
            f"{seen} but the micro-images tilt across the sensor as {sh.tilt_curvature_px2:.2e} "
            f"± {sh.tilt_curvature_se_px2:.1e} px^-2: the micro-image rims are blurred into the "
            "interior (diffraction?); the angular shading behind the disparity's shading bias "
            "and the pitch's rim correction is taken from the tilt"
        )
    return (
        f"{seen}: the micro-image rims are blurred into the interior (diffraction?), so the "
        "angular shading, and with it the disparity's shading bias and the pitch's rim "
        "correction, is taken as anywhere between 0 and the measured curvature (b and L less "
        "certain)"
    )


def priors_section(cam: CameraModelFit, priors: Priors) -> tuple[dict[str, Any], list[str]]:
    """``priors`` of the result: data sheet vs calibrated, and a warning per contradiction.

    ``z = (datasheet - calibrated)/sqrt(σ² + tolerance²)``; a prior is
    contradicted when it is off by more than its tolerance plus three sigma of
    the calibration.
    """
    section: dict[str, Any] = {}
    warnings = []
    for name in PRIORS:
        sheet, tol = priors.value(name), priors.tolerance(name)
        cal, se = cam.values[name], cam.uncertainty[name]
        diff = sheet - cal
        z = diff / math.hypot(se, tol)
        by = cam.determined_by[name]
        contradicted = by == "sweep" and abs(diff) > tol + 3 * se
        section[name] = {
            "datasheet": sheet,
            "calibrated": cal,
            "uncertainty": se,
            "tolerance": tol,
            "z": z,
            "determined_by": by,
            "sweep_only_uncertainty": cam.sweep_only_uncertainty[name],
            "contradicted": contradicted,
        }
        if contradicted:
            warnings.append(
                f"the data sheet's {name} = {sheet:g} mm is contradicted by the sweep: "
                f"calibrated {cal:.4f} ± {se:.4f} mm, off by {diff:+.4f} mm against a tolerance "
                f"of {tol:g} mm (z = {z:+.1f})"
            )
    section["L_mm"] = {"calibrated": cam.values["L_mm"], "uncertainty": cam.uncertainty["L_mm"]}
    fell_back = [n for n in PRIORS if cam.determined_by[n] == "prior"]
    if fell_back:
        warnings.append(
            "the sweep could not fix "
            + ", ".join(fell_back)
            + ": the data-sheet value"
            + ("s were" if len(fell_back) > 1 else " was")
            + " used with "
            + ("their tolerances, which are" if len(fell_back) > 1 else "its tolerance, which is")
            + " carried in the uncertainties"
        )
    check = cam.image_scale
    if check.get("measured") is not None and not check["used"]:
        warnings.append(
            f"the white image's micro-image pitch gives (L+b)/L = {check['measured']:.6f} ± "
            f"{check['measured_se']:.6f}, the sweep {check['sweep']:.6f} ± {check['sweep_se']:.6f} "
            f"(z = {check['z']:+.1f}): the micro-images are not centred on the projections of "
            "the main lens's principal point (a thick lens whose exit pupil lies far from it, "
            "or a microlens pitch other than the data sheet's); b and L come from the sweep alone"
        )
    return section, warnings


def why_no_corners(frames: Sequence[FrameSummary]) -> str:
    """The likely reason a sweep's frames show no measurable board corner: corners seen but
    too near the micro-images' rims to be measured (small micro-images, large Q), or no
    board at all."""
    # a corner identified (its micro-images grouped) but not fitted: too few measured it
    few = sum(
        1
        for fs in frames
        if not np.isfinite(fs.Q)
        and any(
            c is not None and not c.get("found") and int(c.get("micro_images") or 0) > 0
            for c in (fs.standard, fs.reference)
        )
    )
    reasons: dict[str, int] = {}
    for fs in frames:
        for reason, n in fs.rejected.items():
            if reason:
                reasons[reason] = reasons.get(reason, 0) + n
    top = max(reasons, key=lambda k: reasons[k]) if reasons else ""
    rim = "micro-image interior" in top and reasons[top] >= 3 * len(frames)
    if 2 * few < len(frames) and not rim:
        return "is the board aligned with the lens axis and in view?"
    per_frame = reasons[top] / len(frames) if top else 0.0
    seen = (
        f"in {few} frames the corners were identified but measured in fewer than "
        f"{MIN_MICRO_IMAGES} micro-images; {per_frame:.0f} micro-images per frame were "
        f"rejected as '{top}'"
        if 2 * few >= len(frames)
        else f"{per_frame:.0f} micro-images per frame showed a corner but were rejected as '{top}'"
    )
    return (
        f"{seen}: the micro-images are too small for a corner's "
        "four half-edges at this Q (README, Known limits)"
    )


def clipped_edges_note(frames: Sequence[FrameSummary], max_count: int | None) -> str:
    """What the sensor's clip took from the blur ("" when nothing): how many frames had
    half-edges left out because their bright side reached full scale."""
    per_frame = [
        sum(int((c or {}).get("clipped_half_edges") or 0) for c in (fs.standard, fs.reference))
        for fs in frames
    ]
    hit = [n for n in per_frame if n > 0]
    if not hit:
        return ""
    scale = f" ({max_count} counts)" if max_count is not None else ""
    return (
        f"the sensor clipped the board's bright squares at full scale{scale} in {len(hit)} of "
        f"{len(frames)} frames: {sum(hit)} half-edges were left out of the blur (a clipped "
        "edge reads sharper); lower the exposure or the gain and record the sweep again"
    )


WHITE_CLIPPED_WARNING = 1e-3
"""A white image with more than this fraction of its lit pixels clipped is reported:
its micro-images' centres and shading (so the pitch, and b, and the edges' flat field)
are then measured on clipped discs (beyond :data:`~calibration.clipping.WHITE_CLIPPED_LIMIT`
it is refused)."""


def white_clipped_note(grid: MlaGrid, max_count: int | None) -> str:
    """A warning when the white image is clipped ("" otherwise)."""
    fraction = grid.white_clipped_fraction
    if not fraction > WHITE_CLIPPED_WARNING:
        return ""
    scale = f" ({max_count} counts)" if max_count is not None else ""
    return (
        f"the white image is clipped: {100 * fraction:.1f} % of its lit pixels at full "
        f"scale{scale}; the micro-images' centres and shading, and so the pitch, b and the "
        "edges' flat field, are measured on clipped discs (nothing measurable at 20 %, b "
        "-0.21 % at 57 %, which is refused): record the white image with a lower exposure"
    )


def vignetting_note(grid: MlaGrid, frames: Sequence[FrameSummary]) -> str:
    """What the main lens's vignetting took ("" when the white image shows none): where it
    starts, the white image's micro-images left out of the lattice, and the corners
    measured in vignetted micro-images (:mod:`calibration.vignetting`)."""
    onset = grid.vignetting_onset_px
    if not math.isfinite(onset):
        return ""
    note = (
        f"the main lens vignets the micro-images beyond {onset:.0f} px from the principal "
        f"point ({grid.rejected.get('vignetted', 0)} of the white image's micro-images are "
        "cut): the lattice, the shading and the plateau were measured inside that radius, "
        "and the edge spreads use only the pixels that see the whole microlens aperture"
    )
    parts = []
    for name in ("standard", "reference"):
        counts = [
            int((getattr(fs, name) or {}).get("vignetted_micro_images") or 0) for fs in frames
        ]
        hit = [n for n in counts if n > 0]
        if hit:
            parts.append(f"the {name} corner in {len(hit)} of {len(frames)} frames")
    if parts:
        note += (
            f"; {' and '.join(parts)} was measured in vignetted micro-images, whose disparity "
            "and main image can be biased (on a ray-traced camera whose rear stop cut a "
            "quarter of each of the reference corner's micro-images, b -0.02 % and F -0.02 %, "
            "within their sigma): for the best b and F, place the reference corner where the "
            "main lens does not vignet, nearer the axis or with the lens stopped down"
        )
    return note


def corner_disagreement_note(agreement: dict[str, Any]) -> str:
    """A warning when the two corners measure different Q in the same frames ("" otherwise;
    ``agreement`` from :func:`calibration.two_corners.corner_agreement`)."""
    if agreement.get("consistent") is not False:
        return ""
    return (
        "the standard and the reference corner measure different Q in the same frames "
        f"(mean difference {agreement['mean_difference']:+.2e}, "
        f"{100 * agreement['relative_difference']:+.3f} %): the MLA may be tilted or the "
        "field curved, or the disparity reads differently at the two field positions "
        "(up to 0.11 % seen on a ray-traced camera with neither); Q is averaged over "
        "both corners"
    )


__all__ = [
    "KAPPA_PLAUSIBLE_MIN",
    "WHITE_CLIPPED_WARNING",
    "aperture_scale_warning",
    "clipped_edges_note",
    "corner_disagreement_note",
    "priors_section",
    "rim_shading_warning",
    "vignetting_note",
    "white_clipped_note",
    "why_no_corners",
]
