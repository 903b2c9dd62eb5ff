"""The README's main command: a calibration over HTTP on the simulated station, end to end."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from station.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_demo_calibrates_over_http(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    code = main(
        [
            "demo",
            "--config",
            str(ROOT / "config" / "simulated.toml"),
            "--out",
            str(out),
            "--frames",
            "8",
            "--emulator-speedup",
            "50",
        ]
    )
    printed = capsys.readouterr().out
    assert code == 0, printed
    assert "server up at http://127.0.0.1:" in printed
    for label in ("a (mm)", "b (mm)", "Q = b/a", "patch size p (px)", "focus plane u (mm)"):
        assert label in printed
    result = json.loads((out / "result.json").read_text())
    # the paper preset: a = 15, b = 3, focus at u = 300 mm; 8 frames only, so twice the test bounds
    assert abs(result["a_mm"] / 15.0 - 1) < 2e-3
    assert abs(result["b_mm"] / 3.0 - 1) < 2e-3
    assert abs(result["focus"]["object_distance_mm"] - 300.0) < 4.0
    # the job's archive and database are under the demo's output directory
    assert list((out / "data").glob("job-*/sweep.json"))
    assert (out / "data" / "lfcal.sqlite3").is_file()
