"""`lfcal simulate` and `lfcal calibrate` end to end, and their handling of bad input."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest

from station.cli import main

FRAMES = 25  # 4 mm steps over the 96 mm sweep keep the test fast


@pytest.fixture(scope="module")
def sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "rotated"
    code = main(
        [
            "simulate",
            str(out),
            "--preset",
            "rotated",
            "--frames",
            str(FRAMES),
            "--step-mm",
            "4",
            "--width",
            "2400",
            "--height",
            "800",
            "--seed",
            "3",
        ]
    )
    assert code == 0
    return out


@pytest.fixture(scope="module")
def result(sweep: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("res")
    code = main(
        ["calibrate", str(sweep), "--out", str(out / "result.json"), "--plots", str(out / "plots")]
    )
    assert code == 0
    data = json.loads((out / "result.json").read_text())
    data["_plots"] = sorted(p.name for p in (out / "plots").iterdir())
    return data


def test_simulate_writes_a_complete_archive_with_truth(sweep: Path) -> None:
    manifest = json.loads((sweep / "sweep.json").read_text())
    assert manifest["format"] == "lfcal-sweep/1"
    assert len(manifest["frames"]) == FRAMES
    assert (sweep / "white.png").is_file()
    truth = json.loads((sweep / "truth.json").read_text())
    assert truth["focus"]["object_distance_mm"] == pytest.approx(432.37)
    assert len(truth["frames"]) == FRAMES
    assert not list(sweep.parent.glob(".*partial*"))


def test_calibration_matches_truth_within_twice_the_targets(sweep: Path, result: dict) -> None:
    truth = json.loads((sweep / "truth.json").read_text())
    assert abs(result["a_mm"] / truth["a_mm"] - 1) < 1e-3
    assert abs(result["b_mm"] / truth["b_mm"] - 1) < 1e-3
    assert abs(result["Q"] / truth["Q"] - 1) < 1e-3
    assert abs(result["focus"]["object_distance_mm"] - truth["focus"]["object_distance_mm"]) < 2.0
    assert abs(result["focus"]["rail_mm"] - truth["focus"]["rail_mm"]) < 2.0
    tq = {f["index"]: f for f in truth["frames"]}
    worst = max(abs(f["patch_size_px"] - tq[f["index"]]["patch_size_px"]) for f in result["frames"])
    assert worst < 0.1
    assert result["mla"]["lens_pitch_px"] == pytest.approx(truth["mla"]["lens_pitch_px"], rel=1e-6)
    assert result["mla"]["image_pitch_px"] == pytest.approx(
        truth["mla"]["image_pitch_px"], rel=2e-4
    )
    assert result["mla"]["rotation_deg"] == pytest.approx(truth["mla"]["rotation_deg"], abs=0.01)


def test_result_json_has_the_documented_keys(result: dict) -> None:
    for key in (
        "a_mm",
        "b_mm",
        "Q",
        "patch_size_px",
        "uncertainty",
        "focus",
        "mla",
        "frames",
        "estimates",
        "priors",
        "corner_agreement",
        "camera_model",
    ):
        assert key in result
    for key in ("rail_mm", "object_distance_mm", "uncertainty_mm"):
        assert key in result["focus"]
    for key in ("lens_pitch_px", "image_pitch_px", "rotation_deg"):
        assert key in result["mla"]
    for frame in result["frames"]:
        for key in ("rail_mm", "Q", "patch_size_px", "Ls_px", "Lr_px", "La_mm"):
            assert key in frame
    assert result["uncertainty"]["a_mm"] > 0
    assert set(result["estimates"]) >= {"sweep", "paper_route", "paper_argmin_La"}
    for name in ("main_focal_mm", "mla_focal_mm", "rail_zero_object_distance_mm"):
        prior = result["priors"][name]
        assert set(prior) >= {"datasheet", "calibrated", "uncertainty", "z", "tolerance"}
        assert prior["determined_by"] == "sweep"  # both corners in view
    assert set(result["priors"]["L_mm"]) == {"calibrated", "uncertainty"}
    assert result["_plots"] == ["disparity.png", "focus.png"]


def test_result_records_the_priors_it_used(sweep: Path, result: dict) -> None:
    manifest = json.loads((sweep / "sweep.json").read_text())
    inputs = result["inputs"]
    # the manifest's values, with the documented default tolerances where it has none
    assert inputs["optics"] == {
        **manifest["optics"],
        "lens_pitch_px": pytest.approx(80.0),
        "main_focal_tolerance_mm": pytest.approx(0.02 * manifest["optics"]["main_focal_mm"]),
        "mla_focal_tolerance_mm": pytest.approx(0.02 * manifest["optics"]["mla_focal_mm"]),
    }
    assert inputs["board"] == manifest["board"]
    assert inputs["rail"] == {**manifest["rail"], "zero_object_distance_tolerance_mm": 2.0}
    assert inputs["camera"]["principal_point_px"] == manifest["camera"]["principal_point_px"]
    assert (inputs["camera"]["width"], inputs["camera"]["height"]) == (2400, 800)
    assert result["software"]["name"] == "lfcal-station" and result["software"]["version"]


def test_missing_and_corrupt_frames_are_skipped_and_reported(
    sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    damaged = tmp_path / "damaged"
    shutil.copytree(sweep, damaged)
    (damaged / "frames" / "0003.png").unlink()
    (damaged / "frames" / "0007.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    code = main(["calibrate", str(damaged), "--out", str(tmp_path / "r.json")])
    assert code == 0
    data = json.loads((tmp_path / "r.json").read_text())
    assert set(data["skipped_frames"]) == {"3", "7"}
    assert any("skipped" in w for w in data["warnings"])


def test_sweep_with_the_corner_never_found(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "blank"
    assert (
        main(
            [
                "simulate",
                str(out),
                "--preset",
                "rotated",
                "--frames",
                "6",
                "--step-mm",
                "15",
                "--width",
                "800",
                "--height",
                "800",
                "--principal-point",
                "3000,3000",
            ]
        )
        == 0
    )
    code = main(["calibrate", str(out), "--out", str(tmp_path / "partial.json")])
    err = capsys.readouterr().err
    assert code == 3
    assert "corner was found in only 0" in err
    assert "is the board aligned with the lens axis and in view?" in err
    partial = json.loads((tmp_path / "partial.json").read_text())
    assert len(partial["frames"]) == 6


def test_focus_outside_the_sweep_says_extend_the_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "far"
    # rotated focuses at rail 52.37 mm; this sweep covers 70..94 mm only
    assert (
        main(
            [
                "simulate",
                str(out),
                "--preset",
                "rotated",
                "--frames",
                "7",
                "--start-mm",
                "70",
                "--step-mm",
                "4",
                "--width",
                "2400",
                "--height",
                "800",
            ]
        )
        == 0
    )
    code = main(["calibrate", str(out), "--out", str(tmp_path / "partial.json")])
    err = capsys.readouterr().err
    assert code == 4
    assert "focus plane at the sweep edge" in err and "extend the range" in err
    partial = json.loads((tmp_path / "partial.json").read_text())
    assert len(partial["frames"]) == 7 and all(f["Q"] for f in partial["frames"])


def _restate(sweep: Path, out: Path, **changes: dict) -> Path:
    """A copy of ``sweep`` whose manifest states other (data-sheet) values."""
    shutil.copytree(sweep, out)
    manifest = json.loads((out / "sweep.json").read_text())
    for section, values in changes.items():
        manifest[section].update(values)
    (out / "sweep.json").write_text(json.dumps(manifest))
    return out


def test_wrong_data_sheet_values_are_replaced_by_the_sweep(
    sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """F +2 %, f -2 %, rail zero +2 mm in the manifest: the sweep measures the true ones."""
    truth = json.loads((sweep / "truth.json").read_text())
    manifest = json.loads((sweep / "sweep.json").read_text())
    optics, rail = manifest["optics"], manifest["rail"]
    off = _restate(
        sweep,
        tmp_path / "off",
        optics={
            "main_focal_mm": optics["main_focal_mm"] * 1.02,
            "mla_focal_mm": optics["mla_focal_mm"] * 0.98,
            # a tight stated tolerance on F: its 2 % error is a contradiction
            "main_focal_tolerance_mm": 0.002 * optics["main_focal_mm"],
        },
        rail={"zero_object_distance_mm": rail["zero_object_distance_mm"] + 2.0},
    )
    assert main(["calibrate", str(off), "--out", str(tmp_path / "r.json")]) == 0
    printed = capsys.readouterr().out
    data = json.loads((tmp_path / "r.json").read_text())
    priors = data["priors"]
    # twice the targets: a, b 0.1 %; F, f 0.2 %; rail zero 0.4 mm
    assert abs(data["a_mm"] / truth["a_mm"] - 1) < 1e-3
    assert abs(data["b_mm"] / truth["b_mm"] - 1) < 1e-3
    assert abs(priors["main_focal_mm"]["calibrated"] / truth["optics"]["F_mm"] - 1) < 2e-3
    assert abs(priors["mla_focal_mm"]["calibrated"] / truth["optics"]["f_mm"] - 1) < 2e-3
    true_zero = truth["rail"]["zero_object_distance_mm"]
    assert abs(priors["rail_zero_object_distance_mm"]["calibrated"] - true_zero) < 0.4
    assert priors["main_focal_mm"]["datasheet"] == pytest.approx(optics["main_focal_mm"] * 1.02)
    assert priors["main_focal_mm"]["contradicted"] and priors["main_focal_mm"]["z"] > 3
    assert not priors["mla_focal_mm"]["contradicted"]  # 2 % off, default tolerance 2 %
    assert any("main_focal_mm" in w and "contradicted" in w for w in data["warnings"])
    assert "CONTRADICTED" in printed and "data sheet" in printed
    # the paper's route trusts the wrong f: about 2 % off
    assert abs(data["estimates"]["paper_route"]["b_mm"] / truth["b_mm"] - 1) > 0.01


def test_the_focus_plane_does_not_depend_on_the_data_sheet(sweep: Path, tmp_path: Path) -> None:
    """f -2 % moves the first camera fit (made with a rough Q0); the defocus is refitted and
    the main images placed again on the final camera, so the focus plane, F and the rail
    zero agree with the exact data sheet's."""
    manifest = json.loads((sweep / "sweep.json").read_text())
    off = _restate(
        sweep, tmp_path / "off", optics={"mla_focal_mm": manifest["optics"]["mla_focal_mm"] * 0.98}
    )
    full = []
    for name, path in (("exact", sweep), ("off", off)):
        assert main(["calibrate", str(path), "--out", str(tmp_path / f"{name}.json")]) == 0
        full.append(json.loads((tmp_path / f"{name}.json").read_text()))
    # F and the rail zero come from the magnification, whose main images are placed on each
    # round's camera (not on the first one, where the data sheet's f still had a say)
    for key in ("main_focal_mm", "rail_zero_object_distance_mm"):
        e, w = full[0]["priors"][key], full[1]["priors"][key]
        assert abs(w["calibrated"] - e["calibrated"]) < 0.02 * e["uncertainty"]
    exact, wrong = (r["focus"] for r in full)
    assert abs(wrong["Q0"] - exact["Q0"]) < 0.05 * exact["Q0_se"]
    assert abs(wrong["object_distance_mm"] - exact["object_distance_mm"]) < (
        0.05 * exact["uncertainty_mm"]
    )


def test_impossible_data_sheet_values_name_the_prior(
    sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    far = _restate(sweep, tmp_path / "far", optics={"main_focal_mm": 900.0})
    assert main(["calibrate", str(far), "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert "main_focal_mm = 900 mm" in err and len(err.splitlines()) <= 2
    neg = _restate(sweep, tmp_path / "neg", rail={"zero_object_distance_tolerance_mm": -1.0})
    assert main(["calibrate", str(neg)]) == 2
    assert "rail.zero_object_distance_tolerance_mm" in capsys.readouterr().err


def test_standard_corner_only_falls_back_to_the_priors(tmp_path: Path) -> None:
    out = tmp_path / "standard"
    argv = ["simulate", str(out), "--preset", "rotated", "--frames", "13", "--step-mm", "8"]
    argv += ["--width", "900", "--height", "900", "--principal-point", "449.5,449.5"]
    assert main(argv) == 0
    assert main(["calibrate", str(out), "--out", str(tmp_path / "r.json")]) == 0
    data = json.loads((tmp_path / "r.json").read_text())
    truth = json.loads((out / "truth.json").read_text())
    assert data["corners_found"]["reference_frames"] == 0
    by = {k: data["priors"][k]["determined_by"] for k in ("main_focal_mm", "mla_focal_mm")}
    assert by["main_focal_mm"] == "prior"
    assert any("could not fix" in w and "main_focal_mm" in w for w in data["warnings"])
    # the tolerances (2 % by default) are carried in the uncertainty of b and a
    assert data["uncertainty"]["b_mm"] > 0.003 * data["b_mm"]
    assert abs(data["b_mm"] - truth["b_mm"]) < 3 * data["uncertainty"]["b_mm"]
    assert abs(data["a_mm"] - truth["a_mm"]) < 3 * data["uncertainty"]["a_mm"]


def test_a_sweep_that_never_defocuses_gives_focus_not_determined(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "flat"
    # rotated focuses at rail 52.37 mm: 8 frames within ±1.75 mm keep the blur under 0.1 px
    argv = ["simulate", str(out), "--preset", "rotated", "--frames", "8", "--start-mm", "50.6"]
    argv += ["--step-mm", "0.5", "--width", "2400", "--height", "800"]
    assert main(argv) == 0
    code = main(["calibrate", str(out), "--out", str(tmp_path / "partial.json")])
    err = capsys.readouterr().err
    assert code == 4
    assert "focus plane not determined" in err
    partial = json.loads((tmp_path / "partial.json").read_text())
    assert len(partial["frames"]) == 8 and "a_mm" not in partial


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["simulate", "{tmp}/x", "--preset", "nosuch"], "unknown preset 'nosuch'"),
        (["simulate", "{tmp}/x", "--width", "50", "--height", "50"], "smaller than one lens"),
        (
            ["simulate", "/proc/forbidden/x", "--frames", "1", "--width", "300", "--height", "300"],
            "cannot write",
        ),
        (["calibrate", "{tmp}/does-not-exist"], "no such sweep directory"),
        (["simulate", "{tmp}/x", "--b-mm", "2.0"], "b = 2.0 mm must exceed f"),
        (["simulate", "{tmp}/x", "--mla-pitch-mm", "-0.25"], "D = -0.25"),
    ],
)
def test_bad_input_gives_one_clear_line(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert message in err
    assert len(err.splitlines()) == 1
    assert not (tmp_path / "x" / "sweep.json").exists()


def test_invalid_manifest_is_reported_with_its_key(
    sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(sweep, broken)
    manifest = json.loads((broken / "sweep.json").read_text())
    del manifest["optics"]["mla_pitch_mm"]
    manifest["camera"]["bit_depth"] = "12"
    (broken / "sweep.json").write_text(json.dumps(manifest))
    assert main(["calibrate", str(broken)]) == 2
    err = capsys.readouterr().err
    assert "optics.mla_pitch_mm" in err and "camera.bit_depth" in err


def test_calibrated_patch_size_renders_with_fewer_seams(sweep: Path, result: dict) -> None:
    """Render a fine checkerboard at the calibrated focus plane with the calibrated p."""
    import numpy as np

    from calibration.board import Board
    from calibration.lens_grid import LensGrid
    from calibration.presets import get_preset
    from calibration.rendering import seam_scan, seamless_patch_px
    from calibration.sim_sweep import fit_frame
    from calibration.simulator import render_frame

    cam = fit_frame(get_preset("rotated"), 2400, 800).camera
    fine = replace(cam, board=Board(square_mm=1.0, reference_gap_mm=0.0))
    raw = render_frame(fine, object_distance_mm=result["focus"]["object_distance_mm"], seed=9)
    g = result["mla"]["image_grid"]
    grid = LensGrid(tuple(g["origin_px"]), g["pitch_px"], np.radians(g["rotation_deg"]))

    def render_p(p: float) -> float:
        return seamless_patch_px(
            p,
            lens_pitch_px=result["mla"]["lens_pitch_px"],
            image_pitch_px=result["mla"]["image_pitch_px"],
        )

    p_cal = result["patch_size_px"]
    designed = 20.0  # the nominal p of a b/a = 0.25 design, 80 px lens pitch
    sizes = [render_p(p) for p in (p_cal, designed, 0.9 * p_cal, 1.1 * p_cal)]
    scores = seam_scan(raw, image_grid=grid, patch_sizes_px=sizes)
    assert scores[0] < min(scores[1:])


def test_an_unusable_white_image_is_reported_and_stops_the_workers(
    sweep: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The analysis processes start while the white image is read and fitted; when it cannot
    be, the calibration says so and leaves no worker behind."""
    from calibration import pipeline

    broken = tmp_path / "broken-white"
    shutil.copytree(sweep, broken)
    white = (broken / "white.png").read_bytes()
    (broken / "white.png").write_bytes(white[: len(white) // 2])
    started: list[int] = []
    real_start = pipeline._start_pool

    def start_pool(root: str, workers: int) -> pipeline.ProcessPoolExecutor:
        pool = real_start(root, workers)
        started.extend(p.pid for p in pool._processes.values())  # type: ignore[union-attr]
        return pool

    monkeypatch.setattr(pipeline, "_start_pool", start_pool)
    code = main(["calibrate", str(broken)])
    err = capsys.readouterr().err
    assert code != 0
    assert "white image unusable" in err and "white.png" in err
    assert len(started) >= 2
    for pid in started:  # joined by the pool's shutdown before the error was reported
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
