"""Sweep request validation, the retry policy table and the frame sanity check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_station_helpers import write_config

from drivers.camera_errors import CameraLost, CameraTimeout, IncompleteFrame, InvalidSetting
from drivers.errors import (
    ChecksumError,
    ConnectionLost,
    LimitHit,
    MotionTimeout,
    NoReply,
    NotReferenced,
    PositionMismatch,
    StageStalled,
)
from station.config import StationConfig, load_config
from station.faults import Action, FrameRejected, check_frame, rule_for
from station.sweep import HARD_MAX_FRAMES, RequestInvalid, frame_count, plan_sweep


@pytest.fixture
def config(tmp_path: Path) -> StationConfig:
    return load_config(write_config(tmp_path))


def test_defaults_come_from_the_configuration(config: StationConfig) -> None:
    plan = plan_sweep(None, config)
    assert (plan.start_mm, plan.stop_mm, plan.step_mm, plan.frames) == (0.0, 95.0, 5.0, 20)
    assert plan.exposure_us == config.camera.exposure_us and plan.settle_s == 0.0
    assert plan.positions_mm()[:3] == [0.0, 5.0, 10.0] and plan.positions_mm()[-1] == 95.0
    assert plan_sweep({"step_mm": 1.0}, config).frames == 96
    assert frame_count(0, 99, 1) == 100 and frame_count(0, 0.3, 0.1) == 4


def test_every_problem_is_reported_with_its_field(config: StationConfig) -> None:
    with pytest.raises(RequestInvalid) as info:
        plan_sweep(
            {"start_mm": 101, "stop_mm": -1, "step_mm": -2, "exposure_us": 5, "settle_s": 99},
            config,
            exposure_limits_us=(10.0, 1e6),
        )
    fields = [f for f, _ in info.value.problems]
    assert fields == ["start_mm", "stop_mm", "step_mm", "stop_mm", "exposure_us", "settle_s"]
    limits = dict(info.value.problems)
    assert limits["exposure_us"] == ("5 µs is outside the camera's exposure range [10, 1e+06] µs")
    # the device's travel narrows the configured one
    with pytest.raises(RequestInvalid, match=r"outside the rail's travel \[0, 80\] mm"):
        plan_sweep({"stop_mm": 90}, config, rail_limits_mm=(0.0, 80.0))


def test_frame_limit_and_bad_json(config: StationConfig) -> None:
    with pytest.raises(RequestInvalid, match=f"at most {HARD_MAX_FRAMES}.*at least 0.047524 mm"):
        plan_sweep({"start_mm": 0, "stop_mm": 95, "step_mm": 0.001}, config)
    for bad in ({"step_mm": float("nan")}, {"stop_mm": "far"}, {"calibrate": "maybe"}):
        with pytest.raises(RequestInvalid) as info:
            plan_sweep(bad, config)
        assert info.value.problems[0][0] == next(iter(bad))
    with pytest.raises(RequestInvalid, match="must be a JSON object"):
        plan_sweep([1, 2], config)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("error", "action", "extra"),
    [
        (NoReply("x"), Action.RETRY, 1),
        (ChecksumError("x"), Action.RETRY, 2),
        (ConnectionLost("x"), Action.FAIL, 0),
        (NotReferenced("x"), Action.REHOME, 1),
        (StageStalled("x"), Action.FAIL, 0),
        (LimitHit("x"), Action.FAIL, 0),
        (MotionTimeout("x"), Action.RETRY, 1),
        (PositionMismatch("x", target_mm=1, actual_mm=2, tolerance_mm=0.001), Action.RETRY, 1),
        (CameraTimeout("x"), Action.RETRY, 2),
        (IncompleteFrame("x", status="missing-packets"), Action.RETRY, 2),
        (CameraLost("x"), Action.RECONNECT, 1),
        (InvalidSetting("x"), Action.FAIL, 0),
        (FrameRejected("x", kind="blank"), Action.RETRY, 1),
    ],
)
def test_retry_policy(error: Exception, action: Action, extra: int) -> None:
    rule = rule_for(error)
    assert (rule.action, rule.extra_attempts) == (action, extra)


def test_frame_sanity_check() -> None:
    rng = np.random.default_rng(0)
    good = rng.integers(10, 3500, (400, 600), dtype=np.uint16)
    assert check_frame(good, 12, what="frame 0").saturated_fraction == 0
    with pytest.raises(FrameRejected, match="frame 3 at 5.000 mm is blank"):
        check_frame(np.full((400, 600), 8, np.uint16), 12, what="frame 3 at 5.000 mm")
    hot = good.copy()
    hot[:40] = 4095
    with pytest.raises(FrameRejected, match=r"saturated: 10\.0 % of its pixels"):
        check_frame(hot, 12, what="frame")


def test_sweep_cli_lists_every_problem_and_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from station.jobs_cli import sweep_main

    cfg = write_config(tmp_path)
    args = ["--config", str(cfg), "--start", "50", "--stop", "10", "--step", "0"]
    assert sweep_main([*args, "--emulator-speedup", "50"]) == 2
    err = capsys.readouterr().err
    assert "step_mm: must be greater than 0 mm" in err
    assert "stop_mm: must not be below start_mm (50 mm), got 10 mm" in err
    assert sweep_main(["--config", str(tmp_path / "missing.toml")]) == 2
