"""``python -m web.demo``: a calibration over HTTP from start to finish, printed."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_web_support import frame_cache, write_config

from web.demo import demo_main


def test_the_http_demo_calibrates_and_prints_the_result(
    tmp_path: Path,
    pytestconfig: pytest.Config,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv("LFCAL_API_KEYS", raising=False)  # the demo makes a one-time key
    config = write_config(tmp_path)
    code = demo_main(
        [
            "--config",
            str(config),
            "--emulator-speedup",
            "20",
            "--sim-frame-cache",
            str(frame_cache(pytestconfig)),
            "--timeout",
            "180",
        ]
    )
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "calibrated over HTTP" in out
    for name in ("a (mm)", "b (mm)", "Q = b/a", "p (px)", "focus plane u (mm)"):
        line = next(line for line in out.splitlines() if name in line)
        assert "±" in line and "n/a" not in line, line
    assert "10/10 frames" in err


def test_the_http_demo_reports_a_bad_sweep(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_config(tmp_path)
    code = demo_main(["--config", str(config), "--start", "60", "--stop", "40"])
    assert code == 2
    assert "stop_mm" in capsys.readouterr().err
