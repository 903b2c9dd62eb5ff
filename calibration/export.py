"""Exporting a calibration (``lfcal-result/1``) to formats other tools read, and importing ours.

Formats (:data:`FORMATS`), each ``export_text(result, FORMAT) -> str``:

``lfcal``
    The result itself, canonical JSON, validated against the published JSON
    Schema (``calibration/schemas/lfcal-result-1.schema.json``, package data;
    :func:`schema`, :func:`validate_result`). :func:`import_result` reads it
    back: export → import is lossless (the same dict).
``compote``
    The intrinsics file of libpleno / COMPOTE (``intrinsics.js``, read by their
    ``PlenopticCameraConfig``), with the structure of COMPOTE's published
    example ``examples/config/intrinsics.js`` (github.com/comsee-research/compote):
    every value a decimal string (``%.17g``), vectors and matrices as nested
    lists in Eigen's column-major order (a 3-vector is ``[[x, y, z]]``, a
    rotation matrix a list of its *columns*). The mapping is :data:`COMPOTE_MAPPING`
    (also in the README).
``csv``, ``toml``
    A plain summary: one row (CSV) or key (TOML) per quantity with its symbol,
    value, 1σ uncertainty, unit and where it comes from (:func:`summary_rows`).

All functions take the result as a dict; :class:`ExportError` (a ``ValueError``)
names what is wrong in one line.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

import numpy as np

from .export_model import CalibratedCamera, ResultError

FORMATS = ("lfcal", "compote", "csv", "toml")
"""The export formats (``lfcal export --format``)."""

SCHEMA_RESOURCE = "schemas/lfcal-result-1.schema.json"

COMPOTE_MAPPING: tuple[tuple[str, str], ...] = (
    ("main_lens.f", "F, main-lens focal length (mm)"),
    ("D", "L, main lens to MLA (mm); libpleno's D is a distance, not our microlens pitch D"),
    ("d", "b, MLA to sensor (mm)"),
    ("mla.focal_lengths", "[f], one microlens type (I = 1) (mm)"),
    ("mla.mesh.pitch", "[[D, D]], our microlens pitch (mm, data sheet)"),
    (
        "mla.mesh.pose",
        "lens-centre lattice in the camera frame (mm): rotation Rz(θ), translation = lens "
        "(i_max, j_max) at (δ(cx − x), δ(cy − y), −L) (libpleno's lens (k, l) is micro-image "
        "(W−1−k, H−1−l), its camera x, y axes point against the image u, v axes)",
    ),
    ("mla.mesh.width/height", "lenses whose micro-image centre is on the sensor, per axis"),
    ("mia.mesh.pitch", "[[μ, μ]], measured micro-image pitch (px)"),
    (
        "mia.mesh.pose",
        "micro-image lattice in image pixels (u = x, v = y): rotation R(θ), translation = "
        "centre of micro-image (i_min, j_min)",
    ),
    ("mia.mesh.geometry / mla.mesh.geometry", "0 (orthogonal: our MLA is a square grid)"),
    ("pp", "[[cx, cy]], principal point (px, pixel centres at integers)"),
    (
        "sensor.pose.translation",
        "[[−δ(W−1−cx), −δ(H−1−cy), −(L+b)]] (so that libpleno's pp() gives back (cx, cy))",
    ),
    ("sensor.scale / width / height", "δ (mm), W, H (px)"),
    ("Rxyz", "[[0, 0, θ]], MLA rotation angles (rad)"),
    ("focal_planes", "[u0], the calibrated focus plane (object distance from the main lens, mm)"),
    ("dist_focus", "u0 + L + b: focus distance measured from the sensor plane (mm)"),
    ("main_lens.diameter", "A = D·L/b (f-number matching, L/A = b/D) (mm)"),
    ("main_lens.aperture", "F/A, the f-number that matching implies"),
    ("mode", "1 (Keplerian: F < L and f < b)"),
    ("I", "1 (one microlens focal length)"),
    ("distortions, distortions_inverse", "zero (the ESIF model has no main-lens distortion)"),
    ("scaling", "a = 0, b = 1, c = 0 (no depth scaling correction)"),
)
"""libpleno/COMPOTE key -> our symbols (``shared/OPTICS.md``)."""


class ExportError(ValueError):
    """The result cannot be exported or imported (the message says why, in one line)."""


# ----------------------------------------------------------------------- the schema


@cache
def schema() -> dict[str, Any]:
    """The JSON Schema of ``lfcal-result/1`` (draft 2020-12), from the package data."""
    text = resources.files("calibration").joinpath(SCHEMA_RESOURCE).read_text(encoding="utf-8")
    data: dict[str, Any] = json.loads(text)
    return data


def schema_problems(result: Any) -> list[str]:
    """Every way ``result`` breaks the schema, as ``path: message`` lines (empty: valid)."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema())
    out = []
    for err in sorted(validator.iter_errors(result), key=lambda e: list(e.absolute_path)):
        where = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err.absolute_path)
        out.append(f"{where.lstrip('.') or '(top level)'}: {err.message}")
    return out


def validate_result(result: Any) -> None:
    """:class:`ExportError` (first problem, and how many) unless ``result`` fits the schema."""
    problems = schema_problems(result)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ExportError(f"not a valid lfcal-result/1: {problems[0]}{more}")


# ----------------------------------------------------------------------- lfcal


def export_lfcal(result: dict[str, Any]) -> str:
    """The result as canonical JSON text (validated; key order kept, floats exact)."""
    validate_result(result)
    try:
        return json.dumps(result, indent=1, allow_nan=False, ensure_ascii=False) + "\n"
    except ValueError as exc:  # NaN or infinity slipped in
        raise ExportError(f"the result holds a value JSON cannot carry: {exc}") from None


def import_result(text: str | bytes) -> dict[str, Any]:
    """Read an ``lfcal-result/1`` JSON text back (schema-checked); :class:`ExportError`."""
    try:
        data = json.loads(text)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ExportError(f"not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ExportError("not an lfcal-result/1 file: the top level is not a JSON object")
    validate_result(data)
    return data


# ----------------------------------------------------------------------- COMPOTE


def _s(value: float | int) -> str:
    """A number as libv writes it: integers plainly, doubles with 17 significant digits."""
    if isinstance(value, int | np.integer) and not isinstance(value, bool):
        return str(int(value))
    v = float(value)
    if not math.isfinite(v):
        raise ExportError(f"cannot export the non-finite value {v}")
    return f"{v:.17g}"


def _columns(matrix: Any) -> list[list[str]]:
    """A matrix as libv writes an Eigen matrix: the list of its columns."""
    m = np.asarray(matrix, dtype=np.float64)
    return [[_s(x) for x in m[:, c]] for c in range(m.shape[1])]


def _vector(*values: float) -> list[list[str]]:
    """A column vector as libv writes it: one column, ``[[x, y, ...]]``."""
    return [[_s(v) for v in values]]


def _pose(rotation: Any, translation: list[float]) -> dict[str, Any]:
    return {"rotation": _columns(rotation), "translation": _vector(*translation)}


@dataclass(frozen=True)
class _MeshBox:
    """Index range of the lenses whose micro-image centre lies on the sensor."""

    i0: int
    i1: int
    j0: int
    j1: int

    @property
    def width(self) -> int:
        return self.i1 - self.i0 + 1

    @property
    def height(self) -> int:
        return self.j1 - self.j0 + 1


def _mesh_box(cam: CalibratedCamera) -> _MeshBox:
    ii, jj = cam.image_grid.indices_in(cam.width, cam.height)
    if ii.size == 0:
        raise ExportError("no micro-image centre of the calibrated lattice lies on the sensor")
    return _MeshBox(int(ii.min()), int(ii.max()), int(jj.min()), int(jj.max()))


def export_compote(result: dict[str, Any]) -> dict[str, Any]:
    """The libpleno/COMPOTE intrinsics of a result (a JSON-ready dict); see :data:`COMPOTE_MAPPING`."""
    try:
        cam = CalibratedCamera.from_result(result)
    except ResultError as exc:
        raise ExportError(str(exc)) from None
    box = _mesh_box(cam)
    th = cam.image_grid.rotation_rad
    c, s = math.cos(th), math.sin(th)
    rot2 = np.array([[c, -s], [s, c]])
    rot3 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    identity = np.eye(3)
    cx, cy = cam.principal_point_px
    W, H = cam.width, cam.height
    mia_x, mia_y = cam.image_grid.centre(box.i0, box.j0)
    lens_x, lens_y = cam.lens_grid.centre(box.i1, box.j1)
    A = cam.main_aperture_mm
    zero3 = {"depth": _vector(0, 0, 0), "model": "0", "radial": _vector(0, 0, 0)}
    return {
        "D": _s(cam.L),
        "I": "1",
        "Rxyz": _vector(0.0, 0.0, th),
        "d": _s(cam.b),
        "dist_focus": _s(cam.focus_mm + cam.L + cam.b),
        "distortions": dict(zero3, tangential=_vector(0, 0)),
        "distortions_inverse": dict(zero3, tangential=_vector(0, 0)),
        "focal_planes": [_s(cam.focus_mm)],
        "main_lens": {
            "aperture": _s(cam.F / A),
            "diameter": _s(A),
            "f": _s(cam.F),
            "pose": _pose(identity, [0.0, 0.0, 0.0]),
        },
        "mia": {
            "mesh": {
                "geometry": "0",
                "height": _s(box.height),
                "pitch": _vector(cam.image_pitch_px, cam.image_pitch_px),
                "pose": _pose(rot2, [float(mia_x), float(mia_y)]),
                "width": _s(box.width),
            }
        },
        "mla": {
            "focal_lengths": [_s(cam.f)],
            "mesh": {
                "geometry": "0",
                "height": _s(box.height),
                "pitch": _vector(cam.D, cam.D),
                "pose": _pose(
                    rot3,
                    [cam.delta * (cx - float(lens_x)), cam.delta * (cy - float(lens_y)), -cam.L],
                ),
                "width": _s(box.width),
            },
        },
        "mode": "1",
        "pp": _vector(cx, cy),
        "scaling": {"a": "0", "b": "1", "c": "0"},
        "sensor": {
            "height": _s(H),
            "pose": _pose(
                identity,
                [-cam.delta * (W - 1 - cx), -cam.delta * (H - 1 - cy), -(cam.L + cam.b)],
            ),
            "scale": _s(cam.delta),
            "width": _s(W),
        },
    }


# ----------------------------------------------------------------------- summaries


@dataclass(frozen=True)
class SummaryRow:
    """One quantity of the plain summaries: ``section.key`` with its symbol and unit."""

    section: str
    key: str
    symbol: str
    value: float | int | str | None
    uncertainty: float | None
    unit: str
    source: str


def _num(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    f = float(value)
    return f if math.isfinite(f) else None


def summary_rows(result: dict[str, Any]) -> list[SummaryRow]:
    """The calibrated camera as rows (section, key, symbol, value, 1σ, unit, source)."""
    try:
        cam = CalibratedCamera.from_result(result)
    except ResultError as exc:
        raise ExportError(str(exc)) from None
    unc = result.get("uncertainty") or {}
    focus = result.get("focus") or {}
    software = result.get("software") or {}
    glob = (result.get("estimates") or {}).get("global") or {}
    L_se = _num(((result.get("priors") or {}).get("L_mm") or {}).get("uncertainty"))
    if L_se is None and cam.L_source.startswith("estimates.global"):
        L_se = _num(glob.get("L_se_mm"))
    R = SummaryRow
    calib, prior, meas = "calibrated", "prior (data sheet / station)", "measured (white image)"
    return [
        R("camera", "width_px", "W", cam.width, None, "px", prior),
        R("camera", "height_px", "H", cam.height, None, "px", prior),
        R("camera", "pixel_pitch_mm", "δ", cam.delta, None, "mm", prior),
        R("camera", "principal_point_x_px", "cx", cam.principal_point_px[0], None, "px", prior),
        R("camera", "principal_point_y_px", "cy", cam.principal_point_px[1], None, "px", prior),
        R("optics", "main_focal_mm", "F", cam.F, None, "mm", prior),
        R("optics", "mla_focal_mm", "f", cam.f, None, "mm", prior),
        R("optics", "mla_pitch_mm", "D", cam.D, None, "mm", prior),
        R("calibrated", "b_mm", "b", cam.b, _num(unc.get("b_mm")), "mm", calib),
        R("calibrated", "a_mm", "a", cam.a_f, _num(unc.get("a_mm")), "mm", calib),
        R("calibrated", "Q", "Q", _num(result.get("Q")), _num(unc.get("Q")), "", calib),
        R(
            "calibrated",
            "patch_size_px",
            "p",
            cam.patch_px,
            _num(unc.get("patch_size_px")),
            "px",
            calib,
        ),
        R("calibrated", "L_mm", "L", cam.L, L_se, "mm", f"{calib}: {cam.L_source}"),
        R(
            "focus",
            "object_distance_mm",
            "u0",
            cam.focus_mm,
            _num(focus.get("uncertainty_mm")),
            "mm",
            calib,
        ),
        R("focus", "rail_mm", "", _num(focus.get("rail_mm")), None, "mm", calib),
        R("mla", "lens_pitch_px", "D/δ", cam.lens_pitch_px, None, "px", prior),
        R("mla", "image_pitch_px", "μ", cam.image_pitch_px, None, "px", meas),
        R("mla", "rotation_deg", "θ", cam.image_grid.rotation_deg, None, "deg", meas),
        R("mla", "lens_origin_x_px", "", cam.lens_grid.origin_px[0], None, "px", meas),
        R("mla", "lens_origin_y_px", "", cam.lens_grid.origin_px[1], None, "px", meas),
        R("mla", "image_origin_x_px", "", cam.image_grid.origin_px[0], None, "px", meas),
        R("mla", "image_origin_y_px", "", cam.image_grid.origin_px[1], None, "px", meas),
        R("software", "name", "", str(software.get("name", "")), None, "", ""),
        R("software", "version", "", str(software.get("version", "")), None, "", ""),
    ]


def export_csv(result: dict[str, Any]) -> str:
    """The summary as CSV: ``section,key,symbol,value,uncertainty,unit,source`` (UTF-8)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["section", "key", "symbol", "value", "uncertainty", "unit", "source"])
    for r in summary_rows(result):
        writer.writerow(
            [
                r.section,
                r.key,
                r.symbol,
                ""
                if r.value is None
                else (repr(r.value) if isinstance(r.value, float) else r.value),
                "" if r.uncertainty is None else repr(r.uncertainty),
                r.unit,
                r.source,
            ]
        )
    return buf.getvalue()


def _toml_value(value: float | int | str) -> str:
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a TOML basic string is a JSON string
    if isinstance(value, float):
        return repr(value)
    return str(value)


def export_toml(result: dict[str, Any]) -> str:
    """The summary as TOML: one table per section, ``KEY = value`` and
    ``KEY_uncertainty = 1σ`` (values absent in the result are left out)."""
    lines = ["# lfcal-station calibration summary (lfcal-result/1); 1-sigma uncertainties", ""]
    section = None
    for r in summary_rows(result):
        if r.section != section:
            if section is not None:
                lines.append("")
            lines.append(f"[{r.section}]")
            section = r.section
        if r.value is None:
            continue
        comment = f"  # {r.symbol}" + (f" ({r.unit})" if r.unit else "") if r.symbol else ""
        lines.append(f"{r.key} = {_toml_value(r.value)}{comment}")
        if r.uncertainty is not None:
            lines.append(f"{r.key}_uncertainty = {_toml_value(r.uncertainty)}")
    return "\n".join(lines) + "\n"


def export_text(result: dict[str, Any], fmt: str) -> str:
    """The result in format ``fmt`` (one of :data:`FORMATS`) as text."""
    if fmt == "lfcal":
        return export_lfcal(result)
    if fmt == "compote":
        return json.dumps(export_compote(result), indent=4) + "\n"
    if fmt == "csv":
        return export_csv(result)
    if fmt == "toml":
        return export_toml(result)
    raise ExportError(f"unknown export format {fmt!r}: choose one of {', '.join(FORMATS)}")


__all__ = [
    "COMPOTE_MAPPING",
    "FORMATS",
    "ExportError",
    "SummaryRow",
    "export_compote",
    "export_csv",
    "export_lfcal",
    "export_text",
    "export_toml",
    "import_result",
    "schema",
    "schema_problems",
    "summary_rows",
    "validate_result",
]
