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
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .camera_model import (
    CameraModelFit,
    ModelError,
    SweepMeasurements,
    fit_camera_model,
)
from .defocus import (
    DefocusFit,
    DefocusNotDetermined,
    EdgeObservation,
    blur_model_warning,
    fit_defocus,
    jackknife_defocus,
    jackknife_warning,
    rough_focus,
)
from .edge_spread import BinnedEsf
from .focus import corner_size_mm, paper_focus
from .lattice_scale import replace_profiles
from .mla_grid import MlaGrid
from .parameters import Estimate, paper_estimate
from .result_notes import (
    aperture_scale_warning,
    clipped_edges_note,
    corner_disagreement_note,
    priors_section,
    rim_shading_warning,
    vignetting_note,
    white_clipped_note,
    why_no_corners,
)
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
        "Q0_se_kernel": d.Q0_se_kernel,
        "Q0_other_kernel": d.Q0_other_kernel,
        "corners": d.corners,
        "Q0_se_jackknife": d.Q0_se_jackknife,
        "jackknife_Q0": list(d.jackknife_Q0),
        "jackknife_consistent": d.jackknife_consistent,
        "aperture_scale": d.kappa,
        "aperture_shape_box": d.shape_box,
        "diffraction_px": d.diffraction_px,
        "rim_aperture_scale": d.rim_kappa,
        "geometric_excluded": d.geometric_excluded,
        "chi2_reduced": d.chi2_reduced,
        "static_blur_rms_px": d.static_rms_px,
        "max_defocus_px": d.max_blur_px,
        "frames": d.frames,
    }


def _defocus_or_raise(
    observations: list[EdgeObservation],
    g: SweepGeometry,
    partial: dict[str, Any],
    start: DefocusFit | None = None,
    *,
    grid: MlaGrid | None = None,
    hint: str = "",
) -> DefocusFit:
    """The whole-sweep defocus fit (from ``start``'s parameters when given; with ``grid``'s
    white-image rims, :mod:`calibration.white_rim`);
    :class:`FocusNotDeterminedError` with ``partial`` (``hint`` appended to its message)."""
    theta0 = (
        None if start is None else (start.Q0, start.kappa, start.shape_box, start.diffraction_px)
    )
    try:
        defocus = fit_defocus(
            observations,
            lens_pitch_px=g.lens_pitch_px,
            start=theta0,
            rim=None if grid is None else grid.rim,
            rim_q=float("nan") if grid is None else grid.scale - 1.0,
        )
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


@dataclass
class _SweepFit:
    """The camera and the defocus fitted together, as :func:`_fit_sweep` leaves them."""

    cam: CameraModelFit
    measurements: SweepMeasurements
    shading: dict[str, Any]
    defocus: DefocusFit
    inv_m: NDArray[np.float64]


def _start_result(
    frames: list[FrameSummary],
    g: SweepGeometry,
    grid: MlaGrid,
    La: NDArray[np.float64],
    Lp: NDArray[np.float64],
) -> dict[str, Any]:
    """What every result holds, the partial one of a refusal too: the inputs, the MLA,
    every frame (with its measured patch size and corner sizes), the corners found and
    the (so far empty) warnings."""
    frames_out = []
    for k, fs in enumerate(frames):
        d = fs.to_dict(with_corners=True, with_esf=False)
        d["patch_size_px"] = fs.Q * g.mla_pitch_mm / g.pixel_pitch_mm
        d["Lp_mm_per_px"] = float(Lp[k])
        d["La_mm"] = float(La[k])
        frames_out.append(d)
    n_ref = sum(1 for fs in frames if fs.reference and fs.reference.get("found"))
    n_std = sum(1 for fs in frames if fs.standard and fs.standard.get("found"))
    return {
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
        "warnings": [],
    }


def _fit_sweep(
    frames: list[FrameSummary],
    arr: dict[str, NDArray[np.float64]],
    g: SweepGeometry,
    grid: MlaGrid,
    partial: dict[str, Any],
    *,
    with_reference: bool,
    clip_hint: str,
) -> _SweepFit:
    """The camera and the defocus from the whole sweep (raises what :func:`combine` names).

    The defocus is set by the camera's Q(u), which the calibrated camera gives more
    precisely than any one frame's disparity (near focus a frame's Q scatters most, and
    there the blur depends most on it): the camera first, with a rough Q0 (its Q(u) barely
    depends on it), then the defocus on the camera's Q(u), then the camera with the
    defocus's Q0 -- twice when that camera moved Q(u) by more than :data:`REFIT_FRACTION`
    of Q0's σ. With the reference corner, the main images are placed again on each
    camera's Q(u) (:func:`~calibration.two_corners.magnification_on_camera`). Last, the
    jackknife over blocks of the sweep: its larger uncertainty of Q0 goes into the camera.
    """
    inv_m, inv_m_se = inverse_magnification(frames, g)
    observations = _observations(frames, g)
    rough = rough_focus(observations)
    if not np.isfinite(rough[0]):
        _defocus_or_raise(observations, g, partial, hint=clip_hint)  # says why not
    rails = arr["rail_mm"]

    def camera(
        focus: tuple[float, float, float],
    ) -> tuple[CameraModelFit, SweepMeasurements, dict[str, Any]]:
        nonlocal inv_m, inv_m_se
        fitted = _camera_or_raise(focus, arr, inv_m, inv_m_se, grid, g, partial)
        if with_reference:
            # the main images again on this camera's Q(u), not each corner's own: the
            # first placement's camera had a rougher Q0, under which the data sheet had a say
            inv_m, inv_m_se = magnification_on_camera(
                fitted[0], frames, rails, grid, g, shading_eta=fitted[1].eta
            )
            fitted = _camera_or_raise(focus, arr, inv_m, inv_m_se, grid, g, partial)
        return fitted

    cam, _, _ = camera(rough)
    q_model, _ = cam.q_at_rail(rails)
    start: DefocusFit | None = None
    for _ in range(2):
        on_camera = _on_camera(observations, frames, q_model)
        defocus = _defocus_or_raise(on_camera, g, partial, start=start, grid=grid, hint=clip_hint)
        cam, measurements, shading = camera((defocus.Q0, defocus.Q0_se, defocus.kappa))
        q_refined, _ = cam.q_at_rail(rails)
        if float(np.max(np.abs(q_refined - q_model))) <= REFIT_FRACTION * defocus.Q0_se:
            break
        q_model, start = q_refined, defocus
    jackknifed = jackknife_defocus(on_camera, defocus, lens_pitch_px=g.lens_pitch_px)
    if jackknifed.Q0_se > defocus.Q0_se:
        focus = (jackknifed.Q0, jackknifed.Q0_se, jackknifed.kappa)
        cam, measurements, shading = _camera_or_raise(focus, arr, inv_m, inv_m_se, grid, g, partial)
    return _SweepFit(cam, measurements, shading, jackknifed, inv_m)


def _check_focus_in_sweep(
    cam: CameraModelFit, rail: NDArray[np.float64], partial: dict[str, Any]
) -> None:
    """:class:`FocusAtEdgeError` when Q = Q0 lies within half a step of the sweep's ends or
    beyond them."""
    values = cam.values
    focus_rail = values["focus_rail_mm"]
    step = float(np.median(np.diff(np.sort(rail)))) if rail.size > 1 else 1.0
    if rail.min() + 0.5 * step <= focus_rail <= rail.max() - 0.5 * step:
        return
    msg = (
        f"focus plane at the sweep edge or beyond it (Q = Q0 at rail {focus_rail:.1f} mm, "
        f"u = {values['focus_object_distance_mm']:.1f} mm; the sweep covers rail "
        f"{rail.min():.1f}..{rail.max():.1f} mm): extend the range"
    )
    partial["error"] = msg
    raise FocusAtEdgeError(msg, _json_clean(partial))


def _frames_on_camera(
    frames_out: list[dict[str, Any]],
    cam: CameraModelFit,
    rail: NDArray[np.float64],
    g: SweepGeometry,
) -> None:
    """Per frame, the calibrated camera's patch size at that distance beside the measured
    one, and the measured Q's standard error at the disparity's scatter about the camera
    with a floor of :data:`Q_SYSTEMATIC_RELATIVE` (the fit's own kept as ``Q_se_fit``)."""
    D, delta = g.mla_pitch_mm, g.pixel_pitch_mm
    q_model, q_model_se = cam.q_at_rail(rail)
    for k, d in enumerate(frames_out):
        scale = float(cam.disparity_error_scale[k])
        if d.get("Q") is not None and d.get("Q_se") is not None and math.isfinite(scale):
            d["Q_se_fit"] = d["Q_se"]
            d["Q_se"] = float(math.hypot(d["Q_se"] * scale, Q_SYSTEMATIC_RELATIVE * d["Q"]))
        d["patch_size_measured_px"] = d["patch_size_px"]
        d["patch_size_px"] = float(q_model[k]) * D / delta
        d["patch_size_se_px"] = float(q_model_se[k]) * D / delta


def _paper_argmin(
    frames: list[FrameSummary],
    cam: CameraModelFit,
    g: SweepGeometry,
    rail: NDArray[np.float64],
    La: NDArray[np.float64],
) -> tuple[Estimate | None, dict[str, Any] | None]:
    """The paper's focus plane (``argmin La``, Eq. 7-9) and the estimate from the camera's
    Q there, for comparison; (None, None) when La has no minimum in the sweep."""
    paper = paper_focus(rail * g.direction, La)
    if paper is None:
        return None, None
    values, se = cam.values, cam.uncertainty
    paper_rail = paper.object_distance_mm * g.direction
    q_p = float(cam.q_at_rail(np.array([paper_rail]))[0][0])
    u_p = values["rail_zero_object_distance_mm"] + g.direction * paper_rail
    estimate = paper_estimate(
        q_p,
        se["Q0"],
        f=g.mla_focal_mm,
        D=g.mla_pitch_mm,
        delta=g.pixel_pitch_mm,
        focus_object_distance_mm=u_p,
    )
    where = {
        "object_distance_mm": u_p,
        "rail_mm": paper_rail,
        "best_frame_index": frames[paper.best_index].index,
    }
    return estimate, where


def _fit_warnings(fit: _SweepFit, grid: MlaGrid, g: SweepGeometry) -> list[str]:
    """The warnings about the fit itself: rim-blurred shading, an unstable jackknife, blur
    models that disagree, an implausible aperture scale."""
    notes = []
    if grid.shading is not None and not grid.shading.interior_consistent:
        notes.append(rim_shading_warning(grid.shading))
    notes.append(jackknife_warning(fit.defocus, g.lens_pitch_px) or "")
    notes.append(blur_model_warning(fit.defocus) or "")
    notes.append(aperture_scale_warning(fit.defocus.kappa) or "")
    return [n for n in notes if n]


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
    Lp, La = corner_size_mm(arr["Ls_px"], arr["Lr_px"], g.board.reference_gap_mm)
    partial = _start_result(frames, g, grid, La, Lp)
    warnings: list[str] = partial["warnings"]
    good = np.isfinite(arr["Q"])
    if good.sum() < opts.min_frames:
        raise CalibrationError(
            f"a board corner was found in only {int(good.sum())} of {len(frames)} frames "
            f"(need {opts.min_frames}): {why_no_corners(frames)}",
            _json_clean(partial),
        )
    with_reference = partial["corners_found"]["reference_frames"] > 0
    if not with_reference:
        warnings.append(
            "the reference corner (2s, 0) was not found in any frame (outside the ROI?): "
            "no magnification, so the main-lens focal length and the rail zero come from "
            "their data-sheet values and tolerances; Lr, Lp and La are not available"
        )
    clip_note = clipped_edges_note(frames, g.max_count)
    white_notes = (white_clipped_note(grid, g.max_count), vignetting_note(grid, frames), clip_note)
    warnings.extend(n for n in white_notes if n)
    fit = _fit_sweep(
        frames, arr, g, grid, partial, with_reference=with_reference, clip_hint=clip_note
    )
    cam, defocus = fit.cam, fit.defocus
    priors = g.priors()
    corner_spread = corner_systematic(frames, fit.measurements, priors, cam)
    main_image_spread = main_image_systematic(frames, fit.measurements, priors, cam, grid, g)
    values, se = cam.values, cam.uncertainty
    rail = arr["rail_mm"]
    _check_focus_in_sweep(cam, rail, partial)
    _frames_on_camera(partial["frames"], cam, rail, g)
    sweep = _sweep_estimate(cam, g)
    paper_route = paper_estimate(
        values["Q0"],
        se["Q0"],
        f=g.mla_focal_mm,
        D=g.mla_pitch_mm,
        delta=g.pixel_pitch_mm,
        focus_object_distance_mm=values["focus_object_distance_mm"],
        focus_se_mm=se["focus_object_distance_mm"],
    )
    paper_est, paper_focus_dict = _paper_argmin(frames, cam, g, rail, La)
    agreement = corner_agreement(frames)
    priors_out, prior_warnings = priors_section(cam, priors)
    for note in (
        corner_disagreement_note(agreement),
        *prior_warnings,
        *_fit_warnings(fit, grid, g),
    ):
        if note:
            warnings.append(note)
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
                "rail_mm": values["focus_rail_mm"],
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
            "priors": priors_out,
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
            "shading_correction": fit.shading,
            "curves": {
                "object_distance_mm": arr["object_distance_mm"].tolist(),
                "rail_mm": rail.tolist(),
                "inv_Q_model": cam.inv_q_model.tolist(),
                "inv_magnification_model": cam.inv_magnification_model.tolist(),
                "inv_magnification": fit.inv_m.tolist(),
                "blur_diameter_px": [defocus.blur_px.get(i, float("nan")) for i in frame_index],
                "edge_spread_px": [defocus.spread_px.get(i, float("nan")) for i in frame_index],
                "edge_spread_model_px": [
                    defocus.model_spread_px.get(i, float("nan")) for i in frame_index
                ],
            },
        }
    )
    return CalibrationResult(_json_clean(result))
