"""The calibration summary that ``lfcal calibrate`` (and the demo) print.

Two tables: the calibrated quantities with their 1-sigma uncertainties (and,
when the archive carries a simulator's ``truth.json``, the truth and the
error), then the data-sheet priors against what the sweep measured. Any
renderer's truth file is read: the project's ``lfcal-truth/1`` and the flat
files of the independent renderers (``bench/crosscheck``, ``bench/mcsim``).
"""

from __future__ import annotations

from typing import Any

QUANTITIES: list[tuple[str, str, int, bool]] = [
    # label, result key (dotted), digits, relative error shown
    ("a (mm)", "a_mm", 5, True),
    ("b (mm)", "b_mm", 5, True),
    ("Q = b/a", "Q", 6, True),
    ("patch size p (px)", "patch_size_px", 4, False),
    ("focus plane u (mm)", "focus.object_distance_mm", 2, False),
    ("focus rail position (mm)", "focus.rail_mm", 2, False),
    ("main-lens focal F (mm)", "main_focal_mm", 4, True),
    ("microlens focal f (mm)", "mla_focal_mm", 5, True),
    ("lens to MLA L (mm)", "L_mm", 4, True),
    ("rail zero distance (mm)", "priors.rail_zero_object_distance_mm.calibrated", 3, False),
    ("lens pitch (px)", "mla.lens_pitch_px", 4, False),
    ("micro-image pitch (px)", "mla.image_pitch_px", 4, False),
    ("MLA rotation (deg)", "mla.rotation_deg", 4, False),
]

UNCERTAINTY_KEYS = {
    "a_mm": "uncertainty.a_mm",
    "b_mm": "uncertainty.b_mm",
    "Q": "uncertainty.Q",
    "patch_size_px": "uncertainty.patch_size_px",
    "focus.object_distance_mm": "focus.uncertainty_mm",
    "focus.rail_mm": "focus.rail_uncertainty_mm",
    "main_focal_mm": "uncertainty.main_focal_mm",
    "mla_focal_mm": "uncertainty.mla_focal_mm",
    "L_mm": "uncertainty.L_mm",
    "priors.rail_zero_object_distance_mm.calibrated": (
        "priors.rail_zero_object_distance_mm.uncertainty"
    ),
}

TRUTH_KEYS: dict[str, tuple[str, ...]] = {
    # result key -> where each renderer's truth.json keeps it (first found wins)
    "a_mm": ("a_mm", "a_f_mm"),
    "b_mm": ("b_mm",),
    "Q": ("Q", "Q_focus"),
    "patch_size_px": ("patch_size_px", "patch_size_px_focus"),
    "focus.object_distance_mm": ("focus.object_distance_mm", "u0_mm"),
    "focus.rail_mm": ("focus.rail_mm", "focus_rail_mm"),
    "main_focal_mm": ("optics.F_mm", "F_mm"),
    "mla_focal_mm": ("optics.f_mm", "f_mm"),
    "L_mm": ("optics.L_mm", "L_mm"),
    "priors.rail_zero_object_distance_mm.calibrated": (
        "rail.zero_object_distance_mm",
        "u_rail0_mm",
    ),
    "mla.lens_pitch_px": ("mla.lens_pitch_px", "lens_grid.pitch_px"),
    "mla.image_pitch_px": ("mla.image_pitch_px", "micro_image_grid.pitch_px"),
    "mla.rotation_deg": ("mla.rotation_deg", "theta_deg"),
}


def lookup(data: dict[str, Any] | None, dotted: str) -> Any:
    """``data["a"]["b"]`` for ``"a.b"``; None when any part is missing."""
    cur: Any = data
    for part in dotted.split("."):
        if not isinstance(cur, dict) or part not in cur:
            return None
        cur = cur[part]
    return cur


def truth_value(truth: dict[str, Any] | None, key: str) -> float | None:
    """The truth of a result key from any renderer's ``truth.json`` (None if absent)."""
    for candidate in TRUTH_KEYS.get(key, ()):
        value = lookup(truth, candidate)
        if isinstance(value, int | float):
            return float(value)
    return None


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows]
    return lines


def summary_table(result: dict[str, Any], truth: dict[str, Any] | None = None) -> str:
    """A readable summary of a result (and errors against a simulator truth)."""
    header = ["quantity", "value", "± 1σ"] + (["truth", "error"] if truth else [])
    rows = []
    for label, key, digits, relative in QUANTITIES:
        value = lookup(result, key)
        se = lookup(result, UNCERTAINTY_KEYS.get(key, "")) if key in UNCERTAINTY_KEYS else None
        row = [label, _fmt(value, digits), _fmt(se, digits) if se is not None else ""]
        if truth:
            t = truth_value(truth, key)
            row.append(_fmt(t, digits) if t is not None else "")
            if t is not None and isinstance(value, int | float):
                err = float(value) - t
                rel = f" ({100 * err / t:+.3f} %)" if relative and t else ""
                row.append(f"{err:+.{digits}f}{rel}")
            else:
                row.append("")
        rows.append(row)
    lines = _table(header, rows)
    priors = result.get("priors") or {}
    prior_rows = []
    for name, entry in priors.items():
        if not isinstance(entry, dict) or "datasheet" not in entry:
            continue
        prior_rows.append(
            [
                name,
                _fmt(entry.get("datasheet"), 4),
                f"± {_fmt(entry.get('tolerance'), 4)}",
                _fmt(entry.get("calibrated"), 4),
                f"± {_fmt(entry.get('uncertainty'), 4)}",
                f"{entry['z']:+.1f}" if isinstance(entry.get("z"), int | float) else "n/a",
                str(entry.get("determined_by", "")),
                "CONTRADICTED" if entry.get("contradicted") else "ok",
            ]
        )
    if prior_rows:
        lines.append("")
        lines += _table(
            ["prior", "data sheet", "tolerance", "calibrated", "± 1σ", "z", "from", "check"],
            prior_rows,
        )
    found = result.get("corners_found", {})
    lines.append(
        f"corners found: standard in {found.get('standard_frames')} and reference in "
        f"{found.get('reference_frames')} of {found.get('frames')} frames"
    )
    focus = result.get("focus") or {}
    model = focus.get("defocus_model") or {}
    if model:
        diffraction = model.get("diffraction_px") or 0.0
        optics = (
            f", wave optics: diffraction pattern {_fmt(diffraction, 2)} px"
            if diffraction > 0.0
            else ""
        )
        lines.append(
            f"focus: Q0 = {_fmt(model.get('Q0'), 6)} ± {_fmt(model.get('Q0_se'), 6)} from the "
            f"defocus of {model.get('frames')} frames (largest defocus "
            f"{_fmt(model.get('max_defocus_px'), 2)} px, static blur RMS "
            f"{_fmt(model.get('static_blur_rms_px'), 2)} px{optics})"
        )
    camera = result.get("camera_model") or {}
    check = camera.get("image_scale") or {}
    if check.get("measured") is not None:
        eta = (camera.get("values") or {}).get("eta")
        eta_shading = (result.get("shading_correction") or {}).get("eta")
        lines.append(
            f"b/L: the white image's (L+b)/L = {_fmt(check.get('measured'), 6)} "
            f"({'used' if check.get('used') else 'NOT used'}; the sweep alone says "
            f"{_fmt(check.get('sweep'), 6)} ± {_fmt(check.get('sweep_se'), 6)}, "
            f"z = {_fmt(check.get('z'), 1)}); disparity defocus bias eta = {_fmt(eta, 4)} "
            f"(shading predicts {_fmt(eta_shading, 4)})"
        )
    paper = focus.get("paper_argmin_La")
    if paper:
        lines.append(
            f"paper's argmin La (for comparison): u = {_fmt(paper.get('object_distance_mm'), 2)} mm"
        )
    route = (result.get("estimates") or {}).get("paper_route")
    if route:
        lines.append(
            f"paper's route b = f(1+Q0) with the data-sheet f (for comparison): "
            f"a = {_fmt(route.get('a_mm'), 5)} mm, b = {_fmt(route.get('b_mm'), 5)} mm"
        )
    for w in result.get("warnings", []):
        lines.append(f"warning: {w}")
    return "\n".join(lines)
