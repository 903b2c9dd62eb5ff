"""Rendering a lab's own raw frames with a calibration (``lfcal render``), against the simulator.

The seed paper's Fig. 12 point: a scene (text, a Siemens star, cube faces --
not the calibration board) rendered with the calibrated patch size joins up,
with a wrong one it is full of seam artefacts. The scene frames come from the
project's simulator through the same camera model as the calibration sweep
(:mod:`lab_support`); the calibration is a real ``lfcal calibrate`` of that
sweep. Ground truth: the simulator's optics (``p(u) = Q(u)·D/δ``).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from lab_support import FOCUS_MM, NEAR_MM, LabData, lab_camera, lab_data, read_png

from calibration.export_model import CalibratedCamera, ResultError, designed_patch_px
from calibration.raw_image import RawImageError, decode_raw, png_problem
from calibration.raw_render import (
    MIN_LATTICE_CONTRAST,
    FrameMismatch,
    check_frame,
    choose_patch,
    lattice_contrast,
    render_frame_with,
)
from calibration.scene import camera_of_sweep
from calibration.scene import main as scene_main
from station.cli import main


@pytest.fixture(scope="module")
def lab(pytestconfig: pytest.Config) -> LabData:
    return lab_data(pytestconfig)


@pytest.fixture(scope="module")
def camera(lab: LabData) -> CalibratedCamera:
    return CalibratedCamera.from_result(lab.result())


def test_the_calibrated_model_gives_the_true_patch_size_at_any_distance(
    lab: LabData, camera: CalibratedCamera
) -> None:
    """p(u) = Q(u)·D/δ of the calibrated model against the simulator's optics."""
    truth = lab_camera(camera.principal_point_px).optics
    assert camera.L_source == "L_mm"  # the calibrated L (issue 11)
    assert camera.L == pytest.approx(truth.L, abs=0.01)
    for u in (410.0, NEAR_MM, FOCUS_MM, 454.0):
        assert camera.patch_at(u) == pytest.approx(float(truth.patch_px(u)), abs=0.02)
    # at the calibrated focus plane the model gives back the calibrated p exactly
    assert camera.patch_at(camera.focus_mm) == pytest.approx(camera.patch_px, rel=1e-12)
    with pytest.raises(ValueError, match="behind the microlens array"):
        camera.patch_at(120.0)


def test_a_scene_rendered_with_the_calibrated_p_has_fewer_artefacts(
    lab: LabData, camera: CalibratedCamera, tmp_path: Path
) -> None:
    """Fig. 12 of the seed paper: calibrated vs wrong p on a scene at the focus plane."""
    raw = read_png(lab.scene(FOCUS_MM))
    calibrated = render_frame_with(raw, camera, camera.patch_px)
    scores = {
        p: render_frame_with(raw, camera, p, score=True).score
        for p in (0.9 * camera.patch_px, 1.1 * camera.patch_px, 20.0)
    }
    assert calibrated.score < 2.5  # nearly seam-free (1 is perfect)
    for p, score in scores.items():
        assert score > 3 * calibrated.score, (p, score, calibrated.score)
    # the rendering is an upright image of the scene: the bright and dark text are there
    assert calibrated.image.shape == (135, 345)
    img = calibrated.image
    assert img.std() > 0.1 * img.mean()


def test_object_distance_gives_the_patch_size_of_an_off_focus_scene(
    lab: LabData, camera: CalibratedCamera
) -> None:
    raw = read_png(lab.scene(NEAR_MM))
    p_near = choose_patch(camera, "calibrated", object_distance_mm=NEAR_MM)
    assert p_near == pytest.approx(camera.patch_at(NEAR_MM))
    near = render_frame_with(raw, camera, p_near).score
    at_focus = render_frame_with(raw, camera, camera.patch_px).score
    assert near < 2.5 and at_focus > 3 * near


def test_frames_of_another_camera_are_refused_by_their_lattice(
    lab: LabData, camera: CalibratedCamera
) -> None:
    for path in (lab.scene(FOCUS_MM), lab.sweep / "white.png", lab.sweep / "frames" / "0005.png"):
        assert lattice_contrast(read_png(path), camera.image_grid) > 0.6
    other = read_png(lab.other_camera)
    assert other.shape == (camera.height, camera.width)
    assert abs(lattice_contrast(other, camera.image_grid)) < MIN_LATTICE_CONTRAST / 3
    with pytest.raises(FrameMismatch, match="does not show the calibrated micro-image lattice"):
        check_frame(other, camera)
    with pytest.raises(FrameMismatch, match="is 1999x800 px, the calibration is for 2000x800"):
        check_frame(read_png(lab.scene(FOCUS_MM))[:, :1999], camera)


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def _score(out: str) -> float:
    line = next(line for line in out.splitlines() if line.startswith("artefact score"))
    return float(line.split()[2])


def test_lfcal_render_cli_png_tiff_8_bit_white_and_designed(
    lab: LabData, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = read_png(lab.scene(FOCUS_MM))
    tiff = tmp_path / "scene.tiff"
    assert cv2.imwrite(str(tiff), raw)
    eight = tmp_path / "scene8.png"
    assert cv2.imwrite(str(eight), (raw >> 4).astype(np.uint8))  # 12-bit counts -> 8 bit
    result = str(lab.result_path)
    out_png = tmp_path / "out.png"
    code, out, err = _run(
        capsys, "render", str(lab.scene(FOCUS_MM)), "--result", result, "--out", str(out_png)
    )
    assert code == 0, err
    calibrated = _score(out)
    assert "calibrated model at the focus plane" in out
    p_px = float(out.split("with p = ", 1)[1].split()[0])
    assert p_px == pytest.approx(18.0, abs=0.02)  # the simulator's p: the accuracy target
    rendered = cv2.imread(str(out_png), cv2.IMREAD_UNCHANGED)
    assert rendered.dtype == np.uint8 and rendered.shape == (135, 345)

    code, out, err = _run(
        capsys, "render", str(tiff), "--result", result, "--out", str(tmp_path / "t.png")
    )
    assert code == 0, err
    assert _score(out) == pytest.approx(calibrated, rel=1e-9)  # the same pixels
    code, out, err = _run(
        capsys,
        "render",
        str(eight),
        "--result",
        result,
        "--white",
        str(lab.sweep / "white.png"),
        "--out",
        str(tmp_path / "e.png"),
    )
    assert code == 0, err
    assert "flat-fielded" in out and _score(out) < 2.5

    # the designed optics of the data sheet (b = 2.5 mm): p = 20 px, a worse render
    code, out, err = _run(
        capsys,
        "render",
        str(lab.scene(FOCUS_MM)),
        "--result",
        result,
        "--p",
        "designed",
        "--designed-b-mm",
        "2.5",
        "--out",
        str(tmp_path / "d.png"),
    )
    assert code == 0, err
    assert "p = 20.000 px (designed optics)" in out
    assert _score(out) > 3 * calibrated
    # a scene at 400 mm: the calibrated model's p(400) beats the focus-plane p
    code, out, err = _run(
        capsys,
        "render",
        str(lab.scene(NEAR_MM)),
        "--result",
        result,
        "--object-distance-mm",
        str(NEAR_MM),
        "--out",
        str(tmp_path / "n.png"),
    )
    assert code == 0, err
    assert "at u = 400 mm" in out and _score(out) < 2.5


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("wrong-size", "is 2000x799 px, the calibration is for 2000x800 px frames"),
        ("other-camera", "does not show the calibrated micro-image lattice"),
        ("truncated", "is a truncated PNG file"),
        ("damaged", "is a damaged PNG file (CRC error in chunk IDAT"),
        ("not-an-image", "is not a PNG or TIFF file"),
        ("missing", "no such file"),
        ("result-not-json", "not a JSON file"),
        ("result-not-a-result", "not an lfcal-result/1 calibration result"),
        ("designed-unknown", "--p designed needs the designed optics"),
        ("bad-p", "--p must be calibrated, designed or a patch size in pixels"),
        ("white-wrong-size", "is 2000x799 px"),
    ],
)
def test_lfcal_render_bad_input_is_one_line_and_exit_2(
    lab: LabData, tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str, message: str
) -> None:
    scene = lab.scene(FOCUS_MM)
    data = scene.read_bytes()
    raw_arg, result_arg, extra = str(scene), str(lab.result_path), []
    bad = tmp_path / "bad.png"
    if case == "wrong-size":
        cv2.imwrite(str(bad), read_png(scene)[:799])
        raw_arg = str(bad)
    elif case == "other-camera":
        raw_arg = str(lab.other_camera)
    elif case == "truncated":
        bad.write_bytes(data[: len(data) // 2])
        raw_arg = str(bad)
    elif case == "damaged":
        broken = bytearray(data)
        broken[len(data) // 2] ^= 0xFF
        bad.write_bytes(bytes(broken))
        raw_arg = str(bad)
    elif case == "not-an-image":
        bad.write_text("not an image\n")
        raw_arg = str(bad)
    elif case == "missing":
        raw_arg = str(tmp_path / "nothing.png")
    elif case == "result-not-json":
        result_arg = str(scene)
    elif case == "result-not-a-result":
        (tmp_path / "r.json").write_text('{"format": "lfcal-sweep/1"}')
        result_arg = str(tmp_path / "r.json")
    elif case == "designed-unknown":
        extra = ["--p", "designed"]
    elif case == "bad-p":
        extra = ["--p", "sharpest"]
    elif case == "white-wrong-size":
        cv2.imwrite(str(bad), read_png(lab.sweep / "white.png")[:799])
        extra = ["--white", str(bad)]
    out_png = tmp_path / "out.png"
    code, out, err = _run(
        capsys, "render", raw_arg, "--result", result_arg, "--out", str(out_png), *extra
    )
    assert code == 2
    assert out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("lfcal render: ") and message in err, err
    assert not out_png.exists()


def test_png_checks_and_decoding_against_the_specification(lab: LabData) -> None:
    data = lab.scene(FOCUS_MM).read_bytes()
    assert png_problem(data) is None
    # IEND is the last chunk: 12 bytes (length 0, type, CRC 0xAE426082 of "IEND")
    assert data[-12:] == b"\x00\x00\x00\x00IEND\xaeB`\x82"
    assert "truncated" in (png_problem(data[:-12]) or "")
    raw = decode_raw(data)
    assert raw.dtype == np.uint16 and raw.shape == (800, 2000)
    colour = cv2.imencode(".png", np.dstack([(raw >> 4).astype(np.uint8)] * 3))[1].tobytes()
    assert decode_raw(colour).shape == (800, 2000)  # colour is turned to grey
    with pytest.raises(RawImageError, match="empty"):
        decode_raw(b"")


def test_the_scene_tool_rebuilds_the_camera_of_a_simulated_sweep(
    lab: LabData, camera: CalibratedCamera, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rebuilt = camera_of_sweep(lab.truth)
    expected = lab_camera(camera.principal_point_px)
    assert rebuilt.optics == expected.optics and rebuilt.sensor == expected.sensor
    assert rebuilt.mla_rotation_deg == expected.mla_rotation_deg
    assert scene_main([str(tmp_path), str(tmp_path / "x.png"), "--object-distance-mm", "400"]) == 2
    assert "truth.json" in capsys.readouterr().err


def test_a_result_without_what_rendering_needs_is_refused(lab: LabData) -> None:
    result = lab.result()
    del result["mla"]["image_grid"]
    with pytest.raises(ResultError, match="micro-image lattice"):
        CalibratedCamera.from_result(result)
    with pytest.raises(ResultError, match="lfcal-result/1"):
        CalibratedCamera.from_result({"format": "lfcal-sweep/1"})
    assert designed_patch_px(b_mm=3.0, f_mm=2.5, D_mm=0.25, delta_mm=0.0025) == pytest.approx(20.0)
    with pytest.raises(ValueError, match="must exceed f"):
        designed_patch_px(b_mm=2.0, f_mm=2.5, D_mm=0.25, delta_mm=0.0025)
