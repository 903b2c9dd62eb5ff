"""From the frame summaries of a sweep to the calibration result (``lfcal-result/1``).

1. ``Q0``, the disparity at the focus plane, from the geometric defocus of
   every edge of every frame (:mod:`calibration.defocus`);
2. the camera from the whole sweep (:mod:`calibration.camera_model`): ``F``
   and the rail zero from the magnification between the two board corners,
   ``L`` and ``b`` from ``1/Q(v)``, then ``a = b/Q0``, ``f = b/(1+Q0)``, the
   focus plane where ``Q = Q0`` and ``p = Q0·D/δ``; data-sheet values only
   where the sweep cannot fix a quantity;
3. beside it, for comparison: the paper's route (``b = f_datasheet·(1+Q0)``)
   and the paper's ``argmin La`` (Eq. 7–9);
4. checks: the standard and the reference corner must measure the same ``Q``
   in a frame; a data-sheet value the sweep contradicts beyond its tolerance
   is named in a warning.

What the two corners give together (the magnification, their agreement, the coherent
systematics of the camera fitted either way) is in :mod:`calibration.two_corners`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera_model import (
    PRIORS,
    CameraModelFit,
    ModelError,
    Priors,
    SweepMeasurements,
    fit_camera_model,
)
from .defocus import (
    DefocusFit,
    DefocusNotDetermined,
    EdgeObservation,
    fit_defocus,
    jackknife_defocus,
    jackknife_warning,
    rough_focus,
)
from .edge_spread import BinnedEsf
from .focus import corner_size_mm, paper_focus
from .frame_analysis import MIN_MICRO_IMAGES
from .lattice_scale import replace_profiles
from .mla_grid import MlaGrid
from .parameters import Estimate, paper_estimate
from .shading import WhiteShading
from .summary import (
    CalibrationError,
    CalibrationOptions,
    CalibrationResult,
    FocusAtEdgeError,
    FocusNotDeterminedError,
    FrameSummary,
    PriorError,
    SweepGeometry,
    _json_clean,
)
from .two_corners import (
    corner_agreement,
    corner_of,
    corner_systematic,
    inverse_magnification,
    magnification_on_camera,
    main_image_systematic,
)
from .version import DISTRIBUTION, software_version

Q_SYSTEMATIC_RELATIVE = 1e-5
"""Relative systematic uncertainty of one frame's measured Q, added in quadrature to its fit
error (``frames[].Q_se``; the fit's own is ``Q_se_fit``): a bias common to the micro-images
of a frame (lens-lattice and edge-model errors) that their scatter cannot show; measured as
-1e-5 on the project's simulator, where the fit errors alone were 28 % too small."""

REFIT_FRACTION = 0.02
"""The defocus is fitted once more, on the camera with its ``Q0``, when that camera's ``Q(u)``
differs from the first one's (made with the rough ``Q0``) by more than this fraction of
``Q0``'s σ anywhere in the sweep."""


def _frame_arrays(frames: list[FrameSummary]) -> dict[str, NDArray[np.float64]]:
    keys = ("object_distance_mm", "rail_mm", "Q", "Q_se", "Ls_px", "Lr_px", "edge_width_px")
    return {k: np.array([getattr(f, k) for f in frames], dtype=np.float64) for k in keys}


def _observations(frames: list[FrameSummary], g: SweepGeometry) -> list[EdgeObservation]:
    """Every corner's edge-spread function with that corner's own Q, its profiles placed
    by the corner's lattice scale smoothed over the sweep (:mod:`calibration.lattice_scale`)."""
    obs = []
    q_se: dict[tuple[int, str], float] = {}
    for fs in frames:
        for name, esf in fs.esf.items():
            corner = corner_of(fs, name)
            q = None if corner is None else corner.get("Q")
            if q is None or not math.isfinite(q) or not esf:
                continue
            obs.append(EdgeObservation(fs.index, name, float(q), BinnedEsf.from_dict(esf)))
            q_se[(fs.index, name)] = float(corner.get("Q_se") or math.nan)  # type: ignore[union-attr]
    distances = {fs.index: float(fs.object_distance_mm) for fs in frames}
    return replace_profiles(obs, distances, q_se, main_focal_mm=g.main_focal_mm)


SHADING_MODEL_UNCERTAINTY = 0.3
"""Relative uncertainty given to the angular-shading correction of the disparity: the
first-order model of :mod:`calibration.shading` (weights smooth across the aperture,
one curvature for the sensor) is not exact."""


def _shading_bias(
    kappa: float, grid: MlaGrid, g: SweepGeometry
) -> tuple[float, float, dict[str, Any]]:
    """``η`` of the disparity's shading bias ``Q·(1 + η(Q - Q0))`` and its uncertainty.

    ``η = Var(p)·c`` (:mod:`calibration.shading`): ``c`` the angular curvature from the
    white image (uncertain between 0 and the measured curvature when that depends on the
    radius, :meth:`~calibration.shading.WhiteShading.angular_curvature`), the aperture
    variance from the defocus fit's ``κ`` (its RMS width is that of a box ``κ·D/δ`` wide).
    """
    shading = grid.shading
    if shading is None or not np.isfinite(shading.curvature_px2):
        return 0.0, 0.0, {"applied": False}
    variance = (kappa * g.lens_pitch_px) ** 2 / 12.0
    eta = shading.bias_coefficient(variance)
    curvature_se = shading.angular_curvature()[1]
    eta_se = float(np.hypot(curvature_se * variance, SHADING_MODEL_UNCERTAINTY * eta))
    info = {
        "applied": True,
        "eta": eta,
        "eta_se": eta_se,
        "aperture_variance_px2": variance,
        **shading.to_dict(),
    }
    return eta, eta_se, info


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


def _rim_shading_warning(sh: WhiteShading) -> str:
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


def _priors_section(cam: CameraModelFit, priors: Priors) -> tuple[dict[str, Any], list[str]]:
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


def _sweep_estimate(cam: CameraModelFit, g: SweepGeometry) -> Estimate:
    v, se = cam.values, cam.uncertainty
    scale = g.mla_pitch_mm / g.pixel_pitch_mm
    return Estimate(
        a_mm=v["a_mm"],
        b_mm=v["b_mm"],
        Q=v["Q0"],
        patch_size_px=v["Q0"] * scale,
        focus_object_distance_mm=v["focus_object_distance_mm"],
        a_se_mm=se["a_mm"],
        b_se_mm=se["b_mm"],
        Q_se=se["Q0"],
        patch_size_se_px=se["Q0"] * scale,
        focus_se_mm=se["focus_object_distance_mm"],
        L_mm=v["L_mm"],
        L_se_mm=se["L_mm"],
    )


def _on_camera(
    observations: list[EdgeObservation], frames: list[FrameSummary], q_model: NDArray[np.float64]
) -> list[EdgeObservation]:
    """The observations with each frame's ``Q`` replaced by the camera's ``Q(u)``."""
    by_frame = {fs.index: float(q) for fs, q in zip(frames, q_model, strict=True)}
    return [replace(o, Q=by_frame[o.frame]) for o in observations]


def _defocus_dict(d: DefocusFit) -> dict[str, Any]:
    return {
        "Q0": d.Q0,
        "Q0_se": d.Q0_se,
        "Q0_se_curvature": d.Q0_se_curvature,
        "Q0_se_cluster": d.Q0_se_cluster,
        "Q0_se_systematic": d.Q0_se_systematic,
        "Q0_se_model": d.Q0_se_model,
        "Q0_se_jackknife": d.Q0_se_jackknife,
        "jackknife_Q0": list(d.jackknife_Q0),
        "jackknife_consistent": d.jackknife_consistent,
        "aperture_scale": d.kappa,
        "aperture_shape_box": d.shape_box,
        "chi2_reduced": d.chi2_reduced,
        "static_blur_rms_px": d.static_rms_px,
        "max_defocus_px": d.max_blur_px,
        "frames": d.frames,
    }


def _why_no_corners(frames: Sequence[FrameSummary]) -> str:
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
are then measured on clipped discs."""


def white_clipped_note(grid: MlaGrid, max_count: int | None) -> str:
    """A warning when the white image is clipped ("" otherwise)."""
    fraction = grid.white_clipped_fraction
    if not fraction > WHITE_CLIPPED_WARNING:
        return ""
    scale = f" ({max_count} counts)" if max_count is not None else ""
    return (
        f"the white image is clipped: {100 * fraction:.1f} % of its lit pixels at full "
        f"scale{scale}; the micro-images' centres and shading, and so the pitch, b and the "
        "edges' flat field, are measured on clipped discs (b -0.19 % seen with 57 % "
        "clipped): record the white image with a lower exposure"
    )


def _defocus_or_raise(
    observations: list[EdgeObservation],
    g: SweepGeometry,
    partial: dict[str, Any],
    start: DefocusFit | None = None,
    *,
    hint: str = "",
) -> DefocusFit:
    """The whole-sweep defocus fit (from ``start``'s parameters when given);
    :class:`FocusNotDeterminedError` with ``partial`` (``hint`` appended to its message)."""
    theta0 = None if start is None else (start.Q0, start.kappa, start.shape_box)
    try:
        defocus = fit_defocus(observations, lens_pitch_px=g.lens_pitch_px, start=theta0)
    except DefocusNotDetermined as exc:
        partial["error"] = f"focus plane not determined: {exc}" + (f"; {hint}" if hint else "")
        raise FocusNotDeterminedError(partial["error"], _json_clean(partial)) from exc
    partial["focus"] = {"defocus_model": _defocus_dict(defocus)}
    return defocus


def _camera_or_raise(
    focus: tuple[float, float, float],
    arr: dict[str, NDArray[np.float64]],
    inv_m: NDArray[np.float64],
    inv_m_se: NDArray[np.float64],
    grid: MlaGrid,
    g: SweepGeometry,
    partial: dict[str, Any],
) -> tuple[CameraModelFit, SweepMeasurements, dict[str, Any]]:
    """The camera from the sweep with the defocus's ``focus = (Q0, its σ, κ)``;
    :class:`PriorError` with ``partial`` when the data-sheet values admit no thin-lens
    camera."""
    q0, q0_se, kappa = focus
    eta, eta_se, shading = _shading_bias(kappa, grid, g)
    measurements = SweepMeasurements(
        rail_mm=arr["rail_mm"],
        Q=arr["Q"],
        Q_se=arr["Q_se"],
        inv_magnification=inv_m,
        inv_magnification_se=inv_m_se,
        Q0=q0,
        Q0_se=q0_se,
        eta=eta,
        eta_se=eta_se,
        # the pitch's rim-shading correction needs the white image's shading
        image_scale=grid.scale if shading["applied"] else float("nan"),
        image_scale_se=grid.scale_se,
    )
    try:
        cam = fit_camera_model(measurements, g.priors())
    except ModelError as exc:
        partial["error"] = str(exc)
        raise PriorError(str(exc), _json_clean(partial)) from exc
    return cam, measurements, shading


def combine(
    frames: Iterable[FrameSummary],
    geometry: SweepGeometry,
    grid: MlaGrid,
    *,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Focus plane, camera parameters and uncertainties from the frame summaries.

    Raises :class:`CalibrationError` (with the per-frame results in
    ``partial``) when too few frames have corners, :class:`FocusNotDeterminedError`
    when the blur does not locate the focus plane, :class:`FocusAtEdgeError`
    when the focus plane is outside the sweep and :class:`PriorError` when the
    data-sheet values admit no thin-lens camera.
    """
    opts = options or CalibrationOptions()
    g = geometry
    frames = sorted(frames, key=lambda fs: fs.object_distance_mm)
    arr = _frame_arrays(frames)
    u = arr["object_distance_mm"]
    Lp, La = corner_size_mm(arr["Ls_px"], arr["Lr_px"], g.board.reference_gap_mm)
    D, delta = g.mla_pitch_mm, g.pixel_pitch_mm
    frames_out = []
    for k, fs in enumerate(frames):
        d = fs.to_dict(with_corners=True, with_esf=False)
        d["patch_size_px"] = fs.Q * D / delta
        d["Lp_mm_per_px"] = float(Lp[k])
        d["La_mm"] = float(La[k])
        frames_out.append(d)
    n_ref = sum(1 for fs in frames if fs.reference and fs.reference.get("found"))
    n_std = sum(1 for fs in frames if fs.standard and fs.standard.get("found"))
    warnings: list[str] = []
    partial: dict[str, Any] = {
        "format": "lfcal-result/1",
        "software": {"name": DISTRIBUTION, "version": software_version()},
        "inputs": g.to_dict(),
        "mla": grid.to_dict(),
        "frames": frames_out,
        "corners_found": {
            "standard_frames": n_std,
            "reference_frames": n_ref,
            "frames": len(frames),
        },
        "warnings": warnings,
    }
    good = np.isfinite(arr["Q"])
    if good.sum() < opts.min_frames:
        raise CalibrationError(
            f"a board corner was found in only {int(good.sum())} of {len(frames)} frames "
            f"(need {opts.min_frames}): {_why_no_corners(frames)}",
            _json_clean(partial),
        )
    if n_ref == 0:
        warnings.append(
            "the reference corner (2s, 0) was not found in any frame (outside the ROI?): "
            "no magnification, so the main-lens focal length and the rail zero come from "
            "their data-sheet values and tolerances; Lr, Lp and La are not available"
        )
    clip_note = clipped_edges_note(frames, g.max_count)
    for note in (white_clipped_note(grid, g.max_count), clip_note):
        if note:
            warnings.append(note)
    inv_m, inv_m_se = inverse_magnification(frames, g)
    observations = _observations(frames, g)
    # the defocus is set by the camera's Q(u), which the calibrated camera gives more precisely
    # than any one frame's disparity (near focus a frame's Q scatters most, and there the blur
    # depends most on it): the camera first, with a rough Q0 (its Q(u) barely depends on it),
    # then the defocus on the camera's Q(u), then the camera with the defocus's Q0
    rough = rough_focus(observations)
    if not np.isfinite(rough[0]):
        _defocus_or_raise(observations, g, partial, hint=clip_note)  # says why not
    cam, _, _ = _camera_or_raise(rough, arr, inv_m, inv_m_se, grid, g, partial)
    rails = np.array([fs.rail_mm for fs in frames])
    if n_ref:
        # the main images again with the camera's Q(u), not each corner's own (main_image)
        inv_m, inv_m_se = magnification_on_camera(cam, frames, rails, grid, g)
        cam, _, _ = _camera_or_raise(rough, arr, inv_m, inv_m_se, grid, g, partial)
    q_model, _ = cam.q_at_rail(rails)
    # the first camera's Q(u) rests on the rough Q0, which leaves the data sheet some say: a
    # second round, from the first defocus fit, when the camera with its Q0 moved Q(u)
    start: DefocusFit | None = None
    for _ in range(2):
        on_camera = _on_camera(observations, frames, q_model)
        defocus = _defocus_or_raise(on_camera, g, partial, start=start, hint=clip_note)
        focus = (defocus.Q0, defocus.Q0_se, defocus.kappa)
        cam, measurements, shading = _camera_or_raise(focus, arr, inv_m, inv_m_se, grid, g, partial)
        if n_ref:
            # the main images again on this camera's Q(u): the first placement's camera had
            # the rough Q0, under which the data sheet still had a say
            inv_m, inv_m_se = magnification_on_camera(cam, frames, rails, grid, g)
            cam, measurements, shading = _camera_or_raise(
                focus, arr, inv_m, inv_m_se, grid, g, partial
            )
        q_refined, _ = cam.q_at_rail(rails)
        if float(np.max(np.abs(q_refined - q_model))) <= REFIT_FRACTION * defocus.Q0_se:
            break
        q_model, start = q_refined, defocus
    # the jackknife over blocks of the sweep: the larger uncertainty of Q0 goes into the camera
    jackknifed = jackknife_defocus(on_camera, defocus, lens_pitch_px=g.lens_pitch_px)
    if jackknifed.Q0_se > defocus.Q0_se:
        focus = (jackknifed.Q0, jackknifed.Q0_se, jackknifed.kappa)
        cam, measurements, shading = _camera_or_raise(focus, arr, inv_m, inv_m_se, grid, g, partial)
    defocus = jackknifed
    priors = g.priors()
    corner_spread = corner_systematic(frames, measurements, priors, cam)
    main_image_spread = main_image_systematic(frames, measurements, priors, cam, grid, g)
    values, se = cam.values, cam.uncertainty
    rail = arr["rail_mm"]
    focus_rail = values["focus_rail_mm"]
    step = float(np.median(np.diff(np.sort(rail)))) if rail.size > 1 else 1.0
    if not (rail.min() + 0.5 * step <= focus_rail <= rail.max() - 0.5 * step):
        msg = (
            f"focus plane at the sweep edge or beyond it (Q = Q0 at rail {focus_rail:.1f} mm, "
            f"u = {values['focus_object_distance_mm']:.1f} mm; the sweep covers rail "
            f"{rail.min():.1f}..{rail.max():.1f} mm): extend the range"
        )
        partial["error"] = msg
        raise FocusAtEdgeError(msg, _json_clean(partial))
    # per frame, the calibrated camera's patch size at that distance beside the measured one;
    # the measured Q's standard error at the disparity's scatter about the camera, with a floor
    q_model, q_model_se = cam.q_at_rail(rail)
    for k, d in enumerate(frames_out):
        scale = float(cam.disparity_error_scale[k])
        if d.get("Q") is not None and d.get("Q_se") is not None and math.isfinite(scale):
            d["Q_se_fit"] = d["Q_se"]
            d["Q_se"] = float(math.hypot(d["Q_se"] * scale, Q_SYSTEMATIC_RELATIVE * d["Q"]))
        d["patch_size_measured_px"] = d["patch_size_px"]
        d["patch_size_px"] = float(q_model[k]) * D / delta
        d["patch_size_se_px"] = float(q_model_se[k]) * D / delta
    sweep = _sweep_estimate(cam, g)
    paper_route = paper_estimate(
        values["Q0"],
        se["Q0"],
        f=g.mla_focal_mm,
        D=D,
        delta=delta,
        focus_object_distance_mm=values["focus_object_distance_mm"],
        focus_se_mm=se["focus_object_distance_mm"],
    )
    paper = paper_focus(rail * g.direction, La)
    paper_est: Estimate | None = None
    paper_focus_dict: dict[str, Any] | None = None
    if paper is not None:
        paper_rail = paper.object_distance_mm * g.direction
        q_p = float(cam.q_at_rail(np.array([paper_rail]))[0][0])
        u_p = values["rail_zero_object_distance_mm"] + g.direction * paper_rail
        paper_est = paper_estimate(
            q_p, se["Q0"], f=g.mla_focal_mm, D=D, delta=delta, focus_object_distance_mm=u_p
        )
        paper_focus_dict = {
            "object_distance_mm": u_p,
            "rail_mm": paper_rail,
            "best_frame_index": frames[paper.best_index].index,
        }
    agreement = corner_agreement(frames)
    if agreement.get("consistent") is False:
        warnings.append(
            "the standard and the reference corner measure different Q in the same frames "
            f"(mean difference {agreement['mean_difference']:+.2e}, "
            f"{100 * agreement['relative_difference']:+.3f} %): the MLA may be tilted or the "
            "field curved, or the disparity reads differently at the two field positions "
            "(up to 0.11 % seen on a ray-traced camera with neither); Q is averaged over "
            "both corners"
        )
    priors_section, prior_warnings = _priors_section(cam, priors)
    warnings.extend(prior_warnings)
    if grid.shading is not None and not grid.shading.interior_consistent:
        warnings.append(_rim_shading_warning(grid.shading))
    jackknife_note = jackknife_warning(defocus, g.lens_pitch_px)
    if jackknife_note:
        warnings.append(jackknife_note)
    aperture_note = aperture_scale_warning(defocus.kappa)
    if aperture_note:
        warnings.append(aperture_note)
    frame_index = [fs.index for fs in frames]
    result = dict(partial)
    result.update(
        {
            "a_mm": sweep.a_mm,
            "b_mm": sweep.b_mm,
            "Q": sweep.Q,
            "patch_size_px": sweep.patch_size_px,
            "L_mm": values["L_mm"],
            "mla_focal_mm": values["mla_focal_mm"],
            "main_focal_mm": values["main_focal_mm"],
            "uncertainty": {
                "a_mm": sweep.a_se_mm,
                "b_mm": sweep.b_se_mm,
                "Q": sweep.Q_se,
                "patch_size_px": sweep.patch_size_se_px,
                "focus_object_distance_mm": se["focus_object_distance_mm"],
                "focus_rail_mm": se["focus_rail_mm"],
                "L_mm": se["L_mm"],
                "mla_focal_mm": se["mla_focal_mm"],
                "main_focal_mm": se["main_focal_mm"],
            },
            "focus": {
                "object_distance_mm": values["focus_object_distance_mm"],
                "rail_mm": focus_rail,
                "uncertainty_mm": se["focus_object_distance_mm"],
                "rail_uncertainty_mm": se["focus_rail_mm"],
                "Q0": values["Q0"],
                "Q0_se": se["Q0"],
                "method": (
                    "where Q(u) = Q0, Q0 from the geometric defocus (D/δ)|Q - Q0| fitted to the "
                    "edge-spread functions of every frame"
                ),
                "defocus_model": _defocus_dict(defocus),
                "paper_argmin_La": paper_focus_dict,
            },
            "priors": priors_section,
            "camera_model": {
                **cam.to_dict(),
                "corner_systematic": corner_spread,
                "main_image_systematic": main_image_spread,
            },
            "estimates": {
                "sweep": sweep.to_dict(),
                "paper_route": paper_route.to_dict(),
                "paper_argmin_La": None if paper_est is None else paper_est.to_dict(),
            },
            "corner_agreement": agreement,
            "shading_correction": shading,
            "curves": {
                "object_distance_mm": u.tolist(),
                "rail_mm": rail.tolist(),
                "inv_Q_model": cam.inv_q_model.tolist(),
                "inv_magnification_model": cam.inv_magnification_model.tolist(),
                "inv_magnification": inv_m.tolist(),
                "blur_diameter_px": [defocus.blur_px.get(i, float("nan")) for i in frame_index],
                "edge_spread_px": [defocus.spread_px.get(i, float("nan")) for i in frame_index],
                "edge_spread_model_px": [
                    defocus.model_spread_px.get(i, float("nan")) for i in frame_index
                ],
            },
        }
    )
    return CalibrationResult(_json_clean(result))
