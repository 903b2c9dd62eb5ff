"""The `lfcal` command wiring: every subcommand reachable, errors as one line and exit code 2."""

from __future__ import annotations

from pathlib import Path

import pytest

from station.cli import build_parser, main


def test_subcommands_are_registered() -> None:
    choices = build_parser()._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    assert {
        "simulate",
        "calibrate",
        "config",
        "devices",
        "emulate-stage",
        "demo",
        "sweep",
        "jobs",
    } <= set(choices)


def test_devices_with_a_missing_config(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices", "--config", "/nonexistent/station.toml"]) == 2
    assert "file not found" in capsys.readouterr().err


def test_config_check_reports_file_key_and_reason(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[rail]\ndriver = "zaber"\nspeed = 3\n')
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "rail" in err


def test_shipped_configs_pass_the_check(capsys: pytest.CaptureFixture[str]) -> None:
    root = Path(__file__).resolve().parents[1]
    for name in ("simulated.toml", "lab-example.toml"):
        assert main(["config", "check", str(root / "config" / name)]) == 0
    assert capsys.readouterr().out.count("OK") == 2


def test_sweep_and_jobs_are_reachable(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["jobs", "--db", str(tmp_path / "none.sqlite")]) == 2
    assert "no job database" in capsys.readouterr().err
    assert not (tmp_path / "none.sqlite").exists()  # listing never creates a database
    assert main(["sweep", "--config", "/nonexistent/station.toml"]) == 2
    assert "file not found" in capsys.readouterr().err


def test_sweep_with_a_vanishing_step_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = Path(__file__).resolve().parents[1]
    text = (root / "config" / "simulated.toml").read_text()
    text = text.replace('data_dir = "../data"', f'data_dir = "{tmp_path}"')
    text = text.replace('database = "../data/lfcal.sqlite3"', f'database = "{tmp_path}/db.sqlite3"')
    config = tmp_path / "station.toml"
    config.write_text(text)
    code = main(["sweep", "--config", str(config), "--step", "1e-320"])
    assert code == 2
    assert "at most 2000" in capsys.readouterr().err
    assert not (root / "data").exists()


@pytest.mark.parametrize(
    ("argv", "command"),
    [
        (["sweep", "--config"], "lfcal sweep"),
        (["jobs", "--config"], "lfcal jobs"),
        (["recalibrate", "--all", "--config"], "lfcal recalibrate"),
        (["serve", "--config"], "lfcal serve"),
    ],
)
def test_every_command_names_a_broken_config_and_its_problems(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], command: str
) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[rail]\ndriver = "zaber"\nspeed = 3\n')
    assert main([*argv, str(bad)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == f"{command}: {bad}: invalid configuration"
    assert len(lines) > 1 and all(line.startswith("  ") for line in lines[1:])
    assert any("rail" in line for line in lines[1:])
