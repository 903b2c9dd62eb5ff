"""The calibration report: one self-contained, printable HTML page per calibration.

:func:`build_report` turns a result (``lfcal-result/1``), the sweep's manifest,
the archive's fingerprint and rendered crops into one HTML document: inline CSS
(with a print style), every plot and image embedded as a ``data:image/png``
URI, no script, nothing fetched. Sections: verdict, camera identity (model,
serial, firmware, temperature range during the sweep), station and board,
acceptance checks (priors against calibrated values with their tolerances,
PASS/FAIL), calibrated values with 1σ uncertainties, the focus, disparity and
residual plots, crops rendered with the calibrated and the designed patch size
with their artefact scores, software and archive checksum.

Priors: a result with a ``priors`` section (``{name: {datasheet, calibrated,
uncertainty, z, tolerance}}``) gets one check per prior -- FAIL when
``|datasheet − calibrated|`` exceeds the tolerance; an older result, without it,
lists the priors it used (``inputs``) as given. The consistency of the ESIF
estimate with the global fit, the number of frames with a corner and (when the
archive was re-read) the archive's integrity are checks too. The verdict is
PASS when every check passes.

:func:`render_crops` makes the rendered crops from a raw frame.
"""

from __future__ import annotations

import base64
import html
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .export_model import CalibratedCamera, ResultError
from .plots import stretch_to_uint8
from .raw_render import render_frame_with
from .report import disparity_plot, focus_plot, residual_plot
from .report_data import NOT_RECORDED, ArchiveDigest, CameraRecord, camera_record
from .version import DISTRIBUTION, software_version

MIN_CORNER_FRAMES = 5
"""Frames with a standard corner a calibration needs (``CalibrationOptions.min_frames``)."""

CROP_MAX_PX = 640


@dataclass(frozen=True)
class RenderedCrop:
    """A rendered crop for the report: label, PNG bytes and how it was made (px)."""

    label: str
    png: bytes
    patch_px: float
    render_patch_px: float
    score: float


@dataclass
class ReportInputs:
    """Everything a report shows besides the result itself.

    Attributes:
        manifest: the sweep's parsed ``sweep.json`` (None: the archive is not available).
        digest: the archive's fingerprint (None: not available).
        crops: rendered crops (calibrated and designed patch size).
        crops_note: why there are no (or fewer) crops.
        title: the page title (default: from the camera identity).
        job_id: the station job, when known.
        source: where the result came from (a path, ``job 12 of station.toml``).
    """

    manifest: dict[str, Any] | None = None
    digest: ArchiveDigest | None = None
    crops: list[RenderedCrop] = field(default_factory=list)
    crops_note: str | None = None
    title: str | None = None
    job_id: int | None = None
    source: str | None = None


@dataclass(frozen=True)
class Check:
    """One acceptance check: what, the measured value, the limit, and whether it passed."""

    name: str
    value: str
    limit: str
    passed: bool | None  # None: informative, no tolerance


# ----------------------------------------------------------------------- helpers


def _esc(value: Any) -> str:
    return html.escape(str(value), quote=True)


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    f = float(value)
    return f if math.isfinite(f) else None


def _fmt(value: Any, digits: int = 4) -> str:
    v = _num(value)
    return "n/a" if v is None else f"{v:.{digits}f}"


def _get(obj: Any, path: str) -> Any:
    for key in path.split("."):
        if not isinstance(obj, dict):
            return None
        obj = obj.get(key)
    return obj


def _img(png: bytes, alt: str, cls: str = "plot") -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img class="{cls}" alt="{_esc(alt)}" src="data:image/png;base64,{data}">'


def _table(header: Sequence[str] | None, rows: Sequence[Sequence[str]], cls: str = "") -> str:
    """An HTML table (``header`` None: no header row); cells are already HTML."""
    head = (
        ""
        if header is None
        else "<thead><tr>" + "".join(f"<th>{h}</th>" for h in header) + "</tr></thead>"
    )
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}">{head}<tbody>{body}</tbody></table>'


def _verdict(passed: bool | None) -> str:
    if passed is None:
        return '<span class="info">—</span>'
    return '<span class="pass">PASS</span>' if passed else '<span class="fail">FAIL</span>'


# ----------------------------------------------------------------------- checks

PRIOR_NAMES = {
    "main_focal_mm": ("main-lens focal length F", "mm"),
    "mla_focal_mm": ("microlens focal length f", "mm"),
    "rail_zero_object_distance_mm": ("rail zero object distance", "mm"),
    "L_mm": ("main lens to MLA L", "mm"),
}


def prior_checks(result: dict[str, Any]) -> list[Check]:
    """One check per entry of ``priors``: FAIL when ``|datasheet − calibrated| > tolerance``."""
    priors = result.get("priors")
    if not isinstance(priors, dict):
        return []
    out = []
    for key, entry in priors.items():
        if not isinstance(entry, dict):
            continue
        label, unit = PRIOR_NAMES.get(key, (key, ""))
        sheet, cal = _num(entry.get("datasheet")), _num(entry.get("calibrated"))
        tol, z = _num(entry.get("tolerance")), _num(entry.get("z"))
        unc = _num(entry.get("uncertainty"))
        value = f"{_fmt(cal)} ± {_fmt(unc)} {unit}".strip()
        if sheet is not None and cal is not None:
            value += f" (data sheet {_fmt(sheet)}, Δ {cal - sheet:+.4f}"
            value += f", z {z:+.2f})" if z is not None else ")"
        passed: bool | None = None
        limit = "no tolerance given"
        if tol is not None and sheet is not None and cal is not None:
            if isinstance(entry.get("contradicted"), bool):
                # the calibration's own verdict: off by more than the tolerance plus 3 sigma
                passed = not entry["contradicted"]
                limit = f"|data sheet − calibrated| ≤ {_fmt(tol)} {unit} + 3σ".strip()
            else:
                passed = abs(sheet - cal) <= tol
                limit = f"|data sheet − calibrated| ≤ {_fmt(tol)} {unit}".strip()
            if entry.get("determined_by") == "prior":
                value += "; the sweep could not fix it: the data sheet was used"
        out.append(Check(f"prior: {label}", value, limit, passed))
    return out


def result_checks(result: dict[str, Any], digest: ArchiveDigest | None) -> list[Check]:
    """The checks every result has: corners found, consistency, archive integrity."""
    checks = prior_checks(result)
    found = result.get("corners_found") or {}
    n_std = int(found.get("standard_frames") or 0)
    checks.append(
        Check(
            "frames with the standard corner",
            f"{n_std} of {found.get('frames', '?')}",
            f"≥ {MIN_CORNER_FRAMES}",
            n_std >= MIN_CORNER_FRAMES,
        )
    )
    agree = result.get("corner_agreement")
    if isinstance(agree, dict) and isinstance(agree.get("consistent"), bool):
        checks.append(
            Check(
                "standard and reference corner measure the same Q",
                f"mean difference {_fmt(agree.get('relative_difference', 0.0) * 100, 4)} % over "
                f"{agree.get('frames')} frames (RMS z {_fmt(agree.get('rms_z'), 2)})",
                "no significant difference above 0.02 %",
                bool(agree["consistent"]),
            )
        )
    cons = result.get("consistency")
    if isinstance(cons, dict) and "consistent" in cons:
        checks.append(
            Check(
                "ESIF estimate against the global fit",
                f"b differs by {_fmt(cons.get('b_difference_mm'), 5)} mm "
                f"({_fmt(cons.get('b_sigma'), 1)} σ), a by {_fmt(cons.get('a_difference_mm'), 4)} "
                f"mm ({_fmt(cons.get('a_sigma'), 1)} σ)",
                "each within 3 σ, or b within 0.05 % and a within 0.25 %",
                bool(cons["consistent"]),
            )
        )
    if digest is not None and digest.verified is not None:
        problems = "; ".join(digest.problems[:3]) or "every file matches its recorded SHA-256"
        checks.append(Check("archive integrity", problems, "all checksums match", digest.verified))
    return checks


def overall(checks: Sequence[Check]) -> bool:
    """PASS when no check failed (informative checks do not count)."""
    return all(c.passed is not False for c in checks)


# ----------------------------------------------------------------------- crops


def _crop_png(image: NDArray[np.float32], max_px: int = CROP_MAX_PX) -> bytes:
    h, w = image.shape
    cw, ch = min(w, max_px), min(h, max_px)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    crop = stretch_to_uint8(image[y0 : y0 + ch, x0 : x0 + cw])
    ok, buf = cv2.imencode(".png", crop)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def render_crops(
    raw: NDArray[Any],
    camera: CalibratedCamera,
    *,
    designed_px: float | None,
    white: NDArray[Any] | None = None,
) -> list[RenderedCrop]:
    """Central crops (at most 640 px) of ``raw`` rendered with the calibrated patch size and,
    when ``designed_px`` is known, the designed one, each with its artefact score."""
    choices = [("calibrated p", camera.patch_px)]
    if designed_px is not None:
        choices.append(("designed p", float(designed_px)))
    n = max(4, int(round(camera.seamless_patch(camera.patch_px))))
    out = []
    for label, p in choices:
        r = render_frame_with(raw, camera, p, white=white, tile_px=n)
        out.append(RenderedCrop(label, _crop_png(r.image), r.patch_px, r.render_patch_px, r.score))
    return out


# ----------------------------------------------------------------------- sections


def _identity_rows(rec: CameraRecord, manifest: dict[str, Any] | None) -> list[list[str]]:
    cam = (manifest or {}).get("camera") or {}
    rng = rec.temperature_c
    temp = (
        NOT_RECORDED
        if rng is None
        else f"{rng[0]:.1f} – {rng[1]:.1f} °C ({rec.frames_with_temperature} of {rec.frames} frames)"
    )
    expo = (
        NOT_RECORDED
        if rec.exposure_us is None
        else f"{rec.exposure_us[0]:g} – {rec.exposure_us[1]:g} µs"
    )
    gain = NOT_RECORDED if rec.gain_db is None else f"{rec.gain_db[0]:g} – {rec.gain_db[1]:g} dB"
    sensor = (
        f"{cam.get('width', '?')} × {cam.get('height', '?')} px, "
        f"{cam.get('pixel_pitch_mm', '?')} mm pixels, {cam.get('bit_depth', '?')} bit"
        if cam
        else NOT_RECORDED
    )
    return [
        ["vendor", _esc(rec.vendor)],
        ["model", _esc(rec.model)],
        ["serial number", _esc(rec.serial)],
        ["firmware", _esc(rec.firmware)],
        ["sensor (frames)", _esc(sensor)],
        ["temperature during the sweep", _esc(temp)],
        ["exposure", _esc(expo)],
        ["gain", _esc(gain)],
    ]


def _station_rows(result: dict[str, Any], manifest: dict[str, Any] | None) -> list[list[str]]:
    m = manifest or {}
    inputs = result.get("inputs") or {}
    board = inputs.get("board") or m.get("board") or {}
    rail = inputs.get("rail") or m.get("rail") or {}
    station = m.get("station") or {}
    sweep = station.get("sweep") or {}
    frames = result.get("frames") or []
    us = [_num(f.get("object_distance_mm")) for f in frames]
    us_ok = [u for u in us if u is not None]
    span = f"{min(us_ok):.2f} – {max(us_ok):.2f} mm, {len(frames)} frames" if us_ok else "n/a"
    rows = [
        ["job", _esc(station.get("job_id", _get(result, "station.job_id") or "n/a"))],
        [
            "board",
            _esc(
                f"double checkerboard, squares {board.get('square_mm', '?')} mm, reference gap "
                f"Cr {board.get('reference_gap_mm', '?')} mm"
            ),
        ],
        [
            "rail",
            _esc(
                f"u = {rail.get('zero_object_distance_mm', '?')} mm "
                f"{'+' if rail.get('direction', 1) == 1 else '−'} rail position"
            ),
        ],
        ["object distances of the sweep", _esc(span)],
    ]
    if sweep:
        rows.append(["sweep request", _esc(", ".join(f"{k} {v}" for k, v in sweep.items()))])
    simulated = m.get("simulated")
    if simulated:
        what = simulated.get("preset", simulated) if isinstance(simulated, dict) else simulated
        rows.append(["simulated camera", _esc(f"preset {what}")])
    return rows


def _value_rows(result: dict[str, Any]) -> list[list[str]]:
    unc = result.get("uncertainty") or {}
    focus = result.get("focus") or {}
    mla = result.get("mla") or {}
    u0, u0_se = focus.get("object_distance_mm"), focus.get("uncertainty_mm")
    Row = tuple[str, str, Any, Any, str, int]
    rows: list[Row] = [
        ("a (virtual image in focus, in front of the MLA)", "a", result.get("a_mm"),
         unc.get("a_mm"), "mm", 5),
        ("b (MLA to sensor)", "b", result.get("b_mm"), unc.get("b_mm"), "mm", 5),
        ("Q = b/a", "Q", result.get("Q"), unc.get("Q"), "", 6),
        ("patch size", "p", result.get("patch_size_px"), unc.get("patch_size_px"), "px", 4),
        ("focus plane: object distance", "u0", u0, u0_se, "mm", 3),
        ("focus plane: rail position", "", focus.get("rail_mm"), u0_se, "mm", 3),
        ("lens pitch (data sheet D/δ)", "D/δ", mla.get("lens_pitch_px"), None, "px", 4),
        ("micro-image pitch", "μ", mla.get("image_pitch_px"), None, "px", 4),
        ("MLA rotation", "θ", mla.get("rotation_deg"), None, "deg", 4),
        ("MLA lattice residual (RMS)", "", mla.get("residual_rms_px"), None, "px", 4),
    ]  # fmt: skip
    try:
        cam = CalibratedCamera.from_result(result)
        L_unc = _num(_get(result, "priors.L_mm.uncertainty"))
        if L_unc is None and cam.L_source.startswith("estimates.global"):
            L_unc = _num(_get(result, "estimates.global.L_se_mm"))
        rows.insert(5, (f"main lens to MLA ({cam.L_source})", "L", cam.L, L_unc, "mm", 4))
    except ResultError:
        pass
    return [
        [
            _esc(name),
            _esc(sym),
            _fmt(v, d),
            "" if _num(u) is None else "± " + _fmt(u, d),
            _esc(unit),
        ]
        for name, sym, v, u, unit, d in rows
    ]


def _prior_rows(result: dict[str, Any]) -> list[list[str]]:
    """Priors against calibrated values (``priors``), or the priors used as given (``inputs``)."""
    priors = result.get("priors")
    if isinstance(priors, dict) and priors:
        rows = []
        for key, e in priors.items():
            if not isinstance(e, dict):
                continue
            label, unit = PRIOR_NAMES.get(key, (key, ""))
            sheet, cal, tol = (
                _num(e.get("datasheet")),
                _num(e.get("calibrated")),
                _num(e.get("tolerance")),
            )
            passed = (
                None if tol is None or sheet is None or cal is None else abs(sheet - cal) <= tol
            )
            rows.append(
                [
                    _esc(label),
                    _fmt(sheet),
                    _fmt(cal)
                    + (
                        ""
                        if _num(e.get("uncertainty")) is None
                        else " ± " + _fmt(e.get("uncertainty"))
                    ),
                    _fmt(e.get("z"), 2),
                    _fmt(tol),
                    _esc(unit),
                    _verdict(passed),
                ]
            )
        return rows
    inputs = result.get("inputs") or {}
    optics, camera, rail = (inputs.get(k) or {} for k in ("optics", "camera", "rail"))
    pp = camera.get("principal_point_px") or [None, None]
    given = [
        ("main-lens focal length F", optics.get("main_focal_mm"), "mm"),
        ("microlens focal length f", optics.get("mla_focal_mm"), "mm"),
        ("microlens pitch D", optics.get("mla_pitch_mm"), "mm"),
        ("pixel pitch δ", camera.get("pixel_pitch_mm"), "mm"),
        ("principal point x", pp[0], "px"),
        ("principal point y", pp[1], "px"),
        ("rail zero object distance", rail.get("zero_object_distance_mm"), "mm"),
    ]
    return [
        [_esc(n), _fmt(v), "used as given", "", "", _esc(u), _verdict(None)] for n, v, u in given
    ]


CSS = """
body { font-family: "DejaVu Sans", system-ui, sans-serif; color: #1b1b1b; margin: 2em auto;
       max-width: 1000px; padding: 0 1.5em; font-size: 11pt; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { font-size: 1.2em; margin-top: 1.6em;
     border-bottom: 2px solid #263238; padding-bottom: 0.15em; }
.sub { color: #555; margin-top: 0; }
table { border-collapse: collapse; width: 100%; margin: 0.5em 0; }
td, th { border-bottom: 1px solid #ddd; padding: 0.25em 0.5em; text-align: left; vertical-align: top; }
th { background: #eceff1; }
td:nth-child(n+3) { font-family: "DejaVu Sans Mono", monospace; }
table.kv td:first-child { width: 16em; color: #444; }
table.kv td:nth-child(2) { font-family: inherit; }
.pass { color: #fff; background: #2e7d32; padding: 0.05em 0.5em; border-radius: 0.3em; font-weight: bold; }
.fail { color: #fff; background: #c62828; padding: 0.05em 0.5em; border-radius: 0.3em; font-weight: bold; }
.info { color: #777; }
.verdict { font-size: 1.3em; margin: 0.6em 0; }
img.plot { width: 100%; max-width: 900px; display: block; margin: 0.6em auto; }
.crops { display: flex; gap: 1em; flex-wrap: wrap; }
.crops figure { margin: 0; flex: 1 1 45%; }
.crops img { width: 100%; image-rendering: pixelated; border: 1px solid #ccc; }
figcaption { font-size: 0.9em; color: #444; }
.mono { font-family: "DejaVu Sans Mono", monospace; word-break: break-all; }
footer { margin-top: 2em; color: #666; font-size: 0.85em; }
@media print {
  body { margin: 0; max-width: none; font-size: 10pt; }
  h2 { break-after: avoid; } table, figure, img.plot { break-inside: avoid; }
  .pagebreak { break-before: page; }
}
"""


def build_report(result: dict[str, Any], inputs: ReportInputs | None = None) -> str:
    """The report of ``result`` as one self-contained HTML document (see the module docstring)."""
    inp = inputs or ReportInputs()
    rec = camera_record(inp.manifest)
    checks = result_checks(result, inp.digest)
    passed = overall(checks)
    model = rec.model if rec.model != NOT_RECORDED else "camera"
    serial = f" serial {rec.serial}" if rec.serial != NOT_RECORDED else ""
    title = inp.title or f"Calibration report — {model}{serial}"
    when = time.strftime("%Y-%m-%d %H:%M:%S %Z", time.localtime())
    software = result.get("software") or {}
    parts = [
        "<!doctype html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{_esc(title)}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<h1>{_esc(title)}</h1>",
        f'<p class="sub">focused plenoptic camera, ESIF calibration; report made {_esc(when)}'
        + (f"; {_esc(inp.source)}" if inp.source else "")
        + "</p>",
        f'<p class="verdict" id="verdict">Verdict: {_verdict(passed)} '
        f"({sum(c.passed is True for c in checks)} of "
        f"{sum(c.passed is not None for c in checks)} checks passed)</p>",
        "<h2>Camera</h2>",
        _table(None, _identity_rows(rec, inp.manifest), "kv"),
        "<h2>Station and board</h2>",
        _table(None, _station_rows(result, inp.manifest), "kv"),
        "<h2>Acceptance checks</h2>",
        _table(
            ["check", "value", "tolerance", "result"],
            [[_esc(c.name), _esc(c.value), _esc(c.limit), _verdict(c.passed)] for c in checks],
            "checks",
        ),
        "<h2>Priors and calibrated values</h2>",
        _table(
            ["prior", "data sheet", "calibrated", "z", "tolerance", "unit", "result"],
            _prior_rows(result),
            "priors",
        ),
        _table(["quantity", "symbol", "value", "1σ", "unit"], _value_rows(result), "values"),
    ]
    warnings = result.get("warnings") or []
    if warnings:
        parts.append("<p>Warnings of the calibration:</p><ul>")
        parts += [f"<li>{_esc(w)}</li>" for w in warnings]
        parts.append("</ul>")
    parts += [
        '<h2 class="pagebreak">Focus plane</h2>',
        "<p>The focus plane is where the blur model fitted to the edge-spread widths of every "
        "frame has its minimum (bottom panel); the paper's argmin La is shown for comparison.</p>",
        _img(focus_plot(result), "focus plot: La(u), corner sizes, edge widths and blur model"),
        "<h2>Disparity</h2>",
        _img(disparity_plot(result), "disparity plot: Q(u) and the global model"),
        "<h2>Residuals</h2>",
        _img(residual_plot(result), "residuals of Q and of the edge widths"),
        '<h2 class="pagebreak">Rendered images</h2>',
    ]
    if inp.crops:
        parts.append(
            "<p>Georgiev–Lumsdaine patch rendering of the frame nearest the focus plane. "
            "Artefact score: seam discontinuity relative to the inside of the patches "
            '(about 1 is seam-free; larger is worse).</p><div class="crops">'
        )
        for c in inp.crops:
            cap = (
                f"{c.label}: p = {c.patch_px:.3f} px (rendering patch {c.render_patch_px:.3f} px), "
                f"artefact score {c.score:.2f}"
            )
            parts.append(
                f"<figure>{_img(c.png, cap, 'crop')}<figcaption>{_esc(cap)}</figcaption></figure>"
            )
        parts.append("</div>")
    if inp.crops_note:
        parts.append(f'<p class="info">{_esc(inp.crops_note)}</p>')
    digest = inp.digest
    if digest is None:
        archive = [["archive", "not available"]]
    else:
        state = {
            True: "verified: every file re-read",
            False: "PROBLEMS: " + "; ".join(digest.problems[:5]),
            None: "as recorded in the manifest (files not re-read)",
        }[digest.verified]
        archive = [
            [
                "archive checksum (SHA-256 over the manifest and the frame checksums)",
                f'<span class="mono">{_esc(digest.sha256)}</span>',
            ],
            ["files covered", _esc(f"{digest.files} (white image and frames)")],
            ["checksums", _esc(state)],
        ]
    parts += [
        "<h2>Software and data</h2>",
        _table(
            None,
            [
                [
                    "calibrated by",
                    _esc(f"{software.get('name', '?')} {software.get('version', '?')}"),
                ],
                ["report by", _esc(f"{DISTRIBUTION} {software_version()}")],
                ["result format", _esc(result.get("format", "?"))],
                *archive,
            ],
            "kv",
        ),
        "<footer>Units: millimetres unless marked px; uncertainties are 1σ. Symbols as in the "
        "station's OPTICS.md: F main-lens focal length, f microlens focal length, D microlens "
        "pitch, δ pixel pitch, b MLA to sensor, L main lens to MLA, a = b/Q, p = Q·D/δ.</footer>",
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


__all__ = [
    "Check",
    "RenderedCrop",
    "ReportInputs",
    "build_report",
    "overall",
    "prior_checks",
    "render_crops",
    "result_checks",
]
