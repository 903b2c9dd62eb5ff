"""The plumbing of the focus benchmark (``bench/bench_focus.py``), fast.

* the truth of each renderer's own ``truth.json`` format (built by the
  renderers' own truth writers, no rendering) is read right: errors, sigmas
  and z of a result that is off by known amounts, and mcsim's record of the
  manifest's (wrong) data sheet is not taken for the truth;
* a wrong-data-sheet variant differs from its render only in the manifest, by
  exactly the offsets;
* end to end on a tiny simulator sweep (8 frames, standard corner only): the
  rows are produced, the core says that F and the rail zero came from the
  data sheet, a calibration the core refuses is a failed row with its message;
* the coverage rows count seeds within 1 and 3 sigma, leaving out quantities
  taken from the data sheet.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.bench_focus import NO_COS4, RANDOM_CAMERAS, Run, random_cameras_group, select
from bench.crosscheck import indsim
from bench.focus import cache
from bench.focus.configs import (
    ACCURACY,
    ALL_OFF,
    EXACT,
    RANDOM_MIN_BLUR_PX,
    PriorOffset,
    SweepConfig,
    _rendered_frame,
    coverage_config,
    no_cos4_config,
    placement_shift_px,
    principal_point_px,
    random_camera_config,
    repeat_config,
)
from bench.focus.evaluate import (
    Comparison,
    compare,
    coverage_bounds,
    coverage_rows,
    repeat_rows,
    rim_pull_rows,
)
from bench.focus.summary import accuracy_lines, coverage_lines, repeat_lines, rim_pull_lines
from bench.mcsim.__main__ import parser as mcsim_parser
from bench.mcsim.archive import truth as mcsim_truth
from bench.mcsim.spec import build_spec
from bench.wavesim.__main__ import parser as wavesim_parser
from bench.wavesim.settings import build_wave_spec
from bench.wavesim.sweep import wave_truth
from calibration.archive import SweepArchive
from calibration.presets import get_preset, with_sweep
from calibration.sim_sweep import truth as sim_truth
from station.summary_table import truth_value

TRUTH_KEYS: dict[str, tuple[str | tuple[str, ...], ...]] = {
    # what each format calls a, b, u0, F, f, rail zero
    "sim": (
        "a_mm",
        "b_mm",
        ("focus", "object_distance_mm"),
        ("optics", "F_mm"),
        ("optics", "f_mm"),
        ("rail", "zero_object_distance_mm"),
    ),
    "indsim": ("a_f_mm", "b_mm", "u0_mm", "F_mm", "f_mm", "u_rail0_mm"),
    "mcsim": ("a_f_mm", "b_mm", "u0_mm", "F_mm", "f_mm", "u_rail0_mm"),
}


def _get(data: dict[str, Any], key: str | tuple[str, ...]) -> float:
    for part in (key,) if isinstance(key, str) else key:
        data = data[part]
    return float(data)  # type: ignore[arg-type]


def _truths() -> dict[str, dict[str, Any]]:
    sim = sim_truth(with_sweep(get_preset("rotated"), frames=3, start_mm=40.0, step_mm=10.0))
    cam = indsim.Camera(F=50.0, f=2.0, D=0.2, b=2.4, u0=400.0, W=800, H=600)
    frames = [{"index": k, "rail_mm": 10.0 * k, "u_mm": 380.0 + 10.0 * k} for k in range(3)]
    ind = indsim.truth_dict(cam, frames, 380.0, 1)
    spec = build_spec(
        preset="small",
        frames=3,
        manifest_main_focal_mm=30.0,
        manifest_mla_focal_mm=1.2,
        manifest_rail_zero_mm=160.0,
    )
    return {"sim": sim, "indsim": ind, "mcsim": mcsim_truth(spec)}


@pytest.mark.parametrize("renderer", ["sim", "indsim", "mcsim"])
def test_truth_of_each_renderer_is_read(renderer: str) -> None:
    truth = _truths()[renderer]
    a, b, u0, F, f, rail0 = (_get(truth, k) for k in TRUTH_KEYS[renderer])
    p_key = "patch_size_px" if renderer == "sim" else "p_px"
    frames = [
        {
            "index": fr["index"],
            "patch_size_px": fr[p_key] + (0.004 if fr["index"] == 1 else -0.001),
            "patch_size_measured_px": fr[p_key] - (0.03 if fr["index"] == 2 else 0.0),
        }
        for fr in truth["frames"]
    ]
    result = {
        "a_mm": a * (1 + 2e-4),
        "b_mm": b * (1 - 1e-4),
        "main_focal_mm": F * (1 + 5e-4),
        "mla_focal_mm": f * (1 - 3e-4),
        "uncertainty": {
            "a_mm": a * 1e-4,
            "b_mm": b * 2e-4,
            "main_focal_mm": F * 1e-3,
            "mla_focal_mm": f * 1e-4,
        },
        "focus": {"object_distance_mm": u0 - 0.12, "uncertainty_mm": 0.06},
        "priors": {
            "main_focal_mm": {"determined_by": "sweep"},
            "mla_focal_mm": {"determined_by": "sweep"},
            "rail_zero_object_distance_mm": {
                "calibrated": rail0 + 0.05,
                "uncertainty": 0.1,
                "determined_by": "prior",
            },
        },
        "estimates": {"paper_route": {"a_mm": a * (1 - 3e-4), "a_se_mm": a * 3e-4}},
        "frames": frames,
        "corners_found": {"reference_frames": 3},
    }
    length = truth_value(truth, "L_mm")
    assert length is not None
    result["mla"] = {"scale": (length + b) / length - 1.5e-5}  # the rims pulled
    result["camera_model"] = {"image_scale": {"rim_shading": -1.6e-5}}
    cmp = compare(result, truth)
    assert cmp.white_pull == pytest.approx(-1.5e-5, rel=1e-6)
    assert cmp.rim_model == -1.6e-5
    expected = {
        "focus": (-0.12, 0.06),
        "a": (0.02, 0.01),
        "b": (-0.01, 0.02),
        "F": (0.05, 0.1),
        "f": (-0.03, 0.01),
        "rail0": (0.05, 0.1),
        "a_route": (-0.03, 0.03),
    }
    for key, (error, sigma) in expected.items():
        entry = cmp.values[key]
        assert entry["error"] == pytest.approx(error, rel=1e-6, abs=1e-9), key
        assert entry["sigma"] == pytest.approx(sigma, rel=1e-6), key
        assert entry["z"] == pytest.approx(error / sigma, rel=1e-6), key
    assert cmp.values["rail0"]["determined_by"] == "prior"
    assert cmp.fell_back == ["rail_zero_object_distance_mm"]
    assert cmp.p_frames == 3
    assert cmp.worst_p_px == pytest.approx(0.004, abs=1e-9)
    assert cmp.worst_measured_p_px == pytest.approx(0.03, abs=1e-9)


def test_mcsim_manifest_priors_are_not_the_truth() -> None:
    truth = _truths()["mcsim"]
    assert truth["manifest_priors"]["main_focal_mm"] == 30.0
    result = {"main_focal_mm": truth["F_mm"], "uncertainty": {"main_focal_mm": 0.01}}
    assert compare(result, truth).values["F"]["error"] == pytest.approx(0.0, abs=1e-12)


TINY = SweepConfig(
    "sim",
    "tiny-standard",
    ("--preset", "paper", "--width", "1024", "--height", "1024", "--frames", "8")
    + ("--start-mm", "22", "--step-mm", "8"),
    5,
    "8 frames of a 1024x1024 window: the standard corner only",
    priors=(EXACT, ALL_OFF),
    standard_only=True,
)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, cache.Render]:
    root = tmp_path_factory.mktemp("focus")
    render = cache.render(TINY, root)
    assert render.error is None, render.error
    return root, render


def test_render_is_cached_by_its_command(tiny: tuple[Path, cache.Render]) -> None:
    root, render = tiny
    assert render.seconds is not None and (render.path / "truth.json").is_file()
    again = cache.render(TINY, root)
    assert again.seconds is None and again.path == render.path
    other_seed = SweepConfig(TINY.renderer, TINY.name, TINY.args, TINY.seed + 1, TINY.about)
    assert cache.is_cached(root, TINY) and not cache.is_cached(root, other_seed)


def test_wrong_datasheet_variant_changes_only_the_manifest(tiny: tuple[Path, cache.Render]) -> None:
    _, render = tiny
    base = json.loads((render.path / "sweep.json").read_text())
    truth = json.loads((render.path / "truth.json").read_text())
    variant = cache.priors_variant(render.path, ALL_OFF)
    assert cache.priors_variant(render.path, EXACT) == render.path
    changed = json.loads((variant / "sweep.json").read_text())
    expected = copy.deepcopy(base)
    expected["optics"]["main_focal_mm"] = truth["optics"]["F_mm"] * 0.98
    expected["optics"]["mla_focal_mm"] = truth["optics"]["f_mm"] * 1.02
    expected["rail"]["zero_object_distance_mm"] = truth["rail"]["zero_object_distance_mm"] - 2.0
    assert _close(changed, expected), (changed, expected)
    archive = SweepArchive.open(variant)
    assert archive.path_of(base["white"]).resolve() == (render.path / base["white"]).resolve()
    first = base["frames"][0]["file"]
    assert archive.path_of(first).resolve() == (render.path / first).resolve()
    assert json.loads((variant / "truth.json").read_text()) == truth


def _close(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_close(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(map(_close, a, b))
    if isinstance(a, float) or isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-12)
    return bool(a == b)


def test_rows_on_a_tiny_standard_only_sweep(tiny: tuple[Path, cache.Render]) -> None:
    root, render = tiny
    run = Run(root, jobs=1)
    run.accuracy(TINY, render)
    names = [r["name"] for r in run.rows]
    head = "sim tiny-standard [exact]: "
    for label in ("focus-plane error", "a error", "b error", "worst per-frame p error"):
        assert head + label in names, names
    exact = {r["name"][len(head) :]: r for r in run.rows if r["name"].startswith(head)}
    fell = exact["F and rail zero fell back to priors"]
    assert fell["ok"] is True and fell["value"] == 1.0, fell
    # F from the data sheet: no target, and its uncertainty carries the tolerance
    assert exact["F error"]["target"] is None and "data sheet" in exact["F error"]["note"]
    F = run.details[0]["quantities"]["F"]
    assert F["determined_by"] == "prior" and abs(F["z"]) < 3.0
    assert exact["focus-plane error"]["value"] < 1.0  # mm, a sanity bound for 8 frames
    off = [r for r in run.rows if r["name"].startswith(f"sim tiny-standard [{ALL_OFF.name}]")]
    assert off and all(r["unit"] in ("sigma", "px", "bool") for r in off), off
    line = next(x for x in accuracy_lines(run.rows) if x.startswith(head[:-2]))
    assert line.endswith("yes"), line  # the summary line says F and the rail zero fell back
    detail = run.details[0]
    assert detail["exit_code"] == 0 and Path(detail["result"]).is_file()
    # the calibration's truth comparison used this sweep's truth.json
    truth = json.loads((render.path / "truth.json").read_text())
    assert detail["quantities"]["a"]["truth"] == truth["a_mm"]


def test_a_refused_calibration_is_a_failed_row(tiny: tuple[Path, cache.Render]) -> None:
    root, render = tiny
    absurd = PriorOffset("F x20", "F-x20", main_focal_rel=19.0)
    config = SweepConfig(
        TINY.renderer, TINY.name, TINY.args, TINY.seed, TINY.about, priors=(absurd,)
    )
    run = Run(root, jobs=1)
    run.accuracy(config, render)
    assert len(run.rows) == 1
    row = run.rows[0]
    assert row["ok"] is False and row["value"] == 2.0  # PriorError: exit 2
    assert "FAILED" in row["name"] and "main_focal_mm" in row["note"]


def _comparison(z: dict[str, float], by: str = "sweep") -> Comparison:
    cmp = Comparison()
    for key, value in z.items():
        cmp.values[key] = {"error": 0.1 * value, "sigma": 0.1, "z": value, "determined_by": by}
    return cmp


def test_coverage_rows_count_seeds_within_one_and_three_sigma() -> None:
    zs = [0.5, -0.9, 1.5, 2.5, -4.0]
    comparisons = [_comparison({"a": z, "F": z}, by="sweep") for z in zs]
    comparisons[0].values["F"]["determined_by"] = "prior"  # left out
    rows = {r["name"]: r for r in coverage_rows("sim", "exact", comparisons, attempted=6)}
    seeds = rows["sim coverage [exact]: seeds calibrated"]
    assert seeds["value"] == 5 and seeds["ok"] is False
    one = rows["sim coverage [exact]: a error within 1 sigma (5 seeds)"]
    three = rows["sim coverage [exact]: a error within 3 sigma (5 seeds)"]
    assert one["value"] == pytest.approx(2 / 5) and three["value"] == pytest.approx(4 / 5)
    assert three["ok"] is False  # one of five beyond 3 sigma is far too many
    assert "sim coverage [exact]: F error within 1 sigma (4 seeds)" in rows
    rms = rows["sim coverage [exact]: a error RMS error/sigma"]["value"]
    assert rms == pytest.approx(math.sqrt(sum(z * z for z in zs) / 5))
    lo, hi, least3 = coverage_bounds(20)
    assert (lo, hi, least3) == (9, 17, 19)


def test_rim_pull_rows_compare_the_white_pitch_with_the_rim_term() -> None:
    """What the rim term leaves of the lattice's scale error, over the seeds that have both."""
    pulls = [(-1.8e-5, -2.0e-5), (-2.1e-5, -2.0e-5), (-0.9e-5, -1.0e-5), (math.nan, -1e-5)]
    comparisons = []
    for pull, model in pulls:
        cmp = Comparison()
        cmp.white_pull, cmp.rim_model = pull, model
        comparisons.append(cmp)
    rows = rim_pull_rows("mcsim", comparisons)
    assert len(rows) == 1
    row = rows[0]
    assert row["name"] == "mcsim coverage [exact]: white pitch's error after the rim term"
    left = [2e-6, -1e-6, 1e-6]
    assert row["value"] == pytest.approx(np.mean(left))
    assert f"sd {np.std(left, ddof=1):.1e} over 3 seeds" in row["note"]
    assert "pull / term 0.96" in row["note"]  # -4.8e-5 / -5.0e-5
    assert row["ok"] is None  # a measurement of the renderer, not a target
    # a white without shading: nothing to correct, no ratio
    flat = Comparison()
    flat.white_pull, flat.rim_model = 1.2e-6, -1e-8
    unshaded = rim_pull_rows("mcsim", [flat, flat])[0]
    assert unshaded["value"] == pytest.approx(1.21e-6) and "no term" in unshaded["note"]
    # the summary shows them apart from the coverage table
    assert coverage_lines(rows) == coverage_lines([])
    lines = rim_pull_lines(rows)
    assert len(lines) == 2 and lines[1].startswith("mcsim coverage") and "+6.7e-07" in lines[1]
    assert rim_pull_lines([]) == [] and rim_pull_rows("sim", [Comparison()]) == []


def test_repeat_rows_separate_the_bias_from_the_scatter() -> None:
    """Seeds of one accuracy sweep: signed mean error, sample sd, RMS against the target."""
    errors = [0.02, 0.04, 0.03, 0.05]  # a, %: a bias of 0.035 % with a small scatter
    comparisons = []
    for e in errors:
        cmp = Comparison()
        cmp.values["a"] = {"error": e, "sigma": 0.04, "z": e / 0.04, "determined_by": None}
        comparisons.append(cmp)
    config = repeat_config(TINY, 2)
    assert config.seed == TINY.seed + 2000 and config.priors == (EXACT,)
    assert config.name == "tiny-standard-s2" and config.args[:-1] == TINY.args
    rows = {r["name"]: r for r in repeat_rows(TINY, comparisons)}
    head = "sim tiny-standard repeats [exact, 4 seeds]: a error "
    assert rows[head + "mean"]["value"] == pytest.approx(0.035)
    assert rows[head + "sd over seeds"]["value"] == pytest.approx(np.std(errors, ddof=1))
    rms = rows[head + "RMS"]
    assert rms["value"] == pytest.approx(math.sqrt(np.mean(np.square(errors))))
    assert rms["target"] == 0.03 and rms["ok"] is False  # every seed is off the same way
    assert not any("focus" in name for name in rows)  # no focus errors given: no rows
    # the summary keeps them out of the per-calibration lines and shows them apart
    assert all("repeats" not in line for line in accuracy_lines(list(rows.values())))
    lines = repeat_lines(list(rows.values()))
    assert len(lines) == 2 and "+0.0350" in lines[1] and lines[1].rstrip().endswith("*")


def test_each_repeat_moves_the_image_by_a_fraction_of_a_pixel() -> None:
    """Repeats differ in the seed and in where the image falls on the pixels: the principal
    point of every renderer's accuracy sweep moves by the repeat's shift (in [0, 1) px,
    different for each repeat), and the mcsim sweep whose frame is fitted keeps that
    frame's size instead of fitting it again (which would place the principal point anew)."""
    shifts = {placement_shift_px(k) for k in range(1, 6)}
    assert len(shifts) == 5 and all(0 < d < 1 for s in shifts for d in s)
    for configs in ACCURACY.values():
        for config in configs:
            base = principal_point_px(config)
            repeat = repeat_config(config, 3)
            assert "--fit-frame" not in repeat.args
            moved = principal_point_px(repeat)
            assert np.subtract(moved, base) == pytest.approx(placement_shift_px(3), abs=1e-6)
    fitted = next(c for c in ACCURACY["mcsim"] if "--fit-frame" in c.args)
    # the fitted frame of the base render: 1232 x 1232 with its principal point at 613.5, 617.5
    assert principal_point_px(fitted) == (613.5, 617.5)
    assert repeat_config(fitted, 1).args[-5:-1] == ("--width", "1232", "--height", "1232")


def test_repeats_are_calibrated_with_the_exact_data_sheet(tiny: tuple[Path, cache.Render]) -> None:
    root, render = tiny
    run = Run(root, jobs=1)
    first = run.accuracy(TINY, render)
    assert first is not None
    repeat = repeat_config(TINY, 1)
    renders = {(repeat.renderer, repeat.name): cache.render(repeat, root)}
    run.repeats(TINY, first, [repeat], renders)
    details = [d for d in run.details if d["config"] == repeat.name]
    assert [d["priors"] for d in details] == ["exact"]
    names = [r["name"] for r in run.rows if " repeats [" in r["name"]]
    assert "sim tiny-standard repeats [exact, 2 seeds]: a error RMS" in names, names
    # another seed: another noise realisation, so another error
    errors = {
        d["config"]: d["quantities"]["a"]["error"] for d in run.details if d["priors"] == "exact"
    }
    assert errors[TINY.name] != errors[repeat.name]
    # and the image moved against the pixel grid by the repeat's fraction of a pixel
    pp = [
        json.loads((path / "truth.json").read_text())["sensor"]["principal_point_px"]
        for path in (render.path, cache.sweep_dir(root, repeat))
    ]
    assert np.subtract(pp[1], pp[0]) == pytest.approx(placement_shift_px(1))


def test_random_cameras_are_valid_mcsim_sweeps_that_defocus() -> None:
    """Each random camera is an mcsim command line the renderer accepts, drawn the same way
    every time, all different, at the issue's sampling (30 rays, 2x2 fixed points), both
    corners, its own sensor noise and exposure; its sweep defocuses by at least
    RANDOM_MIN_BLUR_PX at one end and passes through the focus plane (by mcsim's own
    truth, not by the formula that drew it)."""
    configs = [random_camera_config(k) for k in range(8)]
    assert [c.args for c in configs] == [random_camera_config(k).args for k in range(8)]
    assert len({c.args for c in configs}) == 8 and len({c.seed for c in configs}) == 8
    for config in configs:
        assert config.renderer == "mcsim" and config.coverage and config.priors[0] == EXACT
        options = vars(mcsim_parser().parse_args(["-", *config.args]))
        # its own sensor, exposed below full scale
        assert 3000 <= options["photons"] <= 40000 and 2 <= options["read_noise_e"] <= 8
        assert options["bit_depth"] in (12, 16) and options["black_level"] in (0, 64)
        assert 0.6 <= options["exposure"] < 1 and 0.7 <= options["white_exposure"] < 1
        for name in ("out_dir", "force", "jobs"):
            options.pop(name)
        truth = mcsim_truth(build_spec(**options))
        render = truth["render"]
        assert (render["rays_per_subpixel"], render["subpixels_per_axis"]) == (30, 2)
        assert render["subpixel_jitter"] is False and render["corners"] == ["standard", "reference"]
        blur = [f["defocus_blur_px"] for f in truth["frames"]]
        assert max(blur) >= RANDOM_MIN_BLUR_PX - 1e-6
        q = np.array([f["Q"] for f in truth["frames"]])
        assert q.min() < truth["Q_focus"] < q.max()


def test_no_cos4_sweeps_are_mcsims_coverage_sweeps_without_cos4_on_request() -> None:
    """``--configs nocos4``: mcsim's coverage sweeps, same seeds and rail phases, rendered
    with every ray counted alike; never in the default run."""
    config = no_cos4_config(3)
    base = coverage_config("mcsim", 3)
    assert config.renderer == "mcsim" and config.name == "nocos4-s03"
    assert config.args == (*base.args, "--no-cos4") and config.seed == base.seed
    assert config.coverage and config.priors == base.priors
    options = vars(mcsim_parser().parse_args(["out", *config.args, "--seed", str(config.seed)]))
    for name in ("out_dir", "force", "jobs"):
        options.pop(name)
    assert mcsim_truth(build_spec(**options))["render"]["cos4_weighting"] is False
    _, named = select(("mcsim",), ("nocos4",), 2, False)
    assert [c.name for c in named[NO_COS4]] == ["nocos4-s00", "nocos4-s01"]
    assert NO_COS4 not in select(("sim", "mcsim"), None, 3, False)[1]
    assert select(("sim",), ("nocos4",), 3, False)[1] == {}


def test_random_cameras_join_the_full_run_not_the_quick_one() -> None:
    """The full benchmark and ``--configs random`` include mcsim's random cameras as their
    own coverage group; ``--quick`` and a run without mcsim do not. wavesim's are drawn
    only when asked for (``--configs random`` with wavesim): the same cameras."""
    _, full = select(("sim", "mcsim", "wavesim"), None, 3, False)
    assert [c.name for c in full[RANDOM_CAMERAS]] == ["random-c00", "random-c01", "random-c02"]
    assert random_cameras_group("wavesim") not in full
    _, named = select(("mcsim",), ("random",), 2, False)
    assert set(named) == {RANDOM_CAMERAS}
    assert RANDOM_CAMERAS not in select(("sim", "mcsim"), None, 3, True)[1]
    assert RANDOM_CAMERAS not in select(("sim",), None, 3, False)[1]
    _, both = select(("mcsim", "wavesim"), ("random",), 2, False)
    assert set(both) == {RANDOM_CAMERAS, random_cameras_group("wavesim")}
    waves = both[random_cameras_group("wavesim")]
    assert [c.renderer for c in waves] == ["wavesim"] * 2
    assert [c.seed for c in waves] == [c.seed for c in both[RANDOM_CAMERAS]]


def test_random_cameras_of_wavesim_are_mcsims_in_wave_optics() -> None:
    """wavesim's random camera ``k`` is mcsim's camera ``k`` (the same optics, sweep, sensor
    and exposure) without the ray tracer's sampling options, a command line wavesim's own
    parser accepts, in green light; its truth's focus plane lies inside the sweep."""
    for k in range(4):
        ray, wave = random_camera_config(k, "mcsim"), random_camera_config(k, "wavesim")
        assert wave.renderer == "wavesim" and wave.name == ray.name
        assert " ".join(wave.args) == " ".join(ray.args).replace("--rays 30 --subpixel 2 ", "")
        options = vars(wavesim_parser().parse_args(["-", *wave.args]))
        for name in ("out_dir", "force", "jobs", "preset"):
            options.pop(name)
        truth = wave_truth(build_wave_spec(**{n: v for n, v in options.items() if v is not None}))
        assert truth["render"]["wavelengths_um"] == [0.55]
        q = np.array([f["Q"] for f in truth["frames"]])
        assert q.min() < truth["Q_focus"] < q.max()
    with pytest.raises(ValueError, match="random cameras"):
        random_camera_config(0, "indsim")


def test_wavesim_sweeps_are_rendered_and_moved_on_the_pixels_by_the_fourier_renderer() -> None:
    """The Fourier-optics renderer's sweeps: its own module renders them, and a repeat moves
    the image against the pixel grid through its principal point, read by its own parser
    (the frame it fitted kept, so the move does not fit the frame again)."""
    config = next(c for c in ACCURACY["wavesim"] if "--fit-frame" in c.args)
    command = cache.render_command(config, Path("out-dir"), jobs=2)
    assert command[1:3] == ["-m", "bench.wavesim"]
    assert command[3:5] == ["out-dir", "--seed"]
    (x, y), width, height = _rendered_frame(config)
    moved = repeat_config(config, 1)
    assert "--fit-frame" not in moved.args
    assert _rendered_frame(moved)[1:] == (width, height)
    dx, dy = placement_shift_px(1)
    np.testing.assert_allclose(_rendered_frame(moved)[0], (x + dx, y + dy), atol=1e-4)
