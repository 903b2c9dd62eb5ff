"""Tests of station.config: TOML loading, validation and problem reports (real files)."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from calibration.archive import validate_manifest
from station.config import (
    ConfigError,
    ConfigProblem,
    StationConfig,
    check_config_file,
    config_check_main,
    load_config,
)
from station.config_sections import RailConfig
from station.devices import transport_settings

REPO = Path(__file__).resolve().parents[1]
SIMULATED = REPO / "config" / "simulated.toml"
LAB = REPO / "config" / "lab-example.toml"
MINIMAL = "[rail]\nzero_object_distance_mm = 250.0\n"
KEY_A = "a" * 16 + "-alpha"
KEY_B = "b" * 16 + "-bravo"


def write(tmp_path: Path, text: str, name: str = "station.toml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def problems_of(path: Path, env: dict[str, str] | None = None) -> list[ConfigProblem]:
    with pytest.raises(ConfigError) as err:
        load_config(path, env=env or {})
    assert isinstance(err.value, ValueError)
    return err.value.problems


def keyed(problems: list[ConfigProblem]) -> dict[str, str]:
    return {p.key: p.reason for p in problems}


# ------------------------------------------------------------------ shipped configs


def test_simulated_config_loads() -> None:
    cfg = load_config(SIMULATED, env={})
    assert cfg.source == SIMULATED
    assert cfg.camera.backend == "simulated" and cfg.camera.preset == "paper"
    assert cfg.camera.sensor_size_px == (2816, 1024) and cfg.camera.bit_depth == 12
    assert cfg.rail.driver == "emulated" and cfg.rail.port is None
    assert cfg.xy_stage.driver == "emulated" and cfg.xy_shares_rail_chain
    assert cfg.rail.object_distance_mm(50.0) == 300.0  # the paper's focus plane
    assert cfg.sweep.frame_count == 100 and cfg.sweep.positions_mm()[-1] == 99.0
    assert cfg.storage.data_dir == REPO / "data"
    assert cfg.storage.database == REPO / "data" / "lfcal.sqlite3"
    assert cfg.server.host == "127.0.0.1" and cfg.server.port == 8000


def test_lab_example_config_loads(tmp_path: Path) -> None:
    cfg = load_config(LAB, env={})
    assert cfg.camera.backend == "aravis" and cfg.camera.address == "192.168.10.20"
    assert cfg.camera.sensor_size_px == (5120, 5120)
    assert cfg.rail.driver == "zaber" and cfg.rail.port == "/dev/ttyUSB0"
    assert cfg.xy_shares_rail_chain and cfg.xy_stage_port == "/dev/ttyUSB0"
    assert (cfg.xy_stage.x.device, cfg.xy_stage.x.axis) == (2, 1)
    assert (cfg.xy_stage.y.device, cfg.xy_stage.y.axis) == (2, 2)
    assert cfg.storage.data_dir == Path("/var/lib/lfcal/data")
    transport = transport_settings(cfg)
    assert (transport.packet_size, transport.buffer_count) == (8192, 4)
    assert transport.packet_resend and transport.packet_socket is None  # automatic
    ring = load_config(
        write(tmp_path, LAB.read_text().replace("# packet_socket = true", "packet_socket = true")),
        env={},
    )
    assert transport_settings(ring).packet_socket is True


def test_config_check_main(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert config_check_main(SIMULATED) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"OK: {SIMULATED}: camera simulated (preset paper")
    bad = write(tmp_path, "[rail]\ndriver = 'zaber'\nzero_object_distance_mm = 250.0\n")
    assert config_check_main(bad) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [
        f'{bad}: rail.port: field required (driver = "zaber" needs a port such as '
        "/dev/ttyUSB0 or socket://host:port)"
    ]
    assert check_config_file(LAB) == []
    assert check_config_file(bad) == err


def test_minimal_config_uses_defaults(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, MINIMAL), env={})
    assert cfg.camera.backend == "simulated" and cfg.camera.sensor_size_px == (5120, 5120)
    assert cfg.board.square_mm == 10.0 and cfg.board.reference_gap_mm == 0.1
    assert cfg.sweep.start_mm == 0.0 and cfg.sweep.stop_mm == 99.0 and cfg.sweep.step_mm == 1.0
    assert cfg.server.api_keys == [] and cfg.server.cors_origins == []
    header = cfg.manifest_header(width=1200, height=1000, principal_point_px=(599.5, 499.5))
    assert validate_manifest(header) == []


# ------------------------------------------------------------------ each kind of error


def test_toml_syntax_error_has_line_and_column(tmp_path: Path) -> None:
    path = write(tmp_path, "[rail]\nzero_object_distance_mm = 250.0\nport = \n")
    (p,) = problems_of(path)
    assert p.file == str(path) and p.key == "line 3, column 8"
    assert p.reason.startswith("TOML syntax error")
    assert str(p) == f"{path}: line 3, column 8: {p.reason}"


def test_missing_file(tmp_path: Path) -> None:
    (p,) = problems_of(tmp_path / "nope.toml")
    assert str(p) == f"{tmp_path / 'nope.toml'}: file not found"


def test_unknown_keys_and_sections(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + "max_speed = 3\n[camra]\n[camera]\nexposure = 5\n")
    got = keyed(problems_of(path))
    assert got["rail.max_speed"] == "unknown key (did you mean 'max_speed_mm_s'?)"
    assert got["camra"] == "unknown section (did you mean 'camera'?)"
    assert got["camera.exposure"] == "unknown key (did you mean 'exposure_us'?)"


@pytest.mark.parametrize(
    ("toml", "key", "reason"),
    [
        (
            "[camera]\nexposure_us = '1000'",
            "camera.exposure_us",
            "must be a valid number, got '1000'",
        ),
        (
            "[camera]\nbackend = 'gige'",
            "camera.backend",
            "must be 'simulated', 'aravis' or 'harvesters'",
        ),
        (
            "[camera]\npixel_format = 'RGB8'",
            "camera.pixel_format",
            "must be 'Mono8', 'Mono10',",
        ),
        (
            "[camera]\nroi = { width = 10.5, height = 4 }",
            "camera.roi.width",
            "must be a valid integer",
        ),
        ("[rail]\ndevice = true", "rail.device", "must be a valid integer, got true"),
        ("[rail]\ndirection = 0", "rail.direction", "must be 1 or -1, got 0"),
        ("[rail]\nbaud_rate = 12345", "rail.baud_rate", "must be one of 9600, 19200"),
        (
            "[rail]\ndriver = 'zaber'\nport = 'tcp://x:1'",
            "rail.port",
            "unknown pyserial URL scheme 'tcp'",
        ),
        (
            "[rail]\ndriver = 'zaber'\nport = 'socket://host'",
            "rail.port",
            "socket:// needs host:port",
        ),
        ("[server]\nport = 70000", "server.port", "must be less than or equal to 65535, got 70000"),
        ("[server]\napi_keys = 'k'", "server.api_keys", "must be a valid list"),
        ("[sweep]\nstep_mm = 0", "sweep.step_mm", "must be greater than 0, got 0"),
        ("[sweep]\nmax_frames = -1", "sweep.max_frames", "must be greater than 0"),
        (
            "[optics]\nmla_focal_mm = -2.5",
            "optics.mla_focal_mm",
            "must be greater than 0, got -2.5",
        ),
        ("[board]\nsquare_mm = 0", "board.square_mm", "must be greater than 0"),
        (
            "[xy_stage]\nx = { device = 100, axis = 1 }",
            "xy_stage.x.device",
            "less than or equal to 99",
        ),
        ("[xy_stage]\nwhite = { x_mm = 1 }", "xy_stage.white.y_mm", "field required"),
        ("[storage]\ndata_dir = 5", "storage.data_dir", "got 5"),
    ],
)
def test_type_and_range_errors(tmp_path: Path, toml: str, key: str, reason: str) -> None:
    text = (
        toml
        + "\n"
        + (MINIMAL if not toml.startswith("[rail]") else "zero_object_distance_mm = 250.0\n")
    )
    got = keyed(problems_of(write(tmp_path, text)))
    assert key in got, got
    assert reason in got[key], got[key]


def test_missing_required(tmp_path: Path) -> None:
    got = keyed(problems_of(write(tmp_path, "[camera]\n")))
    assert got == {"rail": "field required"}
    got = keyed(problems_of(write(tmp_path, "[rail]\ndriver = 'emulated'\n")))
    assert got == {"rail.zero_object_distance_mm": "field required"}


@pytest.mark.parametrize(
    ("toml", "key", "reason"),
    [
        ("[sweep]\nstart_mm = -5.0", "sweep.start_mm", "-5 is outside the rail limits 0..100 mm"),
        ("[sweep]\nstop_mm = 120.0", "sweep.stop_mm", "120 is outside the rail limits"),
        (
            "[sweep]\nstart_mm = 50.0\nstop_mm = 10.0",
            "sweep.stop_mm",
            "must not be below sweep.start_mm",
        ),
        (
            "[sweep]\nstep_mm = 0.01",
            "sweep.step_mm",
            "gives 9901 frames, more than sweep.max_frames",
        ),
        ("[sweep]\nmax_frames = 50", "sweep.step_mm", "gives 100 frames"),
        ("[rail]\nmin_mm = 60.0\nmax_mm = 40.0", "rail.max_mm", "must exceed rail.min_mm (60)"),
        (
            "[rail]\ndirection = -1\nzero_object_distance_mm = 60.0",
            "rail.zero_object_distance_mm",
            "not beyond the main focal length",
        ),
        ("[rail]\ndriver = 'zaber'", "rail.port", "field required"),
        ("[rail]\nport = '/dev/ttyUSB0'", "rail.port", 'not used with driver = "emulated"'),
        (
            "[camera]\nroi = { width = 1000, height = 1000, offset_x = 4500 }",
            "camera.roi.width",
            "ROI columns 4500..5499 leave the 5120 px wide sensor",
        ),
        (
            "[camera]\nwidth = 800\nheight = 600\nroi = { width = 100, height = 700 }",
            "camera.roi.height",
            "leave the 600 px high sensor",
        ),
        ("[camera]\nbackend = 'harvesters'\naddress = 'cam1'", "camera.cti", "field required"),
        (
            "[camera]\nbackend = 'harvesters'\nserial = 'x'\ncti = 'none.cti'",
            "camera.cti",
            "file not found",
        ),
        ("[camera]\nbackend = 'aravis'", "camera.address", "field required"),
        ("[camera]\naddress = '10.0.0.2'", "camera.address", 'not used with backend = "simulated"'),
        (
            "[camera]\nbackend = 'aravis'\nserial = 'S1'\npreset = 'paper'",
            "camera.preset",
            "only used with",
        ),
        (
            "[camera]\npreset = 'zemax'",
            "camera.preset",
            "unknown preset 'zemax': choose one of noisy, paper",
        ),
        (
            "[camera]\nprincipal_point_px = [6000.0, 10.0]",
            "camera.principal_point_px",
            "is outside the",
        ),
        ("[xy_stage]\nx = { device = 1, axis = 1 }", "xy_stage.x", "is the rail's (same chain)"),
        (
            "[xy_stage]\ny = { device = 2, axis = 1 }",
            "xy_stage.y",
            "same device 2 axis 1 as xy_stage.x",
        ),
        ("[xy_stage]\ndriver = 'zaber'", "xy_stage.port", "field required (the rail is emulated"),
        (
            "[xy_stage]\nalignment = { x_mm = 400.0, y_mm = 0.0 }",
            "xy_stage.alignment.x_mm",
            "400 is outside the x travel 0..300 mm",
        ),
        (
            "[xy_stage]\nx = { device = 2, axis = 1, min_mm = 5.0, max_mm = 5.0 }",
            "xy_stage.x.max_mm",
            "must exceed xy_stage.x.min_mm",
        ),
        (
            "[board]\nreference_gap_mm = 10.0",
            "board.reference_gap_mm",
            "must be smaller than board.square_mm",
        ),
        (
            "[optics]\nmla_pitch_mm = 0.002",
            "optics.mla_pitch_mm",
            "must exceed optics.pixel_pitch_mm",
        ),
        (
            "[optics]\ndesigned_b_mm = 2.0",
            "optics.designed_b_mm",
            "must exceed optics.mla_focal_mm",
        ),
        ("[server]\nhost = '0.0.0.0'", "server.api_keys", "required when server.host (0.0.0.0)"),
        ("[server]\napi_keys = ['short']", "server.api_keys[0]", "API key too short"),
        (f"[server]\napi_keys = ['{KEY_A}', '{KEY_A}']", "server.api_keys[1]", "duplicate API key"),
        (
            "[server]\ncors_origins = ['http://a/b']",
            "server.cors_origins[0]",
            "must be an origin like",
        ),
    ],
)
def test_cross_field_errors(tmp_path: Path, toml: str, key: str, reason: str) -> None:
    if toml.startswith("[rail]"):
        extra = "" if "zero_object_distance_mm" in toml else "zero_object_distance_mm = 250.0"
        text = toml + "\n" + extra + "\n"
    else:
        text = MINIMAL + toml + "\n"
    problems = problems_of(write(tmp_path, text))
    got = keyed(problems)
    assert key in got, got
    assert reason in got[key], got[key]
    assert all(p.file == str(tmp_path / "station.toml") for p in problems)


def test_all_problems_are_reported_at_once(tmp_path: Path) -> None:
    text = """
[camera]
backend = "aravis"
exposure = 1000             # unknown key
gain = "3"                  # wrong type
roi = { width = 6000, height = 100 }

[rail]
driver = "zaber"            # but no port
min_mm = 10.0
max_mm = 5.0
zero_object_distance_mm = -3.0
direction = 2

[sweep]
step_mm = 0.01

[server]
port = 0
"""
    path = write(tmp_path, text, "lab.toml")
    with pytest.raises(ConfigError) as err:
        load_config(path, env={})
    got = keyed(err.value.problems)
    assert set(got) == {
        "camera.exposure",
        "camera.gain",
        "camera.address",
        "camera.roi.width",
        "rail.port",
        "rail.max_mm",
        "rail.zero_object_distance_mm",
        "rail.direction",
        "sweep.step_mm",
        "server.port",
    }
    lines = err.value.format_problems()
    assert len(lines) == len(got)
    assert f"{path}: rail.port: field required" in "\n".join(lines)
    assert str(err.value) == "\n".join(lines)


def test_invalid_value_does_not_cause_follow_up_problems(tmp_path: Path) -> None:
    # the invalid width must not be replaced by the default in the ROI check
    text = MINIMAL + "[camera]\nwidth = 'wide'\nroi = { width = 6000, height = 10 }\n"
    got = keyed(problems_of(write(tmp_path, text)))
    assert set(got) == {"camera.width"}


# ------------------------------------------------------------------ environment


def test_env_api_keys_join_the_file_keys(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + f"[server]\napi_keys = ['{KEY_A}']\n")
    cfg = load_config(path, env={"LFCAL_API_KEYS": f"{KEY_B}, {KEY_A}"})
    assert cfg.server.api_keys == [KEY_A, KEY_B]
    assert load_config(path, env={}).server.api_keys == [KEY_A]
    assert KEY_A not in repr(cfg)


def test_env_api_keys_satisfy_a_public_host(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + "[server]\nhost = '0.0.0.0'\n")
    assert problems_of(path)[0].key == "server.api_keys"
    cfg = load_config(path, env={"LFCAL_API_KEYS": f"{KEY_A} {KEY_B}"})
    assert cfg.server.api_keys == [KEY_A, KEY_B]


def test_bad_env_api_key_is_reported_as_environment(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL)
    (p,) = problems_of(path, env={"LFCAL_API_KEYS": f"{KEY_A},tiny"})
    assert (p.file, p.key) == ("environment", "LFCAL_API_KEYS[1]")
    assert "too short" in p.reason


def test_process_environment_is_read_by_default(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("LFCAL_API_KEYS", KEY_B)
    assert load_config(write(tmp_path, MINIMAL)).server.api_keys == [KEY_B]


# ------------------------------------------------------------------ paths


def test_relative_paths_resolve_against_the_config_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    conf_dir = tmp_path / "etc" / "lfcal"
    conf_dir.mkdir(parents=True)
    (conf_dir / "producer.cti").write_bytes(b"")
    text = (
        MINIMAL
        + "[camera]\nbackend = 'harvesters'\nserial = 'S1'\ncti = 'producer.cti'\n"
        + "[storage]\ndata_dir = '../../data'\ndatabase = '/srv/lfcal/db.sqlite3'\n"
    )
    path = write(conf_dir, text)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    cfg = load_config(Path("..") / "etc" / "lfcal" / "station.toml", env={})
    assert cfg.storage.data_dir == tmp_path / "data"
    assert cfg.storage.database == Path("/srv/lfcal/db.sqlite3")
    assert cfg.camera.cti == conf_dir / "producer.cti"
    assert path.is_file()


def test_home_directory_is_expanded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    cfg = load_config(write(tmp_path, MINIMAL + "[storage]\ndata_dir = '~/lfcal'\n"), env={})
    assert cfg.storage.data_dir == tmp_path / "home" / "lfcal"


# ------------------------------------------------------------------ models in code


def test_models_built_in_code_are_cross_checked() -> None:
    rail = RailConfig(zero_object_distance_mm=250.0)
    cfg = StationConfig(rail=rail)
    assert cfg.source is None and cfg.sweep.frame_count == 100
    with pytest.raises(ValidationError, match="sweep.stop_mm: 150 is outside the rail limits"):
        StationConfig.model_validate(
            {"rail": {"zero_object_distance_mm": 250.0}, "sweep": {"stop_mm": 150.0}}
        )
