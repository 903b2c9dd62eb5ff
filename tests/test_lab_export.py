"""Exporting a calibration: our JSON Schema, libpleno/COMPOTE intrinsics, CSV and TOML.

Peers: the JSON Schema is checked with ``jsonschema`` (Draft 2020-12); the
COMPOTE intrinsics against the structure of COMPOTE's published example and
against libpleno's camera model as its source defines it; TOML with the
standard library's ``tomllib``; CSV with ``csv``.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import math
import tomllib
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from lab_support import LabData, lab_camera, lab_data

from calibration.export import (
    FORMATS,
    ExportError,
    export_compote,
    export_text,
    import_result,
    schema,
    schema_problems,
)
from calibration.lens_grid import LensGrid
from station.cli import main

REPO = Path(__file__).resolve().parents[1]

# The structure of COMPOTE's example intrinsics, examples/config/intrinsics.js of
# github.com/comsee-research/compote (commit 6d10e9b73220f0d2c5e9796e5e3a42c3300012a2),
# recorded key by key: "s" is a number written as a string (libv's JSON archive),
# ["s", "s"] a list, [["s", "s", "s"]] a column vector, a list of lists a matrix
# (one inner list per column), "I*s" a list of I strings (I = number of microlens
# types: 3 in the example, 1 for our single-focus MLA).
M3 = [["s", "s", "s"], ["s", "s", "s"], ["s", "s", "s"]]
M2 = [["s", "s"], ["s", "s"]]
V3 = [["s", "s", "s"]]
V2 = [["s", "s"]]
DISTORTIONS = {"depth": V3, "model": "s", "radial": V3, "tangential": V2}
COMPOTE_INTRINSICS: dict[str, Any] = {
    "D": "s",
    "I": "s",
    "Rxyz": V3,
    "d": "s",
    "dist_focus": "s",
    "distortions": DISTORTIONS,
    "distortions_inverse": DISTORTIONS,
    "focal_planes": "I*s",
    "main_lens": {
        "aperture": "s",
        "diameter": "s",
        "f": "s",
        "pose": {"rotation": M3, "translation": V3},
    },
    "mia": {
        "mesh": {
            "geometry": "s",
            "height": "s",
            "pitch": V2,
            "pose": {"rotation": M2, "translation": V2},
            "width": "s",
        }
    },
    "mla": {
        "focal_lengths": "I*s",
        "mesh": {
            "geometry": "s",
            "height": "s",
            "pitch": V2,
            "pose": {"rotation": M3, "translation": V3},
            "width": "s",
        },
    },
    "mode": "s",
    "pp": V2,
    "scaling": {"a": "s", "b": "s", "c": "s"},
    "sensor": {
        "height": "s",
        "pose": {"rotation": M3, "translation": V3},
        "scale": "s",
        "width": "s",
    },
}
# libpleno's own example, examples/config/intrinsics.js of github.com/comsee-research/libpleno
# (commit 5a2b3843de23f847f43f9d0ecca7d239f8f3a6e9), written by an older libpleno: a subset.
LIBPLENO_INTRINSICS: dict[str, Any] = {
    "I": "s",
    "dist_focus": "s",
    "distortions": {"radial": V3, "tangential": V2},
    "main_lens": COMPOTE_INTRINSICS["main_lens"],
    "mia": COMPOTE_INTRINSICS["mia"],
    "mla": COMPOTE_INTRINSICS["mla"],
    "mode": "s",
    "sensor": COMPOTE_INTRINSICS["sensor"],
}


def structure_problems(value: Any, shape: Any, path: str = "") -> list[str]:
    """Where ``value`` differs from the recorded ``shape`` (keys, nesting, types);
    with ``subset`` semantics for dicts only when called on a sub-shape."""
    if shape == "s":
        if not isinstance(value, str):
            return [f"{path}: expected a number as a string, got {type(value).__name__}"]
        try:
            ok = math.isfinite(float(value))
        except ValueError:
            ok = False
        return [] if ok else [f"{path}: {value!r} is not a number"]
    if shape == "I*s":
        if not isinstance(value, list) or not value:
            return [f"{path}: expected a non-empty list of strings"]
        return [p for k, v in enumerate(value) for p in structure_problems(v, "s", f"{path}[{k}]")]
    if isinstance(shape, list):
        if not isinstance(value, list) or len(value) != len(shape):
            return [f"{path}: expected a list of {len(shape)}, got {value!r:.60}"]
        return [
            p
            for k, (v, s) in enumerate(zip(value, shape, strict=True))
            for p in structure_problems(v, s, f"{path}[{k}]")
        ]
    assert isinstance(shape, dict)
    if not isinstance(value, dict):
        return [f"{path}: expected an object"]
    problems = [f"{path}.{k}: missing" for k in shape if k not in value]
    return problems + [
        p
        for k, s in shape.items()
        if k in value
        for p in structure_problems(value[k], s, f"{path}.{k}")
    ]


@pytest.fixture(scope="module")
def lab(pytestconfig: pytest.Config) -> LabData:
    return lab_data(pytestconfig)


@pytest.fixture(scope="module")
def result(lab: LabData) -> dict[str, Any]:
    return lab.result()


def with_priors(result: dict[str, Any]) -> dict[str, Any]:
    """The result with the ``priors`` section the lead's core rework adds (issues 10, 11)."""
    out = copy.deepcopy(result)
    out["priors"] = {
        "main_focal_mm": {
            "datasheet": 50.0,
            "calibrated": 50.12,
            "uncertainty": 0.05,
            "z": -2.2,
            "tolerance": 0.5,
        },
        "mla_focal_mm": {
            "datasheet": 2.0,
            "calibrated": 2.09,
            "uncertainty": 0.01,
            "z": -8.9,
            "tolerance": 0.05,
        },
        "rail_zero_object_distance_mm": {
            "datasheet": 380.0,
            "calibrated": 380.3,
            "uncertainty": 0.2,
            "z": -1.5,
            "tolerance": 1.0,
        },
        "L_mm": {"calibrated": 67.41, "uncertainty": 0.003},
    }
    out["L_mm"] = 67.41
    return out


# ----------------------------------------------------------------------- the schema


def test_the_schema_is_package_data_and_valid_draft_2020_12() -> None:
    jsonschema.Draft202012Validator.check_schema(schema())
    assert schema()["properties"]["format"] == {"const": "lfcal-result/1"}
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert "schemas/*.json" in pyproject["tool"]["setuptools"]["package-data"]["calibration"]
    assert (REPO / "calibration" / "schemas" / "lfcal-result-1.schema.json").is_file()


def test_real_results_validate_and_broken_ones_do_not(result: dict[str, Any]) -> None:
    assert schema_problems(result) == []
    assert schema_problems(with_priors(result)) == []
    # a failed calibration's partial result (what lfcal calibrate --out writes on exit 3/4)
    partial = {k: v for k, v in result.items() if k not in ("a_mm", "b_mm", "Q", "focus")}
    partial["error"] = "the focus plane is at the edge of the sweep"
    assert schema_problems(partial) == []
    broken = copy.deepcopy(result)
    broken["format"] = "lfcal-result/2"
    broken["frames"][3]["Q"] = "0.2"
    del broken["mla"]["image_grid"]
    problems = schema_problems(broken)
    assert any(p.startswith("format:") for p in problems)
    assert any(p.startswith("frames[3].Q:") for p in problems)
    assert any(p.startswith("mla:") and "image_grid" in p for p in problems)


def test_export_then_import_of_our_format_is_lossless(result: dict[str, Any]) -> None:
    for original in (result, with_priors(result)):
        text = export_text(original, "lfcal")
        back = import_result(text)
        assert back == original
        assert json.dumps(back, sort_keys=True) == json.dumps(original, sort_keys=True)
        assert export_text(back, "lfcal") == text
    with pytest.raises(ExportError, match="not JSON"):
        import_result("{")
    with pytest.raises(ExportError, match="not a valid lfcal-result/1: format"):
        import_result(json.dumps(dict(result, format="other")))


# ----------------------------------------------------------------------- COMPOTE


def test_compote_intrinsics_have_the_structure_of_the_published_examples(
    result: dict[str, Any],
) -> None:
    exported = json.loads(export_text(result, "compote"))
    assert structure_problems(exported, COMPOTE_INTRINSICS) == []
    assert set(exported) == set(COMPOTE_INTRINSICS)
    # libpleno's example is a subset of the same structure
    assert structure_problems(exported, LIBPLENO_INTRINSICS) == []
    # our camera: one microlens type, Keplerian, orthogonal grids
    assert exported["I"] == "1" and exported["mode"] == "1"
    # the calibrated microlens focal length (issue 11), not the data sheet's
    (focal,) = exported["mla"]["focal_lengths"]
    assert float(focal) == pytest.approx(result["priors"]["mla_focal_mm"]["calibrated"])
    assert len(exported["focal_planes"]) == 1
    assert exported["mia"]["mesh"]["geometry"] == exported["mla"]["mesh"]["geometry"] == "0"


def _cols(matrix: list[list[str]]) -> np.ndarray:
    """A libv matrix (list of columns) as a numpy array."""
    return np.array([[float(v) for v in col] for col in matrix]).T


def test_compote_geometry_follows_libplenos_camera_model(
    result: dict[str, Any], lab: LabData
) -> None:
    """libpleno (pleno/geometry/camera/plenoptic.cpp, camera.cpp, mesh.cpp, pose.cpp): the
    main lens at the origin, MLA nodes R·(pitch·(k, l), 0) + t, the sensor at
    z = -(D + d) with pixel x = (p - t_sensor)/scale, image (u, v) = (W-1-x, H-1-y),
    micro-image (k, l) the central projection of lens (W_mla-1-k, H_mla-1-l)
    (``mi2ml``), pp() = xy2uv(-t_sensor/scale)."""
    c = export_compote(result)
    truth = lab_camera(tuple(result["inputs"]["camera"]["principal_point_px"])).optics
    D, d = float(c["D"]), float(c["d"])
    assert D == pytest.approx(truth.L, abs=0.01) and d == pytest.approx(truth.b, abs=0.001)
    # the calibrated focal lengths (issue 11: the camera, not the data sheet)
    assert float(c["main_lens"]["f"]) == pytest.approx(
        result["priors"]["main_focal_mm"]["calibrated"]
    )
    assert float(c["main_lens"]["f"]) == pytest.approx(truth.F, rel=2e-3)
    assert float(c["mla"]["focal_lengths"][0]) == pytest.approx(truth.f, rel=2e-3)
    W, H, scale = int(c["sensor"]["width"]), int(c["sensor"]["height"]), float(c["sensor"]["scale"])
    t_sensor = _cols(c["sensor"]["pose"]["translation"])[:, 0]
    assert t_sensor[2] == pytest.approx(-(D + d))
    pp_xy = -t_sensor[:2] / scale
    pp_uv = np.array([W - 1, H - 1]) - pp_xy
    np.testing.assert_allclose(pp_uv, result["inputs"]["camera"]["principal_point_px"], atol=1e-9)
    np.testing.assert_allclose(_cols(c["pp"])[:, 0], pp_uv, atol=1e-9)
    r_mla, t_mla = (
        _cols(c["mla"]["mesh"]["pose"]["rotation"]),
        _cols(c["mla"]["mesh"]["pose"]["translation"])[:, 0],
    )
    r_mia, t_mia = (
        _cols(c["mia"]["mesh"]["pose"]["rotation"]),
        _cols(c["mia"]["mesh"]["pose"]["translation"])[:, 0],
    )
    assert np.allclose(r_mla @ r_mla.T, np.eye(3)) and np.linalg.det(r_mla) == pytest.approx(1)
    assert t_mla[2] == pytest.approx(-D)
    theta = math.atan2(r_mia[1, 0], r_mia[0, 0])
    assert math.degrees(theta) == pytest.approx(0.45, abs=0.002)  # the preset's MLA rotation
    assert float(c["Rxyz"][0][2]) == pytest.approx(theta)
    pitch_mla, pitch_mia = (
        float(c["mla"]["mesh"]["pitch"][0][0]),
        float(c["mia"]["mesh"]["pitch"][0][0]),
    )
    n_w, n_h = int(c["mla"]["mesh"]["width"]), int(c["mla"]["mesh"]["height"])
    errors = []
    for k in range(n_w):
        for l in range(n_h):  # noqa: E741 - libpleno's index names
            node = r_mla @ np.array([pitch_mla * k, pitch_mla * l, 0.0]) + t_mla
            on_sensor = node * (D + d) / D  # through the main-lens centre onto z = -(D + d)
            xy = (on_sensor[:2] - t_sensor[:2]) / scale
            uv = np.array([W - 1 - xy[0], H - 1 - xy[1]])
            mi = r_mia @ (pitch_mia * np.array([n_w - 1 - k, n_h - 1 - l])) + t_mia
            errors.append(float(np.hypot(*(uv - mi))))
    assert max(errors) < 0.05  # px: the exported MLA reproduces our micro-image lattice
    # the mesh spans every micro-image whose centre is on the sensor (a rotated lattice's
    # index rectangle also has corners off the sensor, as in COMPOTE's example)
    on_sensor = [
        (i, j)
        for i in range(n_w)
        for j in range(n_h)
        if (lambda p: 0 <= p[0] <= W - 1 and 0 <= p[1] <= H - 1)(
            r_mia @ (pitch_mia * np.array([i, j])) + t_mia
        )
    ]
    grid = result["mla"]["image_grid"]
    ii, jj = LensGrid(
        tuple(grid["origin_px"]), grid["pitch_px"], math.radians(grid["rotation_deg"])
    ).indices_in(W, H)
    assert len(on_sensor) == ii.size
    assert (n_w, n_h) == (ii.max() - ii.min() + 1, jj.max() - jj.min() + 1)
    # numbers are written with 17 significant digits: exact round trip
    assert float(c["d"]) == result["b_mm"]


# ----------------------------------------------------------------------- CSV / TOML


def test_csv_and_toml_summaries_carry_the_values_exactly(result: dict[str, Any]) -> None:
    rows = {r["key"]: r for r in csv.DictReader(io.StringIO(export_text(result, "csv")))}
    assert float(rows["b_mm"]["value"]) == result["b_mm"]
    assert float(rows["b_mm"]["uncertainty"]) == result["uncertainty"]["b_mm"]
    assert rows["b_mm"]["symbol"] == "b" and rows["b_mm"]["unit"] == "mm"
    assert float(rows["object_distance_mm"]["value"]) == result["focus"]["object_distance_mm"]
    assert float(rows["image_pitch_px"]["value"]) == result["mla"]["image_pitch_px"]
    toml = tomllib.loads(export_text(result, "toml"))
    assert toml["calibrated"]["b_mm"] == result["b_mm"]
    assert toml["calibrated"]["Q_uncertainty"] == result["uncertainty"]["Q"]
    assert toml["camera"]["width_px"] == 2000
    assert toml["mla"]["rotation_deg"] == pytest.approx(0.45, abs=0.002)
    assert toml["software"]["version"] == result["software"]["version"]
    # with the priors section the calibrated L (and its uncertainty) is the one reported
    toml = tomllib.loads(export_text(with_priors(result), "toml"))
    assert toml["calibrated"]["L_mm"] == 67.41 and toml["calibrated"]["L_mm_uncertainty"] == 0.003
    assert toml["optics"]["main_focal_mm"] == 50.12  # the calibrated F, not the data sheet's


# ----------------------------------------------------------------------- the command


def test_lfcal_export_writes_every_format(
    lab: LabData, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for fmt in FORMATS:
        out = tmp_path / f"camera.{fmt}"
        assert main(["export", str(lab.result_path), "--format", fmt, "--out", str(out)]) == 0
        assert out.stat().st_size > 200
    assert import_result((tmp_path / "camera.lfcal").read_text()) == lab.result()
    capsys.readouterr()
    # standard output by default; an archive directory holding result.json works too
    assert main(["export", str(lab.result_path), "--format", "toml"]) == 0
    assert tomllib.loads(capsys.readouterr().out)["calibrated"]["b_mm"] == lab.result()["b_mm"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--format", "xml"],
            "unknown export format 'xml': choose one of lfcal, compote, csv, toml",
        ),
        (["--format", "compote", "@missing"], "no such file"),
        (["--format", "lfcal", "@sweep"], "has no result.json"),
        (["--format", "lfcal", "@not-a-result"], "not an lfcal-result/1 calibration result"),
        (["--format", "lfcal", "@no-grid"], "not a valid lfcal-result/1: mla"),
        (["--format", "compote", "@no-grid"], "micro-image lattice"),
    ],
)
def test_lfcal_export_bad_input_is_one_line_and_exit_2(
    lab: LabData,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    message: str,
) -> None:
    target = str(lab.result_path)
    rest = []
    for a in args:
        if a == "@missing":
            target = str(tmp_path / "none.json")
        elif a == "@sweep":
            target = str(lab.sweep)
        elif a == "@not-a-result":
            (tmp_path / "x.json").write_text('{"format": "lfcal-sweep/1"}')
            target = str(tmp_path / "x.json")
        elif a == "@no-grid":
            broken = lab.result()
            del broken["mla"]["image_grid"]
            (tmp_path / "x.json").write_text(json.dumps(broken))
            target = str(tmp_path / "x.json")
        else:
            rest.append(a)
    code = main(["export", target, *rest])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("lfcal export: ") and message in err, err
